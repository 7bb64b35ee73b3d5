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
    light_of_params,
    resolve_light_depth,
    with_flare_texture,
    with_frame_camera,
)
from godrays_jax.effects.base import Effect
from godrays_jax.effects.lights import Light, lit_by
from godrays_jax.pipeline.batch import dither_seed_of, frames_function
from godrays_jax.primitives.buffers import Buffers
from godrays_jax.primitives.derivatives import values_only
from godrays_jax.primitives.frame_files import read_frame, write_frame_like
from godrays_jax.primitives.images import write_image


def _is_exr(path: str) -> bool:
    return os.path.splitext(path)[1].lower() == ".exr"


def run(args) -> int:
    check_output_path(args.output, args.buffers)
    effect = with_flare_texture(effect_option(args.preset, args.params), args.flare_texture)
    buffers, frame_file = read_frame(args.buffers, **frame_reading(args))
    effect = with_frame_camera(effect, args, args.buffers)
    lights = args.light or [None]
    light = light_of_params(lights[0], args.params, args.buffers, buffers)
    effect, buffers, light_xy, in_front = frame_for_command("apply", effect, buffers, args.buffers, light)
    depths = args.light_depth or [resolve_light_depth(None, args.buffers)]
    if len(lights) > 1 or args.light_color is not None or len(depths) > 1:
        image = _several_lights(effect, buffers, [(light_xy, in_front), *lights[1:]], depths, args)
    else:
        # The program `batch` runs, on a group of one frame, stored traced: a later `apply` neither traces nor
        # compiles it.
        apply = frames_function(effect, layer_only=args.layer_only, light_depth=depths[0], stored=True)
        one_frame = jax.tree.map(lambda leaf: leaf[None], buffers)
        image = apply(one_frame, np.asarray([light_xy], np.float32), np.asarray([in_front]))[0]
    if _is_exr(args.output) and _is_exr(args.buffers):
        # EXR to EXR: every other channel, each channel's format and the metadata as the frame had them.
        write_frame_like(args.output, image, frame_file)
    else:
        write_image(args.output, image, dither_seed=None if args.no_dither else dither_seed_of(args.buffers))
    print(f"wrote {args.output}")
    return 0


def _several_lights(effect: Effect, buffers: Buffers, lights: list, depths: list[float], args) -> np.ndarray:
    """The frame under every light of `--light` (`effects.lights.lit_by`), each with its `--light-depth` and
    `--light-color` (one value for every light, or one per light)."""
    count = len(lights)
    colors = args.light_color or [(1.0, 1.0, 1.0)]
    for name, values in (("--light-depth", depths), ("--light-color", colors)):
        if len(values) not in (1, count):
            raise CommandError(f"{name} gives {len(values)} values for {count} lights: give one, or one per light")
    if args.layer_only:
        raise CommandError(
            "--layer-only draws one light in the effect's own colour: a fog's layer under several or coloured "
            "lights is not a sum of layers"
        )
    chosen = [
        Light(np.asarray(xy, np.float32), in_front=bool(front), depth=depth, color=np.asarray(color, np.float32))
        for (xy, front), depth, color in zip(lights, depths * count if len(depths) == 1 else depths,
                                             colors * count if len(colors) == 1 else colors)
    ]  # fmt: skip

    @jax.jit
    def render(frame):
        with values_only():
            return lit_by(effect, frame, chosen)

    try:
        return np.asarray(render(buffers))
    except ValueError as error:
        raise CommandError(str(error)) from None
