"""Batch processing of frame sequences: plan, run, resume; what `godrays-jax batch` runs.

A run is planned first (`plan_batch`: which frames, where each output goes,
which are already done) and then executed (`run_batch`):

- Frames are read on background threads ahead of the computation and written
  on background threads behind it, so the effect, reading and writing overlap.
- Every frame of the run has the same size and passes, so the effect is
  compiled once: frames are processed in groups of one frame per JAX device
  (`jax.local_devices()`), the group's frames stacked, sharded over the
  devices along the frame axis (`jax.sharding.NamedSharding`) and mapped with
  `jax.vmap`; the last group is padded by repeating a frame.
- Each output keeps its input's file name, channels, per-channel formats and
  metadata (`io.write_frame_like`: only `R, G, B` change) unless another
  extension is asked for (then `io.write_image` writes the colour alone).
- Every output is written to a hidden temporary file that is renamed into
  place, so an interrupted run leaves only complete frames; leftover temporary
  files of a killed run are removed when the next run starts. `resume=True`
  skips frames whose output exists.
- A frame that cannot be used (unreadable, a different size or different
  passes than the run's frames, no depth channel, NaN or infinite colour, no
  light, an effect result that is not finite) is reported and skipped; the
  others go on. `BatchReport.failures` names each one with its reason.

Several machines: give each host a share of the frames (`shard=(index,
count)`, CLI `--shard I/N`, or `--distributed`, which calls
`jax.distributed.initialize()` (cluster auto-detection, or `--coordinator`,
`--num-processes`, `--process-id`) and takes the share from
`jax.process_index()` / `jax.process_count()`); each host computes on its own
local devices and writes its own frames into the shared output folder.
Importing `godrays_jax` creates no JAX array, so the backend is still
uninitialised when the CLI calls `jax.distributed.initialize()`.
"""

import bisect
import collections
import concurrent.futures
import csv
import dataclasses
import glob
import json
import math
import os
import re
import sys
import threading
import time
from collections.abc import Mapping, Sequence
from typing import TextIO

import jax
import numpy as np
import OpenImageIO as oiio
from jaxtyping import Array, Bool, Float

from godrays_jax.primitives.buffers import Buffers
from godrays_jax.primitives.files import temporaries_of
from godrays_jax.effects.base import Effect
from godrays_jax.primitives.io import FrameFile, read_frame, read_light, write_frame_like, write_image

Light = tuple[tuple[float, float], bool]
"""A light for one frame: `((x, y) pixels, in front of the camera)`."""

METADATA = "metadata"
"""`light=METADATA`: each frame's light from its `godrays:light_px` attribute."""

_HASHES = re.compile(r"#+")
_PRINTF = re.compile(r"%0?(\d*)d")
_GLOB_CHARS = re.compile(r"[*?\[]")
_LAST_NUMBER = re.compile(r"(\d+)(?!.*\d)")


class BatchError(ValueError):
    """A run that cannot start (no frames, an output that would overwrite an input, ...)."""


# ----------------------------------------------------------------------------- frames


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
        BatchError: nothing matches.
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
        raise BatchError(f"no frames match {pattern!r}")
    return paths


# ----------------------------------------------------------------------------- lights


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


# ----------------------------------------------------------------------------- planning


@dataclasses.dataclass(frozen=True)
class Job:
    """One frame of a run: its input, its output and whether the output already exists."""

    input: str
    output: str
    done: bool


def output_path(input_path: str, out_dir: str, ext: str | None = None) -> str:
    """`out_dir/<input's name>`, with the extension replaced by `ext` (e.g. `".png"`) if given."""
    name = os.path.basename(input_path)
    if ext:
        name = os.path.splitext(name)[0] + (ext if ext.startswith(".") else "." + ext)
    return os.path.join(out_dir, name)


def plan_batch(
    inputs: Sequence[str],
    out_dir: str,
    *,
    ext: str | None = None,
    resume: bool = False,
    overwrite: bool = False,
    frames: tuple[int, int] | None = None,
    shard: tuple[int, int] | None = None,
) -> list[Job]:
    """The jobs of a run, refusing anything that would lose data.

    Args:
        inputs: input files in frame order (from `expand_frames`).
        out_dir: the output folder (need not exist yet).
        ext: output extension; default: each input's own.
        resume: mark frames whose output exists as done (skipped).
        overwrite: replace existing outputs. Without `resume` or `overwrite`
            an existing output is an error.
        frames: keep frame numbers in `[first, last]` (inclusive) only.
        shard: `(index, count)`: keep the `index`-th of `count` contiguous
            shares of the frames (one per host).

    Raises:
        BatchError: an output that is an input, two inputs with the same
            output, existing outputs without `resume`/`overwrite`, a bad
            shard, or no frame left.
    """
    selected = list(inputs)
    if frames is not None:
        first, last = frames
        selected = [p for p in selected if (n := frame_number(p)) is not None and first <= n <= last]
        if not selected:
            raise BatchError(f"no frame numbered {first}-{last} among the {len(inputs)} frames")
    if shard is not None:
        index, count = shard
        if not (count >= 1 and 0 <= index < count):
            raise BatchError(f"shard must be INDEX/COUNT with 0 <= INDEX < COUNT, got {index}/{count}")
        share = math.ceil(len(selected) / count)
        selected = selected[index * share : (index + 1) * share]
    inputs_abs = {os.path.realpath(p) for p in inputs}
    jobs, seen = [], {}
    existing = []
    for path in selected:
        out = output_path(path, out_dir, ext)
        real_out = os.path.realpath(out)
        if real_out in inputs_abs or (os.path.exists(out) and os.path.samefile(out, path)):
            raise BatchError(f"refusing to overwrite the input {path}: choose another output folder")
        if real_out in seen:
            raise BatchError(f"{seen[real_out]} and {path} would both be written to {out}")
        seen[real_out] = path
        done = os.path.exists(out)
        if done and not (resume or overwrite):
            existing.append(out)
        jobs.append(Job(input=path, output=out, done=done and resume))
    if existing:
        raise BatchError(
            f"{len(existing)} output(s) exist already (first: {existing[0]}): pass --resume to skip them "
            f"or --overwrite to replace them"
        )
    return jobs


def remove_stale_temporaries(jobs: Sequence[Job]) -> list[str]:
    """Delete the hidden temporary files a killed run left for these jobs' outputs; returns them."""
    removed = []
    for job in jobs:
        for stale in temporaries_of(job.output):
            os.remove(stale)
            removed.append(stale)
    return removed


# ----------------------------------------------------------------------------- running


@dataclasses.dataclass
class BatchReport:
    """What a run did. Times are seconds; thread times are summed over threads.

    `compilations` counts how often the effect was compiled during the run:
    1 (every frame shares it; the effect's fields are compiled in as
    constants, so each run compiles once).
    """

    written: list[str] = dataclasses.field(default_factory=list)
    skipped: list[str] = dataclasses.field(default_factory=list)
    failures: dict[str, str] = dataclasses.field(default_factory=dict)
    read_s: float = 0.0
    compute_s: float = 0.0
    write_s: float = 0.0
    wall_s: float = 0.0
    compilations: int = 0
    devices: int = 1

    def summary(self) -> str:
        """One paragraph: counts, speed, and each failed frame with its reason."""
        rate = len(self.written) / self.wall_s if self.wall_s > 0 else 0.0
        lines = [
            f"{len(self.written)} written, {len(self.skipped)} skipped (already done), "
            f"{len(self.failures)} failed in {self.wall_s:.1f} s ({rate:.2f} frames/s on {self.devices} device(s))"
        ]
        lines += [f"  failed: {path}: {reason}" for path, reason in self.failures.items()]
        return "\n".join(lines)


class Progress:
    """A progress line on a stream: done/total, frames/s and ETA.

    On a terminal it redraws one line; elsewhere (logs, pipes) it prints a line
    about every 10 % of the run.
    """

    def __init__(self, total: int, stream: TextIO | None = sys.stderr, *, width: int = 24):
        self.total, self.stream, self.width = total, stream, width
        self.done = 0
        self.start = time.perf_counter()
        self.interactive = bool(stream is not None and stream.isatty())
        self._last_printed = 0

    def advance(self, count: int = 1) -> None:
        self.done += count
        if self.stream is None:
            return
        if self.interactive:
            self.stream.write("\r" + self.line())
            self.stream.flush()
        elif self.done == self.total or self.done - self._last_printed >= max(1, self.total // 10):
            self._last_printed = self.done
            self.stream.write(self.line() + "\n")
            self.stream.flush()

    def line(self) -> str:
        elapsed = time.perf_counter() - self.start
        rate = self.done / elapsed if elapsed > 0 else 0.0
        left = (self.total - self.done) / rate if rate > 0 else math.inf
        eta = "--:--" if not math.isfinite(left) else time.strftime("%H:%M:%S", time.gmtime(left))
        filled = self.width * self.done // max(self.total, 1)
        bar = "#" * filled + "." * (self.width - filled)
        return f"[{bar}] {self.done}/{self.total} frames  {rate:.2f} frames/s  ETA {eta}"

    def close(self) -> None:
        if self.stream is not None and self.interactive:
            self.stream.write("\n")
            self.stream.flush()


@dataclasses.dataclass
class _Loaded:
    job: Job
    buffers: Buffers
    frame_file: FrameFile
    light: Light


def _load(job: Job, light: LightSource, depth_channel: str | None) -> _Loaded:
    buffers, frame_file = read_frame(job.input, depth_channel=depth_channel)
    return _Loaded(job, buffers, frame_file, light_for(job.input, light))


def _header_size(path: str) -> tuple[int, int] | None:
    inp = oiio.ImageInput.open(path)
    if inp is None:
        oiio.geterror()  # clear it: reading the frame reports the error
        return None
    try:
        return inp.spec().height, inp.spec().width
    finally:
        inp.close()


def _common_size(jobs: Sequence[Job]) -> tuple[int, int] | None:
    """The size most of the frames have (from their headers): the run's size."""
    sizes = collections.Counter(size for job in jobs if (size := _header_size(job.input)) is not None)
    return sizes.most_common(1)[0][0] if sizes else None


def _structure_text(buffers: Buffers) -> str:
    return ", ".join(f.name for f in dataclasses.fields(buffers) if getattr(buffers, f.name) is not None)


_traces = collections.Counter()
"""How many times a run's effect was traced (compiled): `BatchReport.compilations` reads it."""


def _frames_function(effect: Effect, layer_only: bool):
    """The effect on a group of stacked frames, jitted with the effect's fields as constants.

    Known at trace time, the fields let kernels specialise (GodRays' disc
    emitter runs its rays only on the window around the light that can hold
    any); one compilation per run and frame size.
    """

    def one_frame(frame: Buffers, light_xy: Float[Array, "2"], visible: Bool[Array, ""]):
        call = effect.layer if layer_only else effect
        return call(frame, light_xy, light_in_front=visible)

    @jax.jit
    def apply(buffers: Buffers, lights: Float[Array, "G 2"], in_front: Bool[Array, " G"]) -> Float[Array, "G H W C"]:
        _traces["frames"] += 1
        return jax.vmap(one_frame)(buffers, lights, in_front)

    return apply


def run_batch(
    jobs: Sequence[Job],
    effect: Effect,
    light: LightSource,
    *,
    layer_only: bool = False,
    depth_channel: str | None = None,
    devices: Sequence[jax.Device] | None = None,
    io_threads: int = 2,
    progress: TextIO | None = sys.stderr,
) -> BatchReport:
    """Run the effect over the jobs that are not done; never raises for a bad frame.

    Args:
        jobs: from `plan_batch`; done jobs are skipped. Output folders are
            created if missing.
        effect: the effect, applied with the same parameters to every frame.
        light: each frame's light (`LightSource`).
        layer_only: write the effect alone instead of the composited frame.
        depth_channel: the depth channel's name (default `Z`, `depth.Z`, `depth`).
        devices: devices to spread the frames over (default: `jax.local_devices()`).
        io_threads: threads for reading and, separately, for writing.
        progress: where the progress line goes (None: nowhere).

    Returns:
        A `BatchReport`; `failures` maps each frame that was not written to why.
    """
    start = time.perf_counter()
    devices = list(devices) if devices is not None else jax.local_devices()
    report = BatchReport(devices=len(devices))
    report.skipped = [job.input for job in jobs if job.done]
    todo = [job for job in jobs if not job.done]
    for folder in {os.path.dirname(os.path.abspath(job.output)) for job in todo}:
        os.makedirs(folder, exist_ok=True)
    remove_stale_temporaries(todo)
    bar = Progress(len(todo), progress)

    traces_before = _traces["frames"]
    apply_to_frames = _frames_function(effect, layer_only)
    mesh = jax.sharding.Mesh(np.array(devices), ("frames",))
    frame_sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("frames"))
    group_size = len(devices)
    size = _common_size(todo)
    timing_lock = threading.Lock()

    def timed_load(job):
        began = time.perf_counter()
        try:
            return _load(job, light, depth_channel)
        finally:
            with timing_lock:
                report.read_s += time.perf_counter() - began

    def write(job: Job, image: np.ndarray, frame_file: FrameFile) -> None:
        began = time.perf_counter()
        try:
            if os.path.splitext(job.output)[1].lower() == os.path.splitext(job.input)[1].lower():
                write_frame_like(job.output, image, frame_file)
            else:
                write_image(job.output, image)
        finally:
            with timing_lock:
                report.write_s += time.perf_counter() - began

    structure = None
    group: list[_Loaded] = []
    pending_writes: collections.deque = collections.deque()

    def fail(job: Job, reason: str) -> None:
        report.failures[job.input] = reason
        bar.advance()

    def settle_writes(limit: int) -> None:
        while len(pending_writes) > limit:
            job, future = pending_writes.popleft()
            try:
                future.result()
                report.written.append(job.input)
                bar.advance()
            except Exception as error:
                fail(job, _reason(error))

    def flush_group() -> None:
        if not group:
            return
        began = time.perf_counter()
        padded = group + [group[-1]] * (group_size - len(group))
        stacked = jax.tree.map(lambda *leaves: np.stack(leaves), *(item.buffers for item in padded))
        lights = np.array([item.light[0] for item in padded], np.float32)
        in_front = np.array([item.light[1] for item in padded], bool)
        args = jax.device_put((stacked, lights, in_front), frame_sharding)
        images = np.asarray(apply_to_frames(*args))
        report.compute_s += time.perf_counter() - began
        for item, image in zip(group, images):
            if not np.all(np.isfinite(image)):
                fail(item.job, "the effect produced NaN or infinite values")
                continue
            pending_writes.append((item.job, writers.submit(write, item.job, image, item.frame_file)))
        group.clear()
        settle_writes(limit=2 * group_size)

    with (
        concurrent.futures.ThreadPoolExecutor(io_threads, thread_name_prefix="godrays-read") as readers,
        concurrent.futures.ThreadPoolExecutor(io_threads, thread_name_prefix="godrays-write") as writers,
    ):
        reads: collections.deque = collections.deque()
        queue = iter(todo)
        lookahead = max(2 * group_size, io_threads + 1)
        try:
            while True:
                while len(reads) < lookahead and (job := next(queue, None)) is not None:
                    reads.append((job, readers.submit(timed_load, job)))
                if not reads:
                    break
                job, future = reads.popleft()
                try:
                    loaded = future.result()
                except Exception as error:
                    fail(job, _reason(error))
                    continue
                frame_size = (loaded.buffers.height, loaded.buffers.width)
                size = size or frame_size
                if frame_size != size:
                    fail(job, f"wrong size {frame_size[1]}x{frame_size[0]} (the run's frames are {size[1]}x{size[0]})")
                    continue
                frame_structure = jax.tree.structure(loaded.buffers)
                if structure is None:
                    structure = frame_structure
                elif frame_structure != structure:
                    fail(job, f"different passes ({_structure_text(loaded.buffers)}) than the run's first frame")
                    continue
                group.append(loaded)
                if len(group) == group_size:
                    flush_group()
            flush_group()
            settle_writes(limit=0)
        except BaseException:
            for _, future in reads:
                future.cancel()
            raise
        finally:
            bar.close()
    report.wall_s = time.perf_counter() - start
    report.compilations = _traces["frames"] - traces_before
    return report


def _reason(error: BaseException) -> str:
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    return lines[0] if lines else type(error).__name__


def describe_plan(jobs: Sequence[Job], light: LightSource) -> list[str]:
    """One line per job for `--dry-run`: input -> output, the light, or why it is skipped."""
    lines = []
    for job in jobs:
        if job.done:
            lines.append(f"skip {job.input} (done: {job.output} exists)")
            continue
        try:
            (x, y), in_front = light_for(job.input, light)
            where = f"light ({x:g}, {y:g}){'' if in_front else ' behind the camera'}"
        except (OSError, ValueError) as error:
            where = f"no light: {_reason(error)}"
        lines.append(f"run  {job.input} -> {job.output}  {where}")
    return lines


def parse_frame_range(text: str) -> tuple[int, int]:
    """`"1001-1100"` (inclusive) or `"1042"` -> `(first, last)`."""
    match = re.fullmatch(r"\s*(-?\d+)\s*(?:[-:]\s*(-?\d+)\s*)?", text)
    if not match:
        raise ValueError(f"--frames must be FIRST-LAST (e.g. 1001-1100), got {text!r}")
    first = int(match.group(1))
    last = int(match.group(2)) if match.group(2) is not None else first
    if last < first:
        raise ValueError(f"--frames {text!r}: the last frame comes before the first")
    return first, last


def parse_shard(text: str) -> tuple[int, int]:
    """`"I/N"` -> `(I, N)`: this host's share, 0-based."""
    match = re.fullmatch(r"\s*(\d+)\s*/\s*(\d+)\s*", text)
    if not match:
        raise ValueError(f"--shard must be INDEX/COUNT (e.g. 0/4), got {text!r}")
    return int(match.group(1)), int(match.group(2))


def run_command(args) -> int:
    """`godrays-jax batch`: the CLI handler (arguments from `cli._add_batch`)."""
    from godrays_jax.app.cli import load_effect_option

    light: LightSource = METADATA
    if args.light is not None:
        light = args.light
    elif args.light_track is not None:
        light = read_light_track(args.light_track)
    shard = parse_shard(args.shard) if args.shard else None
    explicit = (args.coordinator, args.num_processes, args.process_id)
    if any(value is not None for value in explicit) and not args.distributed:
        raise BatchError("--coordinator, --num-processes and --process-id need --distributed")
    if args.distributed:
        if shard is not None:
            raise BatchError("give --shard or --distributed, not both")
        if any(value is not None for value in explicit) and None in explicit:
            raise BatchError("give all of --coordinator, --num-processes and --process-id, or none (auto-detection)")
        if args.num_processes is not None and not 0 <= args.process_id < args.num_processes:
            raise BatchError(f"--process-id must be in 0..{args.num_processes - 1}, got {args.process_id}")
        jax.distributed.initialize(
            coordinator_address=args.coordinator, num_processes=args.num_processes, process_id=args.process_id
        )
        shard = (jax.process_index(), jax.process_count())
    effect = load_effect_option(args.preset, args.params)
    inputs = expand_frames(args.pattern)
    jobs = plan_batch(
        inputs,
        args.output,
        ext=args.ext,
        resume=args.resume,
        overwrite=args.overwrite,
        frames=parse_frame_range(args.frames) if args.frames else None,
        shard=shard,
    )
    if args.dry_run:
        print("\n".join(describe_plan(jobs, light)))
        todo = sum(not job.done for job in jobs)
        print(f"{todo} frame(s) to run, {len(jobs) - todo} done, on {len(jax.local_devices())} device(s); nothing written")
        return 0
    report = run_batch(
        jobs,
        effect,
        light,
        layer_only=args.layer_only,
        depth_channel=args.depth_channel,
        progress=None if args.quiet else sys.stderr,
    )
    print(report.summary(), file=sys.stderr if report.failures else sys.stdout)
    return 1 if report.failures else 0
