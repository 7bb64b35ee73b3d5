"""Frame sequences as render pipelines name them, and the light's position per frame (fixed, metadata or a track).

Not fileseq (3.4): its `findSequenceOnDisk` ignores a range in the pattern (`shot.1001-1002#.exr` gives 1001-1003),
finds nothing under a folder with glob characters (`b[1]/shot.####.exr`), takes `shot.7.exr` for `shot.####.exr`
(padding here is a minimum), and reads `#` as 4 digits each or 1 each, never both (Nuke's `####`, oiiotool's `#`).
"""

import bisect
import csv
import glob
import json
import math
import os
import re
from collections.abc import Mapping, Sequence

from godrays_jax.primitives.checks import check_light
from godrays_jax.primitives.light_metadata import read_light

ScreenLight = tuple[tuple[float, float], bool]
"""A light for one frame: `((x, y) pixels, in front of the camera)`."""


METADATA = "metadata"
"""`light=METADATA`: each frame's light from its `godrays:light_px` attribute."""


_FRAME_TOKEN = re.compile(
    r"(?:(?P<first>-?\d+)-(?P<last>-?\d+)(?:x(?P<step>\d+))?(?=[#@]))?"
    r"(?:(?P<hashes>#+)|(?P<ats>@+)|%(?P<printf>0?\d*)d|\$\{?F(?P<houdini>\d*)\}?)"
)
"""One frame token, optionally preceded by an oiiotool range: `1001-1100#`, `@@@`, `%04d`, `$F4`, `${F4}`."""


_GLOB_CHARS = re.compile(r"[*?\[]")


_LAST_NUMBER = re.compile(r"((?:(?<![A-Za-z0-9])-)?\d+)(?!.*\d)")
"""The last run of digits, with the minus sign before it unless a letter or digit comes before that (`shot.-001`
is -1, `shot-0001` is 1)."""


FRAME_PATTERN_HELP = (
    "frames: 'shot.####.exr' (one digit per #, as Nuke writes it), oiiotool's 'shot.#.exr' (a lone # is 4 digits) "
    "and 'shot.@@@@.exr' (one digit per @), 'shot.%04d.exr', Houdini's 'shot.$F4.exr', a range before # or @ "
    "('shot.1001-1100#.exr', 'shot.1-99x2@@.exr'), a glob ('renders/*.exr') or one file. A padded number has at "
    "least that many digits; frame numbers that need more are written unpadded."
)
"""What `expand_frames` accepts, for the command line's help."""


def frame_number(path: str) -> int | None:
    """The frame number of a file: the last run of digits in its name (`shot.1042.exr` -> 1042).

    Negative where a minus sign comes right before the digits and follows a
    separator or the start of the name (`shot.-001.exr` -> -1, as printf's
    `%04d` pads -1), not where it follows a letter or digit (`shot-0001.exr`
    -> 1).
    """
    match = _LAST_NUMBER.search(os.path.splitext(os.path.basename(path))[0])
    return int(match.group(1)) if match else None


def _natural_key(path: str):
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path)], path


def _token_width(token: re.Match) -> int:
    """Digits of padding a frame token asks for; 0 for an unpadded number."""
    if token["hashes"]:
        # oiiotool reads each # as 4 digits; a run of them is Nuke's and Maya's one digit per #.
        return 4 if len(token["hashes"]) == 1 else len(token["hashes"])
    if token["ats"]:
        return len(token["ats"])
    if token["printf"] is not None:
        return int(token["printf"] or 0)
    return int(token["houdini"] or 0)


def _number_regex(width: int) -> str:
    if width <= 1:
        return r"(-?(?:0|[1-9]\d*))" if width == 0 else r"(-?\d+)"
    # Padded as printf's `%0<width>d` pads (the sign counts: -2 is `-002`); a larger number is written as it is.
    digits = rf"\d{{{width}}}|[1-9]\d{{{width},}}"
    negative = rf"\d{{{width - 1}}}|[1-9]\d{{{width - 1},}}"
    return rf"((?:{digits})|-(?:{negative}))"


def _expand_frame_pattern(pattern: str, token: re.Match) -> list[str]:
    before, after = pattern[: token.start()], pattern[token.end() :]
    if _FRAME_TOKEN.search(after):
        raise ValueError(f"frame pattern {pattern!r} has more than one frame token")
    width = _token_width(token)
    matcher = re.compile(re.escape(before) + _number_regex(width) + re.escape(after))
    numbered = []
    for path in glob.glob(glob.escape(before) + "*" + glob.escape(after)):
        match = matcher.fullmatch(path)
        if match and os.path.isfile(path):
            numbered.append((int(match.group(1)), path))
    if token["first"] is not None:
        first, last, step = int(token["first"]), int(token["last"]), int(token["step"] or 1)
        if last < first or step < 1:
            raise ValueError(f"frame range {first}-{last}x{step} in {pattern!r} is empty")
        numbered = [(n, path) for n, path in numbered if first <= n <= last and (n - first) % step == 0]
    if not numbered:
        digits = f"a frame number of at least {width} digits" if width > 1 else "a frame number"
        raise ValueError(
            f"no frames match {pattern!r} (looked for {before}<{digits}>{after}; a lone # is 4 digits, "
            "#### or @@@@ one digit each)"
        )
    return [path for _, path in sorted(numbered)]


def expand_frames(pattern: str) -> list[str]:
    """The files a pattern names, in frame order.

    `pattern` is one of (`FRAME_PATTERN_HELP`):

    - a frame pattern with one frame token: `####` (one digit per `#`, as
      Nuke writes it; a lone `#` is oiiotool's 4 digits), `@@@@` (one digit
      per `@`, oiiotool), printf `%04d` / `%d`, Houdini `$F4` / `${F4}` /
      `$F` (unpadded). Padded tokens match numbers with at least that many
      digits (a frame past the padding is written unpadded, as these tools
      do) and negative frames. A `#` or `@` token may follow an oiiotool
      range, `FIRST-LAST` or `FIRST-LASTxSTEP` (`shot.1001-1100#.exr`):
      only those frames that exist are taken.
    - a glob (`renders/*.exr`), files sorted by name with numbers compared
      as numbers;
    - one existing file (even if its name holds `#` or `@`).

    Frame patterns are sorted by frame number.

    Raises:
        ValueError: nothing matches (the message says how the pattern was
            read), or a pattern with two frame tokens or an empty range.
    """
    if os.path.isfile(pattern):
        return [pattern]
    if (token := _FRAME_TOKEN.search(pattern)) is not None:
        return _expand_frame_pattern(pattern, token)
    glob_pattern = pattern if _GLOB_CHARS.search(pattern) else glob.escape(pattern)
    paths = sorted((p for p in glob.glob(glob_pattern) if os.path.isfile(p)), key=_natural_key)
    if not paths:
        raise ValueError(f"no frames match {pattern!r}")
    return paths


def maps_by_frame(frames: Sequence[str], pattern: str) -> dict[str, str]:
    """The file of `pattern` (an `expand_frames` pattern) that goes with each of `frames`: the same one for every
    frame where the pattern names one file (a camera that does not move), else the one with the frame's number
    (`frame_number`), as a sequence of depth maps seen from the light is rendered beside the frames.

    Raises:
        ValueError: the pattern matches nothing, two of its files have the same number, or a frame has no number
            or no file with its number (the message names the first).
    """
    files = expand_frames(pattern)
    if len(files) == 1 and os.path.isfile(pattern):
        return {frame: files[0] for frame in frames}
    numbered: dict[int | None, str] = {}
    for path in files:
        if (number := frame_number(path)) in numbered:
            raise ValueError(f"{numbered[number]} and {path} in {pattern!r} have the same frame number")
        numbered[number] = path
    chosen = {}
    for frame in frames:
        number = frame_number(frame)
        if number is None or number not in numbered:
            missing = "has no frame number" if number is None else f"is frame {number}, which {pattern!r} lacks"
            raise ValueError(f"{frame} {missing} ({len(numbered)} file(s) match it)")
        chosen[frame] = numbered[number]
    return chosen


def read_light_track(path: str | os.PathLike) -> dict[int, ScreenLight]:
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
    track: dict[int, ScreenLight] = {}
    for frame, x, y, in_front in entries:
        try:
            number, x, y = int(frame), float(x), float(y)
        except (TypeError, ValueError):
            raise ValueError(f"light track {path}: entry ({frame!r}, {x!r}, {y!r}) must be an integer frame and two numbers") from None
        if not (math.isfinite(x) and math.isfinite(y)):
            raise ValueError(f"light track {path}: frame {number} has a non-finite position ({x}, {y})")
        x, y = check_light((x, y))  # as the library bounds a far light, before a float32 cast could overflow
        track[number] = ((float(x), float(y)), _parse_bool(in_front, path, number))
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


LightSource = tuple[float, float] | ScreenLight | str | Mapping[int, ScreenLight]
"""Where each frame's light comes from: a fixed `(x, y)` in front of the camera or a fixed `ScreenLight`, `METADATA`, or a
track `{frame: ScreenLight}`."""


def light_for(path: str, light: LightSource) -> ScreenLight:
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
    if isinstance(light[0], (tuple, list)):  # a `ScreenLight`: the position and its side
        (x, y), in_front = light
        return (float(x), float(y)), bool(in_front)
    x, y = light
    return (float(x), float(y)), True


def _track_light(track: Mapping[int, ScreenLight], number: int) -> ScreenLight:
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


