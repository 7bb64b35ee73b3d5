"""`godrays-jax fit`: fit an effect's parameters to target frames and write them for `apply --params`."""

import contextlib
import dataclasses
import gc
import math
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np
import tqdm

from godrays_jax.app import allocator
from godrays_jax.app.fit_light import (
    first_light,
    found_lights_text,
    light_lines,
    profile_lines,
    seen_lines,
    tried_line,
    write_text,
)
from godrays_jax.app.options import (
    LIGHT_AUTO,
    NO_SKY,
    CommandError,
    auto_coarse_factor,
    check_output_path,
    default_fit_effect,
    effect_for_frame,
    effect_option,
    found_lights_path,
    frame_field_of_view,
    frame_reading,
    has_sky,
    model_presets,
    read_target,
    resolve_light_depth,
    split_lights,
    tints_text,
    warn,
    with_frame_camera,
    with_light_view,
    with_stored_lights,
)
from godrays_jax.effects.fields import field_metadata, field_value
from godrays_jax.effects.lights import Light
from godrays_jax.effects.presets import preset
from godrays_jax.effects.serialization import effect_to_dict, save_effect
from godrays_jax.pipeline.batch import ready_frame
from godrays_jax.pipeline.determination import determination
from godrays_jax.pipeline.fit import fit
from godrays_jax.pipeline.fit_phases import polishes
from godrays_jax.pipeline.frame_start import (
    closed_room_start,
    enclosed_start,
    ground_layer_start,
    thin_slabs_room_start,
    thin_slabs_start,
)
from godrays_jax.pipeline.light_profile import PROFILE_STEP, profile_light
from godrays_jax.pipeline.light_search import LIGHT_REACH, VISIBLE_CHANGE, find_light
from godrays_jax.pipeline.light_seen import DRAWN_SHARE, nearest_seen, seen_lights
from godrays_jax.pipeline.problem import fitted_bounds
from godrays_jax.pipeline.report import fit_report_image, image_metrics
from godrays_jax.primitives.frame_reading import read_buffers
from godrays_jax.primitives.light_metadata import read_light_depth
from godrays_jax.primitives.images import write_image


def run(args) -> int:
    """`godrays-jax fit`: read frames and targets, fit, print progress and results, write params (and a report)."""
    pairs = [(args.buffers, args.target), *[tuple(pair) for pair in args.frames or []]]
    check_output_path(args.output, *[path for pair in pairs for path in pair])
    if args.report:
        check_output_path(args.report, *[path for pair in pairs for path in pair])
    lights = args.light or []
    if lights == [LIGHT_AUTO]:
        lights *= len(pairs)  # `--light auto` once finds every frame's light
    if len(lights) not in (0, len(pairs)):
        raise CommandError(f"give --light once per frame ({len(pairs)} frames) or not at all, got {len(lights)}")
    light_views = args.light_view or [None] * len(pairs)
    if len(light_views) != len(pairs):
        raise CommandError(
            f"give --light-view once per frame ({len(pairs)} frames) or not at all, got {len(light_views)}"
        )
    if args.fit_light or LIGHT_AUTO in lights:
        check_output_path(found_lights_path(args.output), *[path for pair in pairs for path in pair])
    effect = effect_option(args.preset, args.params, default=default_fit_effect)
    fov = frame_field_of_view(args, args.buffers)
    effect = with_frame_camera(effect, args, args.buffers)
    frames, light_positions, in_front, targets, depths, others = [], [], [], [], [], []
    searched = {}  # frame index -> (the frame as read, whether from the target alone) for each light searched for
    # frame path -> (the light found, `LightSearch` or `SeenLight`; the frame as read; its distance; the lights in
    # view drawn beside it)
    found = {}
    for index, (buffers_path, target_path) in enumerate(pairs):
        frame = with_light_view(read_buffers(buffers_path, **frame_reading(args)), light_views[index])
        effect = effect_for_frame("fit", effect, frame, buffers_path)
        target = read_target(target_path)
        if target.shape[:2] != frame.color.shape[:2]:
            raise CommandError(
                f"{target_path} is {target.shape[1]}x{target.shape[0]} but {buffers_path} is {frame.width}x{frame.height}"
            )
        given, depth, beside = _frame_lights(args, lights[index] if lights else None, buffers_path)
        (light, front) = first_light(given, frame, target, buffers_path, fit_light=args.fit_light, space=args.space)
        if given == LIGHT_AUTO or args.fit_light:
            in_view, start = _lights_in_view(frame, effect, fov, buffers_path), None if given == LIGHT_AUTO else light
            seen = in_view[0] if start is None and in_view else None
            if start is not None:  # the light given, where one is in view near it
                seen = nearest_seen(in_view, start, LIGHT_REACH * max(frame.height, frame.width))
            if seen is None:
                searched[index] = (frame, given == LIGHT_AUTO)
            else:  # its own pixels place it: no search, no fits around it
                light, front = tuple(float(v) for v in seen.light_xy), True
                if math.isfinite(seen.depth) and not _light_depth_given(args, buffers_path, header=start is not None):
                    depth = seen.depth
                also = [other for other in in_view if other is not seen]
                drawn = [other for other in also if other.flux >= DRAWN_SHARE * seen.flux] if start is None else []
                # `--light auto`: the bright lights in view drawn beside the first, their tints fitted
                beside = [Light(np.asarray(other.light_xy, np.float32), depth=other.depth) for other in drawn]
                for line in seen_lines(buffers_path, seen, drawn, [o for o in also if o not in drawn], given_xy=start,
                                       depth=depth):  # fmt: skip
                    _say(line)
                found[buffers_path] = (seen, frame, depth, drawn)
        try:
            frame = ready_frame(effect, frame, light, buffers_path)
        except ValueError as error:
            raise CommandError(str(error)) from None
        if not has_sky(frame):
            warn("fit", f"{buffers_path} has {NO_SKY}")
        frames.append(frame)
        light_positions.append(jnp.asarray(light, jnp.float32))
        in_front.append(bool(front))
        depths.append(depth)
        others.append(beside)
        targets.append(target)
    if len({len(beside) for beside in others}) > 1 and LIGHT_AUTO in lights:
        # One tint a light beside the first, shared by every frame: frames with as many lights in view.
        _say("the frames show different numbers of lights in view: each is drawn with its brightest alone")
        others = [[] for _ in others]
        found = {path: (*entry[:3], []) for path, entry in found.items()}
    fixed = tuple(name for name in (args.fixed or "").split(",") if name)
    fit_tints = LIGHT_TINTS not in fixed  # the tints of the lights beside the first: not a field of the effect
    if fit_tints and any(others):  # written beside the parameters, for `apply --params`
        check_output_path(found_lights_path(args.output), *[path for pair in pairs for path in pair])
    fixed = tuple(name for name in fixed if name != LIGHT_TINTS)
    if "fov_x_deg" in effect.CAMERA_FIELDS and "fov_x_deg" not in fixed:
        if fov is not None:
            fixed += ("fov_x_deg",)  # the frame's camera says it: not a parameter to fit
        else:  # its derivatives reach everything, the shadows' table among them (docs/fitting.md)
            warn("fit", f"{args.buffers} carries no field of view, so the fit fits fov_x_deg as well, which takes "
                        "more time and memory; --fov-x-deg gives it")  # fmt: skip
    # Checked before the progress bar is drawn: an error is then the command's one line.
    if args.max_steps < 0:
        raise CommandError(f"--max-steps must be an integer >= 0, got {args.max_steps}")
    try:
        fitted_bounds(effect, fixed=fixed)
    except ValueError as error:
        raise CommandError(f"--fixed: {error}") from None

    coarse_factor = auto_coarse_factor(frames[0].height, frames[0].width) if args.coarse_factor is None else args.coarse_factor
    if coarse_factor < 1:
        raise CommandError(f"--coarse-factor must be an integer >= 1, got {coarse_factor}")
    start_names, starts = fit_starts(effect, frames, fov)
    # In a room read wholly closed the presets' thick slabs shade the beams its windows let in and their far-reaching
    # media fill the windows with lit haze; from them the race keeps a thinned medium, where the room's own start,
    # slower in its first steps, goes much further (benchmarks/README.md, "A sunbeam through a window in view").
    room = closed_room_start(effect, frames, wholly=True) if args.params is None and all(in_front) else None
    if room is not None:
        effect, start_names, starts = room, [], []
        _say("the frames are read as closed beyond their edges (a room, its windows): the fit starts from thin slabs "
             "and a medium ending at the farthest wall, on the other fields of the start given, and races no other")
    for index, (frame, auto) in searched.items():
        path = pairs[index][0]
        _say(f"finding the light of {path} ({'from the target' if auto else 'refining its light'})")
        search = _search_with_progress(
            effect, frames[index], targets[index], start_xy=None if auto else np.asarray(light_positions[index]),
            fields=tuple(name for name in fitted_bounds(effect, fixed=fixed) if name not in effect.POLISH_FIELDS),
            starts=starts, light_depth=depths[index], space=args.space,
        )  # fmt: skip
        for line in light_lines(path, search, auto=auto, start_names=start_names):
            _say(line)
        found[path] = (search, frame, depths[index], [])
        light_positions[index] = jnp.asarray(search.light_xy, jnp.float32)
        frames[index] = ready_frame(effect, frame, tuple(search.light_xy), path)
    if searched:
        # JAX's caches hold the search's programs, and with them memory that the fits after it never use: as live
        # as those fits' own buffers, it raised each one's peak (benchmarks/README.md, "A light out of view").
        jax.clear_caches()
        gc.collect()
        allocator.hand_back_free_memory()
    fit_options = {
        "loss": args.loss, "space": args.space, "solver": args.solver, "fixed": fixed, "max_steps": args.max_steps,
        "light_in_front": in_front, "light_depth": depths, "other_lights": others, "fit_light_tints": fit_tints,
        "coarse_factor": coarse_factor, "coarse_jacobian": True, "starts": starts,
    }  # fmt: skip
    # The search's light lies where its few fields match best; the loss of whole fits places it (`light_profile`).
    # The lowest of those fits, by every frame's light: the command's own fit where the lights are placed at them.
    lowest = {"loss": math.inf, "lights": None, "result": None}
    for index, (frame, _) in searched.items():
        path = pairs[index][0]
        _say(f"placing the light of {path} by whole fits around it")

        def fitted_loss(xy, index=index, frame=frame, path=path):
            lights_now, frames_now = list(light_positions), list(frames)
            lights_now[index] = jnp.asarray(xy, jnp.float32)
            frames_now[index] = ready_frame(effect, frame, tuple(xy), path)
            try:
                fitted = fit(effect, frames_now, lights_now, targets, **fit_options)
                loss = fitted.loss_after
            except ValueError:  # the fit diverged at this light: the highest loss (`profile_light`)
                loss = math.inf
            if loss < lowest["loss"]:
                lowest.update(loss=loss, lights=_lights_key(lights_now), result=fitted)
            _say(tried_line(xy, loss))
            allocator.hand_back_free_memory()  # each fit faults in what it needs once, and no more stays resident
            return loss

        step, rise = PROFILE_STEP * max(frame.height, frame.width), VISIBLE_CHANGE**2 if args.loss == "mse" else None
        profile = profile_light(fitted_loss, np.asarray(light_positions[index]), step=step, visible_rise=rise)
        for line in profile_lines(profile, visible_rise=rise, step=step):
            _say(line)
        # The search's standard error and covariance were its light's, with its few fields: not the light placed.
        placed = dataclasses.replace(
            found[path][0], light_xy=profile.light_xy, visible_shift=profile.visible_shift,
            standard_error=np.full(2, np.nan), covariance=np.full((2, 2), np.nan),
        )  # fmt: skip
        found[path] = (placed, frame, depths[index], [])
        light_positions[index] = jnp.asarray(profile.light_xy, jnp.float32)
        frames[index] = ready_frame(effect, frame, tuple(profile.light_xy), path)
    if lowest["lights"] is not None and lowest["lights"] == _lights_key(light_positions):
        result = lowest["result"]  # the same fit again: `fit` is deterministic
        _say("the fit at the light placed is the lowest of those around it: its result is kept")
    else:
        result = _fit_with_progress(effect, frames, light_positions, targets, args, coarse_factor, fit_options)
    chosen = result.effect if args.fractional_counts else result.rounded
    values = effect_to_dict(chosen)
    _say(f"fitted {type(chosen).__name__} ({_steps_line(result, coarse_factor)}):")
    for name in result.fitted:
        _say(f"  {name} = {values[name]}")
    if result.light_tints is not None:
        _say(f"  {LIGHT_TINTS} = {tints_text(result.light_tints)} (each light's over the first's; apply --params "
             f"takes them from {found_lights_path(args.output)})")
        others = [[dataclasses.replace(light, tint=tint) for light, tint in zip(beside, result.light_tints)]
                  for beside in others]  # fmt: skip
    if result.start:
        _say(f"started from the fitted fields of {start_names[result.start - 1]} (a lower loss than the start given)")
    if result.kept_start:
        _say("the start given fits the frames better than where the fit ended: its parameters are kept")
    if effect.fit_stand_in() is not effect:
        cheaper = _statics_line(effect.fit_stand_in(), effect)
        _say(f"fitted through its stand-in (cheaper: {cheaper}); the losses and parameters written are the effect's own")
    loss_name = f"{args.loss} ({args.space})"
    after = result.loss_after if args.fractional_counts else result.loss_rounded
    _say(f"loss before {result.loss_before:.6g}, after {after:.6g} ({loss_name})")
    fitted_images = result.images_after if args.fractional_counts else result.images_rounded
    _say(_metrics_line(result.images_before, fitted_images, targets))
    lines = _determination_lines(
        result, frames, light_positions, targets, in_front, depths, others, args.space, coarse_factor
    )  # fmt: skip
    for line in lines:
        _say(line)
    fitted_tints = result.light_tints
    report = fit_report_image(targets[0], fitted_images[0], result.loss_history) if args.report else None
    _write_outputs(args.output, chosen, [
        *([(args.report, lambda path: write_image(path, report))] if args.report else []),
        *([(found_lights_path(args.output), lambda path: write_text(path, found_lights_text(found, fitted_tints)))]
          if found or fitted_tints is not None else []),
    ])  # fmt: skip
    if found or fitted_tints is not None:
        _say(f"wrote {found_lights_path(args.output)}")
    if args.report:
        _say(f"wrote {args.report}")
    _say(f"wrote {args.output}")
    return 0


def _fit_with_progress(effect, frames, light_positions, targets, args, coarse_factor: int, fit_options: dict):
    """`fit` under a progress bar of its steps (both phases' where a coarse phase or a polish makes two)."""
    phases = 2 if coarse_factor > 1 or polishes(args.solver, args.loss) else 1  # a coarse phase's fine one polishes
    bar = tqdm.tqdm(total=phases * args.max_steps, desc="fit", unit="step", file=sys.stderr, dynamic_ncols=True)

    def progress(step, value):
        bar.set_postfix_str(f"loss {value:.4g}", refresh=False)
        bar.update(step - bar.n)

    try:
        return fit(effect, frames, light_positions, targets, progress=progress, **fit_options)
    finally:
        bar.close()


def _search_with_progress(effect, frame, target, **options):
    """`find_light` under a progress bar of its evaluations, handing the heap's free pages back after each: the
    heap the command keeps (`allocator.keep_freed_memory`) grew by whole temporaries of its Jacobian, whose size
    changes between its descents, where the time to fault one in again is small beside an evaluation's
    (benchmarks/README.md, "A light out of view")."""
    bar = tqdm.tqdm(desc="finding the light", unit="step", file=sys.stderr, dynamic_ncols=True)
    lowest = math.inf  # each start's and each rejected step's loss is heard too: the bar shows the lowest so far

    def progress(evaluations, loss):
        nonlocal lowest
        lowest = min(lowest, loss)
        bar.set_postfix_str(f"lowest loss {lowest:.4g}", refresh=False)
        bar.update(evaluations - bar.n)
        allocator.hand_back_free_memory()

    try:
        return find_light(effect, frame, target, progress=progress, **options)
    finally:
        bar.close()


def _lights_key(light_positions) -> tuple:
    """Every frame's light, exactly, as a key: two fits at the same lights (and frames, options) are the same fit."""
    return tuple(tuple(np.asarray(xy, np.float32).tolist()) for xy in light_positions)


LIGHT_TINTS = "light_tints"
"""The fitted tints of the lights beside each frame's first, as `fit` prints them and `--fixed` names them."""


def _frame_lights(args, given, path: str) -> tuple:
    """A frame's lights: `first_light`'s `given` (`--light`'s first, `LIGHT_AUTO` or None: the header's), the first's
    distance, and the lights beside it (`effects.lights.Light`s, each tint over the first's: the fitted
    `light_color` is the first light's), from `--light`, `--light-depth`, `--light-tint` or the frame's header."""
    if given == LIGHT_AUTO:
        if args.light_tint is not None or (args.light_depth or [0])[1:]:
            raise CommandError(
                "--light auto finds the lights: give --light-depth once (the first's) and no --light-tint"
            )
        return given, resolve_light_depth((args.light_depth or [None])[0], path), []
    lights, depths, tints = with_stored_lights(path, given, args.light_depth, args.light_tint)
    first, depth, tint, beside = split_lights(lights, depths, tints, lambda: resolve_light_depth(None, path))
    if beside and args.fit_light:
        raise CommandError(f"--fit-light refines one light, and {path} has {len(beside) + 1}: fit without it")
    first_tint = np.ones(3) if tint is None else np.asarray(tint, np.float64)
    if not np.all(first_tint > 0):
        raise CommandError(f"--light-tint: the first light's tint must be above 0 in every channel, got {tint}")
    beside = [dataclasses.replace(light, tint=np.asarray(light.tint / first_tint, np.float32)) for light in beside]
    return first, depth, beside


def _lights_in_view(frame, effect, fov, path: str) -> list:
    """The lights in view of `frame` (`light_seen.seen_lights`), their distances along rays from the frame's field
    of view (or the effect's) where its depth is planar."""
    fov_x_deg = fov if fov is not None else getattr(effect, "fov_x_deg", None)
    try:
        return seen_lights(frame, fov_x_deg=None if fov_x_deg is None else float(fov_x_deg))
    except ValueError as error:
        raise CommandError(f"finding the light of {path}: {error}; --fov-x-deg gives it") from None


def _light_depth_given(args, path: str, *, header: bool) -> bool:
    """Whether the first light's distance is given: by `--light-depth`, or (`header`: the light refined is the
    header's or `--light`'s, `--fit-light`) by the frame's header. `--light auto` reads a lamp in view's from its
    pixels before the header's, whose position it does not read either."""
    return (args.light_depth or [None])[0] is not None or (header and read_light_depth(path) is not None)


def _say(line: str) -> None:
    """A line of the fit's results on stdout, shown as it comes (a pipe would hold it back until the end)."""
    print(line, flush=True)


def _write_outputs(output: str, effect, beside: list) -> None:
    """The fitted parameters and the files written with them (`beside`: `(path, write)` pairs, the report and the
    lights found), all or none: each is written whole (atomically), the parameters last, and those written before
    are removed again if the parameters cannot follow them (an error, an interrupt). Lights found by an earlier fit
    beside `output` and not by this one are removed, so that `apply --params` does not read them with these."""
    written = []
    try:
        for path, write in beside:
            write(path)
            written.append(path)
        save_effect(output, effect)
    except BaseException:
        for path in written:
            with contextlib.suppress(OSError):
                os.remove(path)
        raise
    if found_lights_path(output) not in written:
        with contextlib.suppress(FileNotFoundError):
            os.remove(found_lights_path(output))


def fit_starts(effect, frames, fov_x_deg) -> tuple[list[str], list]:
    """The other starts `fit` races beside `effect`, and their names: the model's presets (`model_presets`),
    then a fog layer read from the frames (`ground_layer_start`) on the fields of `effect` and of each preset, and
    in frames with no sky a medium bounded to the room they show (`enclosed_start`) on `effect`'s, in frames
    with a light view thin slabs (`thin_slabs_start`), then thin slabs and a medium ending at the farthest wall
    (`thin_slabs_room_start`) on `effect`'s, and in frames the fog reads as closed beyond
    their edges thin slabs and a medium ending at the farthest wall (`closed_room_start`) on `effect`'s.

    So the result does not hang on the start given (`benchmarks/fit_volumetric.py --starts`); the presets take
    the frame's field of view `fov_x_deg` (or keep theirs when it is `None`), which the layer's heights need.
    """
    names = [f"preset {name}" for name in model_presets(effect)]
    starts = [preset(name).with_camera(fov_x_deg=fov_x_deg) for name in model_presets(effect)]
    for name, base in [("the start given", effect), *zip(list(names), list(starts))]:
        layer = ground_layer_start(base, frames)
        if layer is not None:
            names.append(f"the ground layer estimated from the frame, on the other fields of {name}")
            starts.append(layer)
    beside_given = (
        (enclosed_start, "the medium of the room the frames show (no sky)"),
        (thin_slabs_start, "thin slabs (the light view casts the frames' shadows)"),
        (thin_slabs_room_start, "thin slabs and a medium ending at the farthest wall (the light view casts the frames' "
                                "shadows)"),
        (closed_room_start, "thin slabs and a medium ending at the farthest wall (a room read as closed beyond the "
                            "frame)"),
    )  # fmt: skip
    for estimate, what in beside_given:
        start = estimate(effect, frames)
        if start is not None:
            names.append(f"{what}, on the other fields of the start given")
            starts.append(start)
    return names, starts


def _statics_line(stand_in, effect) -> str:
    """The static fields in which the stand-in differs from the effect, as `name=value`."""
    names = [name for name, info in field_metadata(effect).items() if info.kind == "static"]
    return ", ".join(f"{n}={field_value(stand_in, n)!r}" for n in names if field_value(stand_in, n) != field_value(effect, n))


def _steps_line(result, coarse_factor: int) -> str:
    """How many steps the fit took, in which phases, and why it stopped."""
    coarse = f"{result.coarse_steps} steps at 1/{coarse_factor} resolution, then " if coarse_factor > 1 else ""
    if result.converged:
        why = "converged"
    elif result.plateaued:
        why = "stopped: the loss had stopped moving"
    else:
        why = "stopped at --max-steps"
    polish = f" ({result.polish_steps} of them polishing with Marquardt's scaling)" if result.polish_steps else ""
    return f"{coarse}{result.steps} steps{polish}, {why}"


def _metrics_line(start_images, fitted_images, targets) -> str:
    """PSNR and SSIM before and after, by scikit-image in display space: a check independent of the fit's loss."""
    before = [image_metrics(image, target) for image, target in zip(start_images, targets)]
    after = [image_metrics(image, target) for image, target in zip(fitted_images, targets)]
    (psnr_before, ssim_before), (psnr_after, ssim_after) = np.mean(before, axis=0), np.mean(after, axis=0)
    over = f", mean over {len(targets)} frames" if len(targets) > 1 else ""
    return (
        f"PSNR before {psnr_before:.2f} dB, after {psnr_after:.2f} dB; SSIM before {ssim_before:.4f}, "
        f"after {ssim_after:.4f} (skimage.metrics in display space x/(1+x){over})"
    )


def _determination_lines(result, frames, lights, targets, in_front, depths, others, space, coarse_factor) -> list[str]:
    """Which fitted parameters the frames leave poorly determined, and what offsets them (`determination`, its
    Jacobian as the fit's polish took it)."""
    try:
        found = determination(
            result.effect, frames, lights, targets, fitted=result.fitted, space=space, light_in_front=in_front,
            light_depth=depths, other_lights=others, fit_light_tints=result.light_tints is not None,
            coarse_factor=coarse_factor,
        )
    except ValueError as error:  # the fit stands; only what it can say of it is less
        return [f"cannot tell which fitted parameters the frames determine: {error}"]
    lines = []
    if found.on_bound:
        at = ", ".join(f"{name} at {value:.6g}" for name, value in found.on_bound.items())
        lines.append(f"on a bound of its fitting range (the frames may ask for a value beyond it): {at}")
    if not found.poorly_determined:
        lines.append(f"every fitted parameter is determined by the frames (Jacobian condition number {found.condition:.3g})")
        return lines
    lines.append(
        "poorly determined (a step of 10% of its range, offset by the others, changes the frame by less than "
        f"0.001 RMS in {space} space): {', '.join(found.poorly_determined)}"
    )
    for name in found.poorly_determined:
        (own, step), *others = found.offsets[name].items()
        offset = ", ".join(f"{other} {value:+.3g}" for other, value in others) or "nothing (it changes nothing)"
        lines.append(f"  {own} {step:+.3g} offset by {offset}: {found.offset_change[name]:.2g} RMS")
    return lines
