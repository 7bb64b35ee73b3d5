"""The depth a scene's light sees (`light_view`): a frame's depth map seen from the light, for the shadows that
what lies outside the frame casts into its fog (`primitives.light_view.LightView`)."""

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

from godrays_jax.primitives.camera import Camera, ray_depth_scale
from godrays_jax.primitives.light_view import LightView
from godrays_jax.raster.lights import checked_light_index, light_point
from godrays_jax.raster.rasterizer import render
from godrays_jax.raster.scene import Scene

SUN_VIEW_DISTANCE = 100.0
"""A sun's view is a pinhole's (the rasterizer's only camera) this many `reach`es up-sun of the frame's camera:
its rays then leave the sun's direction by at most half a degree over the covered sphere, about the sun's own
disc."""

WIDEST_VIEW_DEG = 150.0
"""The widest field of view of a point light's map (one pinhole view; a light inside the covered sphere sees it
all only in a cube of views)."""


def light_view(scene: Scene, camera: Camera, *, reach: float, size: int = 1024, index: int = 0) -> LightView:
    """The depth seen from `scene.lights[index]` (the first by default) over the sphere of radius `reach` (scene
    units) around `camera` (the frame's): where the frame's fog lies, `reach` its medium's `max_distance`.

    A pinhole view `size x size` pixels (`LightView`'s `perspective` projection, its depth along the view's axis,
    `inf` where it sees nothing), of every object but the scene's visible sun object: for a directional light from
    `SUN_VIEW_DISTANCE * reach` up-sun looking at the frame's camera, for a point light from the light looking at
    the middle of the sphere's part in front of the camera (at most `WIDEST_VIEW_DEG` wide).

    Raises:
        ValueError: `reach` not a finite number > 0, `size` not an int >= 2, or `index` not one of the lights.
    """
    index = checked_light_index(scene, index)
    if not (isinstance(reach, (int, float)) and math.isfinite(reach) and reach > 0):
        raise ValueError(f"reach must be a finite number of scene units > 0, got {reach!r}")
    if isinstance(size, bool) or not isinstance(size, int) or size < 2:
        raise ValueError(f"size must be an int >= 2, got {size!r}")
    frame_position = np.asarray(camera.position, np.float64)
    point = light_point(scene, index)
    if point is None:  # a light at infinity
        toward = np.asarray(scene.lights[index].direction, np.float64)
        distance = SUN_VIEW_DISTANCE * reach
        position, target = frame_position + distance * toward / np.linalg.norm(toward), frame_position
        fov = 2.0 * math.degrees(math.atan(reach / distance))
    else:
        _, _, forward = (np.asarray(axis, np.float64) for axis in camera.basis())
        position, target = np.asarray(point, np.float64), frame_position + 0.5 * reach * forward
        distance = float(np.linalg.norm(target - position))
        if distance < 1e-6 * reach:  # the light at the middle: look the way the frame does
            target, distance = position + forward, 1.0
        fov = min(2.0 * math.degrees(math.atan(reach / distance)), WIDEST_VIEW_DEG)
    forward = (target - position) / np.linalg.norm(target - position)
    up = np.array([0.0, 1.0, 0.0]) if abs(forward[1]) < 0.99 else np.array([0.0, 0.0, -1.0])
    far_side = float(np.linalg.norm(frame_position - position)) + 2.0 * reach
    view = Camera(position=position, target=target, up=up, fov_x_deg=fov, width=size, height=size,
                  near=1e-4 * far_side, far=far_side)  # fmt: skip
    occluders = tuple(obj for number, obj in enumerate(scene.objects) if number != scene.sun)
    seen = render(dataclasses.replace(scene, objects=occluders, sun=None), view, with_glow_pass=False)
    planar = seen.depth / ray_depth_scale(size, size, fov_x_deg=view.fov_x_deg)
    light_axes, frame_axes = (jnp.stack(one.basis()) for one in (view, camera))  # rows: right, up, forward
    rotation = jnp.matmul(light_axes, frame_axes.T, precision="highest")
    shift = jnp.matmul(light_axes, camera.position - view.position, precision="highest")
    return LightView(depth=planar, from_camera=jnp.concatenate([rotation, shift[:, None]], axis=1),
                     scale=view.focal_px, projection="perspective")  # fmt: skip
