"""`godrays-jax tune`: serve the live tuner for one frame until Ctrl-C."""

import numpy as np

from godrays_jax.app.options import (
    CommandError,
    check_output_path,
    effect_option,
    frame_for_command,
    frame_reading,
    read_target,
    resolve_light_depth,
    with_frame_camera,
)
from godrays_jax.app.server import HOST, TuneServer
from godrays_jax.app.tuner import Tuner
from godrays_jax.effects.lights import Light
from godrays_jax.primitives.frame_reading import read_buffers
from godrays_jax.primitives.light_metadata import read_lights


def run(args) -> int:
    """The `godrays-jax tune` command: serve the tuner until Ctrl-C (options: `cli`)."""
    check_output_path(args.output, args.buffers, *([args.target] if args.target else []))
    if args.preview_pixels < 1:
        raise CommandError(f"--preview-pixels must be >= 1, got {args.preview_pixels}")
    if args.fit_steps < 1:
        raise CommandError(f"--fit-steps must be >= 1, got {args.fit_steps}")
    effect = effect_option(args.preset, args.params)
    buffers = read_buffers(args.buffers, **frame_reading(args))
    effect = with_frame_camera(effect, args, args.buffers)
    # A frame that stores several lights (a render of several) is tuned under all of them, the first dragged.
    stored = (read_lights(args.buffers) or []) if args.light is None else []
    other_lights = [Light(np.asarray(light.xy, np.float32), in_front=light.in_front, depth=light.depth,
                          tint=np.asarray(light.tint, np.float32)) for light in stored[1:]]  # fmt: skip
    # A frame without depth keeps the open sky found around the starting light while the light is dragged.
    effect, buffers, light_xy, in_front = frame_for_command("tune", effect, buffers, args.buffers, args.light)
    target = None if args.target is None else read_target(args.target)
    if target is not None and target.shape[:2] != (buffers.height, buffers.width):
        raise CommandError(
            f"--target {args.target} is {target.shape[1]}x{target.shape[0]}, "
            f"the frame {buffers.width}x{buffers.height}: they must match"
        )
    tuner = Tuner(
        buffers, light_xy, effect=effect, target=target, light_in_front=in_front,
        light_depth=resolve_light_depth(None, args.buffers), other_lights=other_lights, save_path=args.output,
        max_preview_pixels=args.preview_pixels, fit_steps=args.fit_steps,
    )  # fmt: skip
    try:
        server = TuneServer(tuner, port=args.port)
    except OSError as error:
        tuner.close()
        raise CommandError(f"cannot listen on {HOST}:{args.port}: {error.strerror or error}") from None
    try:
        print(f"compiling the first renders for {buffers.width}x{buffers.height} ...", flush=True)
        server.warm_up()
        print(f"tuner at {server.url} (Ctrl-C stops it); save writes {tuner.save_path}", flush=True)
        server.wait()
    except KeyboardInterrupt:
        print("tuner stopped", flush=True)
    finally:
        server.close()
    return 0


