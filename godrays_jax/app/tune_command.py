"""`godrays-jax tune`: serve the live tuner for one frame until Ctrl-C."""

from godrays_jax.app.options import (
    CommandError,
    check_output_path,
    effect_option,
    frame_for_command,
    frame_reading,
    read_target,
    resolve_light_depth,
    split_lights,
    with_frame_camera,
    with_light_view,
    with_stored_lights,
)
from godrays_jax.app.server import HOST, TuneServer
from godrays_jax.app.tuner import Tuner
from godrays_jax.primitives.frame_reading import read_buffers


def run(args) -> int:
    """The `godrays-jax tune` command: serve the tuner until Ctrl-C (options: `cli`)."""
    check_output_path(args.output, args.buffers, *([args.target] if args.target else []))
    if args.preview_pixels < 1:
        raise CommandError(f"--preview-pixels must be >= 1, got {args.preview_pixels}")
    if args.fit_steps < 1:
        raise CommandError(f"--fit-steps must be >= 1, got {args.fit_steps}")
    effect = effect_option(args.preset, args.params)
    buffers = with_light_view(read_buffers(args.buffers, **frame_reading(args)), args.light_view)
    effect = with_frame_camera(effect, args, args.buffers)
    # Several lights (`--light 'A;B'`, or a frame that stores several) are tuned together, each dragged.
    first, light_depth, light_tint, other_lights = split_lights(
        *with_stored_lights(args.buffers, args.light, args.light_depth, args.light_tint),
        lambda: resolve_light_depth(None, args.buffers),
    )
    # A frame without depth keeps the open sky found around the starting light while the light is dragged.
    effect, buffers, light_xy, in_front = frame_for_command("tune", effect, buffers, args.buffers, first)
    target = None if args.target is None else read_target(args.target)
    if target is not None and target.shape[:2] != (buffers.height, buffers.width):
        raise CommandError(
            f"--target {args.target} is {target.shape[1]}x{target.shape[0]}, "
            f"the frame {buffers.width}x{buffers.height}: they must match"
        )
    tuner = Tuner(
        buffers, light_xy, effect=effect, target=target, light_in_front=in_front,
        light_depth=light_depth, other_lights=other_lights, light_tint=light_tint, save_path=args.output,
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


