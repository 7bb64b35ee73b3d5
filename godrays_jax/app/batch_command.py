"""`godrays-jax batch`: a sequence of frames through one effect, on this host's share of the frames."""

import re
import sys

import jax

from godrays_jax.app.options import (
    NO_SKY,
    effect_for_frame,
    effect_option,
    frame_reading,
    resolve_light_depth,
    split_lights,
    warn,
    warn_of_stored_lights,
    with_frame_camera,
)
from godrays_jax.effects.lights import check_lights_add
from godrays_jax.pipeline.batch import BatchError, describe_plan, plan_batch, run_batch
from godrays_jax.pipeline.sequences import (
    METADATA,
    LightSource,
    expand_frames,
    maps_by_frame,
    read_light_track,
)
from godrays_jax.primitives.frame_reading import read_buffers
from godrays_jax.primitives.light_metadata import read_light_depth


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


def _other_light_depth(inputs: list[str], first: float) -> tuple[str, float] | None:
    """The first frame whose stored light distance differs from `first` (headers only), or None."""
    for path in inputs[1:]:
        try:
            depth = read_light_depth(path)
        except (OSError, ValueError):
            continue  # an unreadable frame is reported when the run reaches it
        if depth is not None and depth != first:
            return path, depth
    return None


def run(args) -> int:
    """`godrays-jax batch` (arguments from `cli`): plan, then run or list the frames; exit status 1 if any frame failed."""
    light: LightSource = METADATA
    if args.light_track is not None:
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
        # Left here, at its frames' end, not at the interpreter's exit, where JAX leaves only after it has dropped
        # its backends: every process waits at the shutdown barrier until the last has written its share, so that
        # process 0, which holds the coordination service, takes it down only when no other process needs it.
        try:
            return _run_share(args, light, (jax.process_index(), jax.process_count()))
        finally:
            jax.distributed.shutdown()
    return _run_share(args, light, shard)


def _run_share(args, light: LightSource, shard: tuple[int, int] | None) -> int:
    """`run` past the cluster: the frames of `shard` (this process's share, or every frame where None)."""
    effect = effect_option(args.preset, args.params)
    inputs = expand_frames(args.pattern)
    # The camera and the light's distance come from the first frame: one compiled program for the shot.
    effect = with_frame_camera(effect, args, inputs[0])
    first, light_depth, light_tint, beside = split_lights(
        args.light, args.light_depth, args.light_tint, lambda: resolve_light_depth(None, inputs[0]),
        layer_only=args.layer_only,
    )
    if beside or light_tint is not None:
        check_lights_add(effect)  # before any folder or frame (`frames_function` refuses it too)
    if first is not None:
        light = first
    if args.light is None and args.light_track is None:
        warn_of_stored_lights("batch", inputs[0], hint=(
            ", and batch with --light 'X,Y;X,Y' (--light-depth, --light-tint)"
        ))
    if args.light_depth is None and (moved := _other_light_depth(inputs, light_depth)) is not None:
        warn("batch", f"{moved[0]} stores the light's distance {moved[1]:g}, the first frame {light_depth:g}: every "
             "frame takes the first frame's (one compiled program); pass --light-depth D to choose")  # fmt: skip
    if effect.reads_light_pass:
        effect = effect_for_frame("batch", effect, read_buffers(inputs[0], **frame_reading(args)), inputs[0])
    jobs = plan_batch(
        inputs,
        args.output,
        ext=args.ext,
        resume=args.resume,
        overwrite=args.overwrite,
        frames=parse_frame_range(args.frames) if args.frames else None,
        shard=shard,
    )
    light_views = None
    if args.light_view is not None:
        try:
            light_views = maps_by_frame([job.input for job in jobs if not job.done], args.light_view)
        except ValueError as error:
            raise BatchError(f"--light-view: {error}") from None
    if args.dry_run:
        print("\n".join(describe_plan(jobs, light)))
        if light_views:
            maps = sorted(set(light_views.values()))
            print(f"light-view maps: {maps[0]}" if len(maps) == 1 else f"light-view maps: {len(maps)} files, one a frame")
        for light_beside in beside:
            x, y = (float(value) for value in light_beside.xy)
            side = "" if light_beside.in_front else ", behind the camera"
            print(f"every frame also lit by the light at ({x:g}, {y:g}){side}, distance {float(light_beside.depth):g}")
        todo = sum(not job.done for job in jobs)
        print(f"{todo} frame(s) to run, {len(jobs) - todo} done, on {len(jax.local_devices())} device(s); nothing written")
        return 0
    report = run_batch(
        jobs,
        effect,
        light,
        layer_only=args.layer_only,
        light_depth=light_depth,
        light_tint=light_tint,
        beside=beside,
        light_views=light_views,
        dither=not args.no_dither,
        **{key: value for key, value in frame_reading(args).items() if key != "without_depth"},  # run_batch reads both
        progress=None if args.quiet else sys.stderr,
    )
    if report.without_sky:
        count = len(report.without_sky)
        warn("batch", f"{count} frame(s) (first: {report.without_sky[0]}) have {NO_SKY}")
    print(report.summary(), file=sys.stderr if report.failures else sys.stdout)
    return 1 if report.failures else 0


