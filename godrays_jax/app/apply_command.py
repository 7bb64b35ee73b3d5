"""`godrays-jax apply`: one frame through one effect."""

import jax.numpy as jnp

from godrays_jax.app.options import check_output_path, effect_option, resolve_light
from godrays_jax.primitives.io import read_buffers, write_image


def run(args) -> int:
    check_output_path(args.output, args.buffers)
    effect = effect_option(args.preset, args.params)
    buffers = read_buffers(args.buffers, depth_channel=args.depth_channel)
    light_xy, in_front = resolve_light(args.light, args.buffers)
    light = jnp.asarray(light_xy, jnp.float32)
    if args.layer_only:
        image = effect.layer(buffers, light, light_in_front=in_front)
    else:
        image = effect(buffers, light, light_in_front=in_front)
    write_image(args.output, image)
    print(f"wrote {args.output}")
    return 0
