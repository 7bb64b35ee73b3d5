"""`godrays-jax fit`: fit an effect's parameters to target frames and write them for `apply --params`."""

import sys

import jax.numpy as jnp

from godrays_jax.app.options import (
    NO_SKY,
    CommandError,
    check_output_path,
    effect_for_frame,
    effect_option,
    frame_reading,
    has_sky,
    resolve_light,
    warn,
)
from godrays_jax.effects.serialization import effect_to_dict, save_effect
from godrays_jax.pipeline.fit import default_fit_effect, fit, render_compiled
from godrays_jax.pipeline.report import fit_report_image
from godrays_jax.primitives.io import read_buffers, read_image, write_image


def run(args) -> int:
    """`godrays-jax fit`: read frames and targets, fit, print progress and results, write params (and a report)."""
    pairs = [(args.buffers, args.target), *[tuple(pair) for pair in args.frames or []]]
    check_output_path(args.output, *[path for pair in pairs for path in pair])
    if args.report:
        check_output_path(args.report, *[path for pair in pairs for path in pair])
    lights = args.light or []
    if len(lights) not in (0, len(pairs)):
        raise CommandError(f"give --light once per frame ({len(pairs)} frames) or not at all, got {len(lights)}")
    effect = effect_option(args.preset, args.params, default=default_fit_effect)
    frames, light_positions, in_front, targets = [], [], [], []
    for index, (buffers_path, target_path) in enumerate(pairs):
        frame = read_buffers(buffers_path, **frame_reading(args))
        if not has_sky(frame):
            warn("fit", f"{buffers_path} has {NO_SKY}")
        effect = effect_for_frame("fit", effect, frame, buffers_path)
        (light, front) = resolve_light(lights[index] if lights else None, buffers_path)
        target = read_image(target_path)
        if target.shape[:2] != frame.color.shape[:2]:
            raise CommandError(
                f"{target_path} is {target.shape[1]}x{target.shape[0]} but {buffers_path} is {frame.width}x{frame.height}"
            )
        frames.append(frame)
        light_positions.append(jnp.asarray(light, jnp.float32))
        in_front.append(bool(front))
        targets.append(target)
    fixed = tuple(name for name in (args.fixed or "").split(",") if name)

    def progress(step, value):
        print(f"step {step}: loss {value:.6g}", file=sys.stderr, flush=True)

    result = fit(
        effect, frames, light_positions, targets, loss=args.loss, space=args.space, solver=args.solver,
        fixed=fixed, max_steps=args.max_steps, light_in_front=in_front, progress=progress,
    )  # fmt: skip
    chosen = result.effect if args.fractional_counts else result.rounded
    save_effect(args.output, chosen)
    values = effect_to_dict(chosen)
    print(f"fitted {type(chosen).__name__} ({result.steps} steps, {'converged' if result.converged else 'stopped at --max-steps'}):")
    for name in result.fitted:
        print(f"  {name} = {values[name]}")
    loss_name = f"{args.loss} ({args.space})"
    after = result.loss_after if args.fractional_counts else result.loss_rounded
    print(f"loss before {result.loss_before:.6g}, after {after:.6g} ({loss_name})")
    if args.report:
        fitted_image = render_compiled(chosen, frames[0], light_positions[0], in_front[0])
        write_image(args.report, fit_report_image(targets[0], fitted_image, result.loss_history))
        print(f"wrote {args.report}")
    print(f"wrote {args.output}")
    return 0


