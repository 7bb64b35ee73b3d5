"""Frame sequences in batches, what `godrays-jax batch` runs (the user's guide: docs/pipelines.md, "Batch processing a
shot").

A run is planned (`plan_batch`: the frames, where each output goes, which are done) and run (`run_batch`):
frames are read on threads ahead of the effect and written behind it; the effect is compiled once for the shot
and mapped over groups of one frame per local device, sharded along the frame axis (the last group padded by
repeating a frame). Each frame is claimed before it is read (`files.claim`), so overlapping runs share the
frames, and written atomically (`files.atomic_write`); a frame that cannot be used is skipped and named in
`BatchReport.failures`. Importing this module creates no JAX array, so the command line can still call
`jax.distributed.initialize()` for `--distributed`.
"""

import collections
import concurrent.futures
import dataclasses
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
import tqdm
from jaxtyping import Array, Bool, Float

from godrays_jax.effects.base import Effect, needs_depth
from godrays_jax.effects.lights import Light, check_lights_add, lit_by
from godrays_jax.effects.plates import buffers_without_depth
from godrays_jax.effects.presets import presets_without_depth
from godrays_jax.pipeline import exported
from godrays_jax.pipeline.sequences import LightSource, ScreenLight, frame_number, light_for
from godrays_jax.primitives.buffers import Buffers
from godrays_jax.primitives.checks import error_line
from godrays_jax.primitives.derivatives import values_only
from godrays_jax.primitives.files import Claim, claim, release, remove_stale, temporaries_of
from godrays_jax.primitives.frame_files import FrameFile, read_frame, write_frame_like
from godrays_jax.primitives.frame_reading import SKY_DEPTH, DepthKindOption
from godrays_jax.primitives.image_files import read_header
from godrays_jax.primitives.images import write_image
from godrays_jax.primitives.light_view_files import read_light_view


class BatchError(ValueError):
    """A run that cannot start (no frames, an output that would overwrite an input, ...)."""


@dataclasses.dataclass(frozen=True)
class Job:
    """One frame of a run: its input, its output and whether the output already exists."""

    input: str
    output: str
    done: bool
    overwrite: bool = False


_EXTENSION = re.compile(r"\.?[A-Za-z0-9][A-Za-z0-9_]*")
"""An extension and nothing more (`png`, `.exr`): no path separator, no `..`, no space."""


def output_path(input_path: str, out_dir: str, ext: str | None = None) -> str:
    """`out_dir/<input's name>`, with the extension replaced by `ext` (`"png"` or `".png"`) if given.

    Raises:
        BatchError: `ext` is not an extension alone (letters, digits and `_`
            after an optional dot): no path can leave `out_dir` through it.
    """
    name = os.path.basename(input_path)
    if ext is not None:
        if not _EXTENSION.fullmatch(ext):
            raise BatchError(f"--ext must be an extension such as png or .exr, got {ext!r}")
        name = os.path.splitext(name)[0] + "." + ext.lstrip(".")
    return os.path.join(out_dir, name)


def check_output_folder(out_dir: str) -> None:
    """Refuse an output folder that is a file, or whose path goes through a missing folder (`missing/../out`).

    The folder itself and missing folders above it are created when the run
    starts; a `..` after a missing folder would make the path mean another
    folder once that one is created.

    Raises:
        BatchError: naming the file or the missing folder.
    """
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise BatchError(f"output folder {out_dir} is not a folder")
    parts = out_dir.split(os.sep)
    for index, part in enumerate(parts):
        before = os.sep.join(parts[:index])
        if part == os.pardir and before and not os.path.isdir(before):
            raise BatchError(f"output folder {out_dir} goes through {before}, which does not exist")


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
            shard, no frame left, an `ext` that is not an extension alone,
            or an output folder that `check_output_folder` refuses.
    """
    check_output_folder(out_dir)
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
        if os.path.dirname(os.path.abspath(out)) != os.path.abspath(out_dir):  # a name such as `..`
            raise BatchError(f"{path} would be written outside the output folder {out_dir}")
        real_out = os.path.realpath(out)
        if real_out in inputs_abs or (os.path.exists(out) and os.path.samefile(out, path)):
            raise BatchError(f"refusing to overwrite the input {path}: choose another output folder")
        if real_out in seen:
            raise BatchError(f"{seen[real_out]} and {path} would both be written to {out}")
        seen[real_out] = path
        done = os.path.exists(out)
        if done and not (resume or overwrite):
            existing.append(out)
        jobs.append(Job(input=path, output=out, done=done and resume, overwrite=overwrite))
    if existing:
        raise BatchError(
            f"{len(existing)} output(s) exist already (first: {existing[0]}): pass --resume to skip them "
            f"or --overwrite to replace them"
        )
    return jobs


def remove_stale_temporaries(jobs: Sequence[Job]) -> list[str]:
    """Delete the temporary files that dead runs left beside these jobs' outputs (done or not); returns them.

    A live run's temporaries are kept (`files.is_stale`), and so are its
    claims; lock files nobody holds any more are removed.
    """
    removed = []
    for job in jobs:
        removed += remove_stale(temporaries_of(job.output))
        if job.done:  # a run killed after placing this frame but before letting it go left its lock file
            release(claim(job.output))
    return removed


@dataclasses.dataclass
class BatchReport:
    """What a run did. Times are seconds; thread times are summed over threads.

    `without_sky` lists the frames that have no sky pixel (coverage 1
    everywhere: no depth at or above the sky threshold, no alpha below 1),
    which effects that shine through the sky leave unchanged.
    `compilations` counts how often the effect was compiled during the run:
    1 (every frame shares it; the effect's fields are compiled in as
    constants, so each run compiles once).
    """

    written: list[str] = dataclasses.field(default_factory=list)
    without_sky: list[str] = dataclasses.field(default_factory=list)
    skipped: list[str] = dataclasses.field(default_factory=list)
    held: list[str] = dataclasses.field(default_factory=list)
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
        if self.held:
            lines[0] += f"; {len(self.held)} left to another run (it holds them, or wrote them meanwhile)"
        lines += [f"  failed: {path}: {reason}" for path, reason in self.failures.items()]
        return "\n".join(lines)


@dataclasses.dataclass
class _Loaded:
    job: Job
    buffers: Buffers
    frame_file: FrameFile
    light: ScreenLight


def without_depth_error(name: str, effect: Effect) -> str:
    """Why `effect` cannot run on the frame `name`, which has no depth: one line naming the presets that can."""
    return (
        f"{name} has no depth channel and {type(effect).__name__} measures distance in it; presets that run "
        f"without depth: {', '.join(presets_without_depth())}"
    )


def ready_frame(effect: Effect, buffers: Buffers, light_xy: tuple[float, float], name: str) -> Buffers:
    """The frame as the effect reads it: a frame without depth gets its open sky (`plates.buffers_without_depth`).

    Raises:
        ValueError: the frame has no depth and the effect needs it (`without_depth_error`).
    """
    if buffers.depth is not None:
        return buffers
    if needs_depth(effect):
        raise ValueError(without_depth_error(name, effect))
    return buffers_without_depth(buffers.color, light_xy, alpha=buffers.coverage)


def dither_seed_of(path: str) -> int:
    """The seed of a frame's 8-bit dither: its frame number (0 without one), so each frame's grain differs and repeats."""
    number = frame_number(path)
    return 0 if number is None else number % 2**32


def _load(job: Job, light: LightSource, reading: dict, effect: Effect, light_views: Mapping[str, str]) -> _Loaded:
    buffers, frame_file = read_frame(job.input, **reading)
    if job.input in light_views:
        buffers = dataclasses.replace(buffers, light_view=read_light_view(light_views[job.input]))
    frame_light = light_for(job.input, light)
    return _Loaded(job, ready_frame(effect, buffers, frame_light[0], job.input), frame_file, frame_light)


def _header_size(path: str) -> tuple[int, int] | None:
    try:
        spec = read_header(path)
    except (FileNotFoundError, ValueError):
        return None  # reading the frame reports the error
    return spec.height, spec.width


def _common_size(jobs: Sequence[Job]) -> tuple[int, int] | None:
    """The size most of the frames have (from their headers): the run's size."""
    sizes = collections.Counter(size for job in jobs if (size := _header_size(job.input)) is not None)
    return sizes.most_common(1)[0][0] if sizes else None


def _structure_text(buffers: Buffers) -> str:
    names = [f.name for f in dataclasses.fields(buffers) if getattr(buffers, f.name) is not None]
    return ", ".join(f"{name} ({buffers.light_view.projection})" if name == "light_view" else name for name in names)


def frames_function(
    effect: Effect, *, layer_only: bool = False, light_depth: float = math.inf, light_tint=None,
    beside: Sequence[Light] = (), stored: bool = False, traces: collections.Counter | None = None,
):  # fmt: skip
    """The effect on a group of stacked frames `(G, H, W, ...)`, jitted with the effect's fields as constants.

    `light_depth` is the light's distance (scene units) for every frame of the group (`Effect.layer`).
    `light_tint` (linear RGB; None: 1) is that light's tint (`effects.lights.Light`) and `beside` the lights drawn
    beside it in every frame (`effects.lights.lit_by`, their light added); with either, `layer_only` is refused
    (`ValueError`): a fog's layer under several or tinted lights is not a sum of layers; so is an effect whose
    light does not add (`effects.lights.check_lights_add`), here, before any frame.

    Known at trace time, the fields let kernels specialise (GodRays' disc
    emitter runs its rays only on the window around the light that can hold
    any); one compilation per run and frame size, and one program for every
    run of the same effect and size, found in JAX's persistent compilation
    cache when the command line enables it. `stored`: run it from a program
    traced once and kept by `exported` (keyed by the effect's values too), so
    a later process does not trace it either; for arrays on one device (a
    batch spreads its groups over devices and runs the program as traced).
    `traces`: counts each trace (compilation) under `"frames"` (a run's
    `BatchReport.compilations`). Frames rendered to be written: it takes no
    derivatives (`derivatives.values_only`).
    """

    several = light_tint is not None or len(beside) > 0
    if several and layer_only:
        raise ValueError(
            "layer_only draws one light as the effect has it: a fog's layer under several or tinted lights is not "
            "a sum of layers"
        )
    if several:
        check_lights_add(effect)

    def one_frame(frame: Buffers, light_xy: Float[Array, "2"], visible: Bool[Array, ""]):
        with values_only():
            if several:
                tint = (1.0, 1.0, 1.0) if light_tint is None else light_tint
                own = Light(light_xy, in_front=visible, depth=light_depth, tint=tint)
                return lit_by(effect, frame, [own, *beside])
            call = effect.layer if layer_only else effect
            return call(frame, light_xy, light_in_front=visible, light_depth=light_depth)

    @jax.jit
    def apply(buffers: Buffers, lights: Float[Array, "G 2"], in_front: Bool[Array, " G"]) -> Float[Array, "G H W C"]:
        if traces is not None:
            traces["frames"] += 1
        if lights.shape[0] == 1:
            # A group of one frame (one device): its program without the group's axis, whose batched gathers and
            # loops XLA runs about half as fast on the CPU (benchmarks/README.md, "The fit as users run it").
            return one_frame(jax.tree.map(lambda leaf: leaf[0], buffers), lights[0], in_front[0])[None]
        return jax.vmap(one_frame)(buffers, lights, in_front)

    if not stored:
        return apply
    closed_over = (effect, layer_only, light_depth, light_tint, tuple(beside))
    return lambda *args: exported.call("frames", apply, *args, closed_over=closed_over)


def run_batch(
    jobs: Sequence[Job],
    effect: Effect,
    light: LightSource,
    *,
    layer_only: bool = False,
    light_depth: float = math.inf,
    light_tint=None,
    beside: Sequence[Light] = (),
    depth_channel: str | None = None,
    color_layer: str | None = None,
    sky_depth: float = SKY_DEPTH,
    depth_kind: DepthKindOption = "auto",
    fov_x_deg: float | None = None,
    light_views: Mapping[str, str] | None = None,
    dither: bool = True,
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
        light_depth: the light's distance (scene units, `inf`: at infinity) for every frame.
        light_tint, beside: that light's tint and the lights beside it in every frame (`frames_function`).
        depth_channel, color_layer, sky_depth, depth_kind, fov_x_deg: how
            frames are read (`read_frame`; frames without depth are read too,
            and get their open sky from `plates.buffers_without_depth`).
        light_views: each frame's depth map seen from the light (`read_light_view`), by the frame's path
            (`sequences.maps_by_frame`); a frame not in it has none. Every frame's map must have the first's size
            and projection (one program).
        dither: 8-bit outputs (PNG, JPEG, TIFF through `--ext`) get
            triangular dither seeded by the frame number (`dither_seed_of`).
        devices: devices to spread the frames over (default: `jax.local_devices()`).
        io_threads: threads for reading and, separately, for writing.
        progress: a stream for the progress bar (frames done, frames/s, ETA; None: no bar).

    Returns:
        A `BatchReport`; `failures` maps each frame that was not written to why.
    """
    start = time.perf_counter()
    devices = list(devices) if devices is not None else jax.local_devices()
    todo = [job for job in jobs if not job.done]
    for folder in {os.path.dirname(os.path.abspath(job.output)) for job in todo}:
        os.makedirs(folder, exist_ok=True)
    remove_stale_temporaries(jobs)
    reading = {
        "depth_channel": depth_channel, "color_layer": color_layer, "sky_depth": sky_depth, "depth_kind": depth_kind,
        "fov_x_deg": fov_x_deg, "without_depth": True,
    }  # fmt: skip
    traces = collections.Counter()
    run = _Run(
        report=BatchReport(devices=len(devices), skipped=[job.input for job in jobs if job.done]),
        bar=tqdm.tqdm(total=len(todo), unit="frame", file=progress, disable=progress is None, dynamic_ncols=True),
        apply=frames_function(
            effect, layer_only=layer_only, light_depth=light_depth, light_tint=light_tint, beside=beside,
            traces=traces,
        ),
        sharding=jax.sharding.NamedSharding(jax.sharding.Mesh(np.array(devices), ("frames",)), jax.sharding.PartitionSpec("frames")),
        group_size=len(devices), size=_common_size(todo), dither=dither,
    )  # fmt: skip
    try:
        with (
            concurrent.futures.ThreadPoolExecutor(io_threads, thread_name_prefix="godrays-read") as readers,
            concurrent.futures.ThreadPoolExecutor(io_threads, thread_name_prefix="godrays-write") as writers,
        ):
            run.writers = writers
            reads = _Reads(run, readers, iter(todo), lambda job: _load(job, light, reading, effect, light_views or {}),
                           lookahead=max(2 * run.group_size, io_threads + 1))  # fmt: skip
            try:
                for job, loaded in reads:
                    run.admit(job, loaded)
                run.flush_group()
                run.settle_writes(limit=0)
            except BaseException:
                reads.cancel()
                raise
            finally:
                run.bar.close()
    finally:
        for held in run.claims.values():  # frames an interruption left unfinished (written ones are released)
            release(held)
    run.report.wall_s = time.perf_counter() - start
    run.report.compilations = traces["frames"]
    return run.report


@dataclasses.dataclass
class _Run:
    """A batch's state: its report and progress bar, the frames it holds claims on, the group being gathered for
    the devices, the writes in flight, and the size and passes every frame must share (the first frame's where
    the headers do not say). One thread (the caller's) changes it; the readers and writers only time themselves
    into the report under `lock`."""

    report: BatchReport
    bar: tqdm.tqdm
    apply: object  # `frames_function`'s
    sharding: jax.sharding.NamedSharding
    group_size: int
    size: tuple[int, int] | None
    dither: bool
    writers: concurrent.futures.Executor | None = None
    structure: object = None
    light_view_size: tuple[int, int] | None = None
    claims: dict[str, Claim] = dataclasses.field(default_factory=dict)
    group: list[_Loaded] = dataclasses.field(default_factory=list)
    pending_writes: collections.deque = dataclasses.field(default_factory=collections.deque)
    lock: threading.Lock = dataclasses.field(default_factory=threading.Lock)

    def take(self, job: Job) -> bool:
        """Claim the frame; False (and left to the other run) if another run holds it or placed it meanwhile."""
        held = claim(job.output)
        if held is not None and (job.overwrite or not os.path.exists(job.output)):
            self.claims[job.output] = held
            return True
        release(held)
        self.report.held.append(job.input)
        self.bar.update()
        return False

    def fail(self, job: Job, reason: str) -> None:
        self.report.failures[job.input] = reason
        release(self.claims.pop(job.output, None))
        self.bar.update()

    def admit(self, job: Job, loaded: "_Loaded | BaseException") -> None:
        """A frame read (or its reading's error): refused with its reason, or into the group, which goes to the
        devices when full. Every frame must have the run's size and the first frame's passes (one program)."""
        if isinstance(loaded, BaseException):
            self.fail(job, error_line(loaded))
            return
        frame_size = (loaded.buffers.height, loaded.buffers.width)
        self.size = self.size or frame_size
        if frame_size != self.size:
            self.fail(job, f"wrong size {frame_size[1]}x{frame_size[0]} (the run's frames are {self.size[1]}x{self.size[0]})")
            return
        structure = jax.tree.structure(loaded.buffers)
        if self.structure is None:
            self.structure = structure
        if structure != self.structure:
            self.fail(job, f"different passes ({_structure_text(loaded.buffers)}) than the run's first frame")
            return
        if (view := loaded.buffers.light_view) is not None:
            self.light_view_size = self.light_view_size or view.depth.shape
            if view.depth.shape != self.light_view_size:
                self.fail(job, f"a light-view map of {view.depth.shape[1]}x{view.depth.shape[0]} (the run's first "
                          f"frame's is {self.light_view_size[1]}x{self.light_view_size[0]})")  # fmt: skip
                return
        if np.min(np.asarray(loaded.buffers.coverage)) >= 1.0:
            self.report.without_sky.append(job.input)
        self.group.append(loaded)
        if len(self.group) == self.group_size:
            self.flush_group()

    def flush_group(self) -> None:
        """The group through the effect on the devices (the last frame repeated to fill it), each image to the
        writers; a frame whose image is not finite fails."""
        if not self.group:
            return
        began = time.perf_counter()
        padded = self.group + [self.group[-1]] * (self.group_size - len(self.group))
        stacked = jax.tree.map(lambda *leaves: np.stack(leaves), *(item.buffers for item in padded))
        lights = np.array([item.light[0] for item in padded], np.float32)
        in_front = np.array([item.light[1] for item in padded], bool)
        images = np.asarray(self.apply(*jax.device_put((stacked, lights, in_front), self.sharding)))
        self.report.compute_s += time.perf_counter() - began
        for item, image in zip(self.group, images):
            if not np.all(np.isfinite(image)):
                self.fail(item.job, "the effect produced NaN or infinite values")
                continue
            self.pending_writes.append((item.job, self.writers.submit(self.write, item.job, image, item.frame_file)))
        self.group.clear()
        self.settle_writes(limit=2 * self.group_size)

    def write(self, job: Job, image: np.ndarray, frame_file: FrameFile) -> None:
        """On a writer thread: EXR to EXR keeps every channel and the header; other formats are display-encoded
        colour, 8-bit ones dithered (`dither_seed_of`)."""
        began = time.perf_counter()
        try:
            if all(os.path.splitext(path)[1].lower() == ".exr" for path in (job.output, job.input)):
                write_frame_like(job.output, image, frame_file, replace=job.overwrite)
            else:
                seed = dither_seed_of(job.input) if self.dither else None
                write_image(job.output, image, replace=job.overwrite, dither_seed=seed)
        finally:
            with self.lock:
                self.report.write_s += time.perf_counter() - began

    def settle_writes(self, limit: int) -> None:
        """Wait for the oldest writes until at most `limit` are in flight, recording each as written or failed."""
        while len(self.pending_writes) > limit:
            job, future = self.pending_writes.popleft()
            try:
                future.result()
                self.report.written.append(job.input)
                release(self.claims.pop(job.output, None))
                self.bar.update()
            except Exception as error:
                self.fail(job, error_line(error))


class _Reads:
    """The frames read ahead on the readers, in order: iterating gives `(job, loaded)` (or the reading's error in
    place of `loaded`), each frame claimed (`_Run.take`) before it is read; at most `lookahead` in flight."""

    def __init__(self, run: _Run, readers: concurrent.futures.Executor, queue, load, *, lookahead: int):
        self.run, self.readers, self.queue, self.load, self.lookahead = run, readers, queue, load, lookahead
        self.in_flight: collections.deque = collections.deque()

    def _timed_load(self, job: Job) -> _Loaded:
        began = time.perf_counter()
        try:
            return self.load(job)
        finally:
            with self.run.lock:
                self.run.report.read_s += time.perf_counter() - began

    def __iter__(self):
        while True:
            while len(self.in_flight) < self.lookahead and (job := next(self.queue, None)) is not None:
                if self.run.take(job):
                    self.in_flight.append((job, self.readers.submit(self._timed_load, job)))
            if not self.in_flight:
                return
            job, future = self.in_flight.popleft()
            try:
                yield job, future.result()
            except Exception as error:  # noqa: BLE001 - a frame that cannot be read fails alone (`_Run.admit`)
                yield job, error

    def cancel(self) -> None:
        """Cancel the reads not yet started (an interruption)."""
        for _, future in self.in_flight:
            future.cancel()


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
            where = f"no light: {error_line(error)}"
        lines.append(f"run  {job.input} -> {job.output}  {where}")
    return lines


