"""`godrays-jax render`: a scene file through the built-in rasterizer to an EXR frame."""

import math
import os

import numpy as np

from godrays_jax.app.options import CommandError, check_output_path
from godrays_jax.effects.presets import preset
from godrays_jax.primitives.camera_metadata import CLIP_PLANES_ATTR, FOV_X_ATTR
from godrays_jax.primitives.frame_files import write_buffers
from godrays_jax.primitives.light_metadata import (
    LIGHT_DEPTH_ATTR,
    StoredLight,
    lights_metadata,
)
from godrays_jax.primitives.light_view_files import write_light_view
from godrays_jax.raster import (
    light_distance,
    light_pixel,
    light_view,
    load_scene,
    render,
)


def frame_lights(scene, camera) -> list[StoredLight]:
    """Every light of the scene as the frame's header stores it: its pixel, side and distance; its tint its colour
    over the first light's, channel by channel (the first's tint 1: the effect's own light is the first light's, as
    for a scene of one light; lamps of one colour tint 1 each). A channel the first light lacks takes the other's
    colour over the first's mean (or as it is, under a black first light)."""
    first = np.asarray(scene.light.color, np.float64)
    mean = float(np.mean(first))
    lights = []
    for index, light in enumerate(scene.lights):
        xy, _, in_front = light_pixel(scene, camera, index=index)
        color = np.asarray(light.color, np.float64)
        tint = np.where(first > 0, color / np.where(first > 0, first, 1.0), color / (mean if mean > 0 else 1.0))
        lights.append(StoredLight(
            (float(xy[0]), float(xy[1])), bool(in_front), light_distance(scene, camera, index=index),
            (1.0, 1.0, 1.0) if index == 0 else tuple(float(value) for value in tint),
        ))  # fmt: skip
    return lights


def frame_metadata(camera, lights: list[StoredLight]) -> dict:
    """The header `render` writes beside the first light's pixel: its distance, the camera's field of view and clip
    planes (effects that measure directions or hardware depth read them); for a scene of several lights, every light
    (`lights_metadata` of `frame_lights`), which `apply` and `tune` draw."""
    return {
        LIGHT_DEPTH_ATTR: lights[0].depth,
        FOV_X_ATTR: float(camera.fov_x_deg),
        CLIP_PLANES_ATTR: (float(camera.near), float(camera.far)),
        **(lights_metadata(lights) if len(lights) > 1 else {}),
    }


def run(args) -> int:
    check_output_path(args.output, args.scene)
    if args.light_view:
        check_output_path(args.light_view, args.scene, args.output)
    reach = args.light_view_reach
    if reach is None:
        reach = float(preset("volumetric_haze").medium.max_distance)
    elif not (math.isfinite(reach) and reach > 0):
        raise CommandError(f"--light-view-reach must be a number of scene units > 0, got {reach}")
    if args.light_view and os.path.abspath(args.light_view) == os.path.abspath(args.output):
        raise CommandError("--light-view names the frame's own output (-o): give it a file of its own")
    scene, camera = load_scene(args.scene)
    buffers = render(scene, camera, with_glow_pass=not args.no_glow)
    seen = light_view(scene, camera, reach=reach) if args.light_view else None  # before either file is written
    lights = frame_lights(scene, camera)
    write_buffers(args.output, buffers, light_xy=lights[0].xy, light_in_front=lights[0].in_front,
                  metadata=frame_metadata(camera, lights))  # fmt: skip
    if seen is not None:
        write_light_view(args.light_view, seen)
        print(f"wrote {args.light_view}")
    if args.light:
        for light in lights:
            side = "in front" if light.in_front else "behind the camera"
            print(f"light {light.xy[0]:.4f},{light.xy[1]:.4f} {side}, at distance {light.depth:.4f}")
    print(f"wrote {args.output}")
    return 0
