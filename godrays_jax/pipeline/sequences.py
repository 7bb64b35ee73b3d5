"""Frame sequences as render pipelines name them, and the light's position per frame (fixed, metadata or a track)."""

import bisect
import csv
import glob
import json
import math
import os
import re
from collections.abc import Mapping, Sequence

from godrays_jax.primitives.io import read_light

Light = tuple[tuple[float, float], bool]
"""A light for one frame: `((x, y) pixels, in front of the camera)`."""


METADATA = "metadata"
"""`light=METADATA`: each frame's light from its `godrays:light_px` attribute."""


_HASHES = re.compile(r"#+")


_PRINTF = re.compile(r"%0?(\d*)d")


_GLOB_CHARS = re.compile(r"[*?\[]")


_LAST_NUMBER = re.compile(r"(\d+)(?!.*\d)")


def frame_number(path: str) -> int | None:
    """The frame number of a file: the last run of digits in its name (`shot.1042.exr` -> 1042)."""
    match = _LAST_NUMBER.search(os.path.splitext(os.path.basename(path))[0])
    return int(match.group(1)) if match else None


def _natural_key(path: str):
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path)], path


def expand_frames(pattern: str) -> list[str]:
    """The files a pattern names, in frame order.

    `pattern` is a frame pattern (`shot.####.exr`: one `#` per digit, or
    printf-style `shot.%04d.exr`), a glob (`renders/*.exr`) or one file name.
    Files are sorted by name with numbers compared as numbers.

    Raises:
        ValueError: nothing matches.
    """
    if _HASHES.search(pattern):
        glob_pattern = _HASHES.sub(lambda m: "[0-9]" * len(m.group(0)), glob.escape(pattern))
    elif _PRINTF.search(pattern):
        glob_pattern = _PRINTF.sub(lambda m: "[0-9]" * int(m.group(1) or 1), glob.escape(pattern))
    elif _GLOB_CHARS.search(pattern):
        glob_pattern = pattern
    else:
        glob_pattern = glob.escape(pattern)
    paths = sorted((p for p in glob.glob(glob_pattern) if os.path.isfile(p)), key=_natural_key)
    if not paths:
        raise ValueError(f"no frames match {pattern!r}")
    return paths


def read_light_track(path: str | os.PathLike) -> dict[int, Light]:
    """A light track: the light's pixel position for each frame number.

    CSV: one row per frame, columns `frame, x, y` and optionally `in_front`
    (1/0, true/false; default true), with or without a header row. JSON:
    `{"1001": [x, y], ...}`, `{"1001": {"x": .., "y": .., "in_front": ..}}`,
    or a list of `{"frame": .., "x": .., "y": .., "in_front": ..}` objects.
    Positions are pixels (x right, y down, pixel centres at `i + 0.5`), finite.
    Keys may be sparse: `light_for` interpolates linearly between the keyed
    frames around a frame (not across a change of `in_front`) and does not
    extrapolate past the first or last key.

    Raises:
        ValueError: the file cannot be parsed, naming the file and the entry.
    """
    path = os.fspath(path)
    with open(path, newline="") as stream:
        text = stream.read()
    entries: list[tuple[object, object, object, object]] = []
    if os.path.splitext(path)[1].lower() == ".json":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as error:
            raise ValueError(f"light track {path} is not valid JSON: {error}") from None
        if isinstance(data, Mapping):
            for key, value in data.items():
                if isinstance(value, Mapping):
                    entries.append((key, value.get("x"), value.get("y"), value.get("in_front", True)))
                elif isinstance(value, Sequence) and len(value) == 2:
                    entries.append((key, value[0], value[1], True))
                else:
                    raise ValueError(f"light track {path}: frame {key!r} must be [x, y] or {{x, y, in_front}}")
        elif isinstance(data, list):
            for value in data:
                if not isinstance(value, Mapping):
                    raise ValueError(f"light track {path}: list entries must be objects with frame, x, y")
                entries.append((value.get("frame"), value.get("x"), value.get("y"), value.get("in_front", True)))
        else:
            raise ValueError(f"light track {path} must hold a JSON object or list")
    else:
        for row in csv.reader(text.splitlines()):
            cells = [cell.strip() for cell in row]
            if not cells or not cells[0] or cells[0].startswith("#"):
                continue
            if cells[0].lower() == "frame":
                continue
            if len(cells) not in (3, 4):
                raise ValueError(f"light track {path}: row {row!r} must be frame, x, y[, in_front]")
            entries.append((cells[0], cells[1], cells[2], cells[3] if len(cells) == 4 else True))
    track: dict[int, Light] = {}
    for frame, x, y, in_front in entries:
        try:
            number, x, y = int(frame), float(x), float(y)
        except (TypeError, ValueError):
            raise ValueError(f"light track {path}: entry ({frame!r}, {x!r}, {y!r}) must be an integer frame and two numbers") from None
        if not (math.isfinite(x) and math.isfinite(y)):
            raise ValueError(f"light track {path}: frame {number} has a non-finite position ({x}, {y})")
        track[number] = ((x, y), _parse_bool(in_front, path, number))
    if not track:
        raise ValueError(f"light track {path} lists no frames")
    return track


def _parse_bool(value: object, path: str, number: int) -> bool:
    if isinstance(value, bool):
        return value
    text = str(value).strip().lower()
    if text in ("1", "true", "yes"):
        return True
    if text in ("0", "false", "no"):
        return False
    raise ValueError(f"light track {path}: frame {number} has in_front {value!r} (use 1/0 or true/false)")


LightSource = tuple[float, float] | str | Mapping[int, Light]
"""Where each frame's light comes from: a fixed `(x, y)`, `METADATA`, or a track `{frame: Light}`."""


def light_for(path: str, light: LightSource) -> Light:
    """The light for one frame from a `LightSource`; `ValueError` if it has none."""
    if isinstance(light, str):
        if light != METADATA:
            raise ValueError(f"light must be (x, y), {METADATA!r} or a track, got {light!r}")
        stored = read_light(path)
        if stored is None:
            raise ValueError("no light position in its metadata (godrays:light_px)")
        return stored
    if isinstance(light, Mapping):
        number = frame_number(path)
        if number is None:
            raise ValueError("no frame number in its name to look up in the light track")
        return _track_light(light, number)
    x, y = light
    return (float(x), float(y)), True


def _track_light(track: Mapping[int, Light], number: int) -> Light:
    """The track's light at frame `number`: its own entry, else linear between the keyed frames around it.

    Positions are interpolated only between two keys on the same side of the
    camera; across a change of `in_front` (the projected position jumps there)
    the nearer key is held, the earlier one on a tie. Frames before the first
    or after the last key have no light: the track does not extrapolate.
    """
    if number in track:
        return track[number]
    keys = sorted(track)
    after = bisect.bisect_left(keys, number)
    if after == 0 or after == len(keys):
        raise ValueError(f"frame {number} is outside the light track (frames {keys[0]}-{keys[-1]})")
    first, last = keys[after - 1], keys[after]
    (start, start_in_front), (end, end_in_front) = track[first], track[last]
    if start_in_front != end_in_front:
        return track[first] if number - first <= last - number else track[last]
    t = (number - first) / (last - first)
    return (start[0] + t * (end[0] - start[0]), start[1] + t * (end[1] - start[1])), start_in_front


