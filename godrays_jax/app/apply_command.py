"""`godrays-jax apply`: one frame through one effect."""

import os

import jax
import numpy as np

from godrays_jax.app.options import (
    CommandError,
    check_output_path,
    effect_option,
    frame_for_command,
    frame_reading,
    lights_of_params,
    resolve_light_depth,
    split_lights,
    tints_of_params,
    with_flare_texture,
    with_frame_camera,
    with_light_view,
    with_stored_lights,
)
from godrays_jax.pipeline.batch import dither_seed_of, frames_function
from godrays_jax.primitives.frame_files import read_frame, write_frame_like
from godrays_jax.primitives.images import write_image


def _is_exr(path: str) -> bool:
    return os.path.splitext(path)[1].lower() == ".exr"


def run(args) -> int:
    check_output_path(args.output, args.buffers)
    effect = with_flare_texture(effect_option(args.preset, args.params), args.flare_texture)
    buffers, frame_file = read_frame(args.buffers, **frame_reading(args))
    buffers = with_light_view(buffers, args.light_view)
    effect = with_frame_camera(effect, args, args.buffers)
    found = lights_of_params(args.params, args.buffers, buffers) if args.light is None else None
    lights, depths, tints = args.light, args.light_depth, args.light_tint
    if found is not None:  # the lights `fit` found, at the distances it drew them at
        lights = found.lights
        if depths is None:
            depths = [resolve_light_depth(None, args.buffers) if depth is None else depth for depth in found.depths]
    else:
        lights, depths, tints = with_stored_lights(args.buffers, lights, depths, tints)
    tints = tints_of_params(args.light_tint, args.params, lights) or tints
    if args.layer_only and args.light is None and lights and len(lights) > 1:
        where = "has {} lights found by fit" if found is not None else "stores {} lights (godrays:lights)"
        raise CommandError(f"{args.buffers} {where.format(len(lights))} and --layer-only draws one: "
                           "pass --light X,Y to choose it")  # fmt: skip
    first, light_depth, light_tint, beside = split_lights(
        lights, depths, tints, lambda: resolve_light_depth(None, args.buffers), layer_only=args.layer_only
    )
    effect, buffers, light_xy, in_front = frame_for_command("apply", effect, buffers, args.buffers, first)
    several = bool(beside) or light_tint is not None
    # The program `batch` runs, on a group of one frame, stored traced: a later `apply` neither traces nor compiles it.
    apply = frames_function(
        effect, layer_only=args.layer_only, light_depth=light_depth, light_tint=light_tint, beside=beside, stored=True
    )
    one_frame = jax.tree.map(lambda leaf: leaf[None], buffers)
    try:
        image = apply(one_frame, np.asarray([light_xy], np.float32), np.asarray([in_front]))[0]
    except ValueError as error:
        if not several:
            raise
        raise CommandError(f"--light: {error}") from None  # a blend whose layers do not add (`lit_by`)
    if _is_exr(args.output) and _is_exr(args.buffers):
        # EXR to EXR: every other channel, each channel's format and the metadata as the frame had them.
        write_frame_like(args.output, image, frame_file)
    else:
        write_image(args.output, image, dither_seed=None if args.no_dither else dither_seed_of(args.buffers))
    print(f"wrote {args.output}")
    return 0

