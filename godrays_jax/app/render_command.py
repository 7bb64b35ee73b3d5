"""`godrays-jax render`: a scene file through the built-in rasterizer to an EXR frame."""

from godrays_jax.app.options import check_output_path
from godrays_jax.primitives.camera_metadata import CLIP_PLANES_ATTR, FOV_X_ATTR
from godrays_jax.primitives.frame_files import write_buffers
from godrays_jax.primitives.light_metadata import LIGHT_DEPTH_ATTR
from godrays_jax.raster import light_distance, light_pixel, load_scene, render


def frame_metadata(scene, camera) -> dict:
    """The header `render` writes beside the light's pixel: the light's distance, the camera's field of view and
    clip planes (effects that measure directions or hardware depth read them)."""
    return {
        LIGHT_DEPTH_ATTR: light_distance(scene, camera),
        FOV_X_ATTR: float(camera.fov_x_deg),
        CLIP_PLANES_ATTR: (float(camera.near), float(camera.far)),
    }


def run(args) -> int:
    check_output_path(args.output, args.scene)
    scene, camera = load_scene(args.scene)
    buffers = render(scene, camera, with_glow_pass=not args.no_glow)
    xy, _, in_front = light_pixel(scene, camera)
    light_xy = (float(xy[0]), float(xy[1]))
    metadata = frame_metadata(scene, camera)
    depth = metadata[LIGHT_DEPTH_ATTR]
    write_buffers(args.output, buffers, light_xy=light_xy, light_in_front=bool(in_front), metadata=metadata)
    if args.light:
        side = "in front" if in_front else "behind the camera"
        print(f"light {light_xy[0]:.4f},{light_xy[1]:.4f} {side}, at distance {depth:.4f}")
    print(f"wrote {args.output}")
    return 0
