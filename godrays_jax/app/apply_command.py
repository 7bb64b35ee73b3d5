"""`godrays-jax apply`: one frame through one effect."""

import os

import jax
import numpy as np

from godrays_jax.app.options import (
    NO_SKY,
    CommandError,
    check_output_path,
    effect_for_frame,
    effect_option,
    frame_field_of_view,
    frame_reading,
    has_sky,
    resolve_light,
    resolve_light_depth,
    warn,
    with_field_of_view,
    with_frame_clip_planes,
    with_flare_texture,
)
from godrays_jax.pipeline.batch import dither_seed_of, frames_function, ready_frame
from godrays_jax.primitives.frame_files import read_frame, write_frame_like
from godrays_jax.primitives.images import write_image


def _is_exr(path: str) -> bool:
    return os.path.splitext(path)[1].lower() == ".exr"


def run(args) -> int:
    check_output_path(args.output, args.buffers)
    effect = with_flare_texture(effect_option(args.preset, args.params), args.flare_texture)
    buffers, frame_file = read_frame(args.buffers, **frame_reading(args))
    effect = with_field_of_view(effect, frame_field_of_view(args, args.buffers))
    effect = with_frame_clip_planes(effect, args.buffers)
    effect = effect_for_frame("apply", effect, buffers, args.buffers)
    light_xy, in_front = resolve_light(args.light, args.buffers)
    try:
        buffers = ready_frame(effect, buffers, light_xy, args.buffers)
    except ValueError as error:
        raise CommandError(str(error)) from None
    if not has_sky(buffers):
        warn("apply", f"{args.buffers} has {NO_SKY}")
    light_depth = resolve_light_depth(args.light_depth, args.buffers)
    # The program `batch` runs, on a group of one frame, stored traced: a later `apply` neither traces nor compiles it.
    apply = frames_function(effect, layer_only=args.layer_only, light_depth=light_depth, stored=True)
    one_frame = jax.tree.map(lambda leaf: leaf[None], buffers)
    image = apply(one_frame, np.asarray([light_xy], np.float32), np.asarray([in_front]))[0]
    if _is_exr(args.output) and _is_exr(args.buffers):
        # EXR to EXR: every other channel, each channel's format and the metadata as the frame had them.
        write_frame_like(args.output, image, frame_file)
    else:
        write_image(args.output, image, dither_seed=None if args.no_dither else dither_seed_of(args.buffers))
    print(f"wrote {args.output}")
    return 0
