"""A sun fully hidden behind a box, seen through haze: the scene and a single-scattering reference.

A path tracer shows a smooth halo around such a silhouette; screen-space
shafts that sum the open sky toward the light show spikes from its corners
instead. `readme_pictures.py` draws the reference beside the presets, and the
medium is the one of the path-traced fog frame the `physically_based` preset
was fitted to (extinction 0.02 per unit, Henyey-Greenstein g = 0.8, a sphere
of radius 40 around the camera).
"""

import dataclasses
import json
from pathlib import Path

import numpy as np

import godrays_jax as gr

SCENE = Path(__file__).resolve().parent / "scenes" / "hidden_sun.json"
"""The scene: a sun sphere, and a tilted box 19 units along the line to it (it hides the whole disc; three faces
show, so its silhouette is a hexagon with sharp corners), a dim sky. The camera looks at the sun."""
EXTINCTION, ANISOTROPY, MEDIUM_RADIUS = 0.02, 0.8, 40.0

_TABLE = json.loads(SCENE.read_text())
_BOX = next(obj for obj in _TABLE["objects"] if obj.get("name") == "box")
SUN_DIRECTION = np.asarray(_TABLE["light"]["direction"], np.float64)
BOX_CENTRE = np.asarray(_BOX["translation"], np.float64)
BOX_HALF_SIZE = float(_BOX["scale"])  # the box's vertices are the unit cube's corners


def _box_rotation() -> np.ndarray:
    """The box's rotation, as the rasterizer applies `rotation_deg`: about x, then y, then z."""
    ax, ay, az = np.deg2rad(_BOX["rotation_deg"])
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    return rz @ ry @ rx


def scene_and_camera(width: int, height: int) -> tuple[gr.Scene, gr.Camera]:
    """The scene file at `width` x `height` pixels."""
    scene, camera = gr.load_scene(SCENE)
    return scene, dataclasses.replace(camera, width=width, height=height)


def _box_distance(origins: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Distance along each ray to the box (slab test in the box's frame), `inf` where it misses."""
    rotation = _box_rotation()
    local_origin = (origins - BOX_CENTRE) @ rotation
    local_direction = direction @ rotation
    with np.errstate(divide="ignore", invalid="ignore"):
        near = (-BOX_HALF_SIZE - local_origin) / local_direction
        far = (BOX_HALF_SIZE - local_origin) / local_direction
    enter = np.nanmax(np.minimum(near, far), axis=-1)
    leave = np.nanmin(np.maximum(near, far), axis=-1)
    return np.where(leave >= np.maximum(enter, 0.0), np.maximum(enter, 0.0), np.inf)


def single_scattering(camera: gr.Camera, *, steps: int = 200) -> np.ndarray:
    """Sun light scattered once toward the camera, `(H, W)`, relative units (a NumPy ray march).

    Along each camera ray up to the box or the medium's edge, every step adds
    `exp(-extinction * t) * HG(cos theta)` where the sun is not blocked by the
    box; the sun is a directional light.
    """
    right, up, forward = (np.asarray(v, np.float64) for v in camera.basis())
    rays = np.asarray(camera.ray_directions(), np.float64) @ np.stack([right, up, forward])
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    end = np.minimum(_box_distance(np.zeros(3), rays), MEDIUM_RADIUS)
    cosine = rays @ SUN_DIRECTION
    phase = (1 - ANISOTROPY**2) / (4 * np.pi * (1 + ANISOTROPY**2 - 2 * ANISOTROPY * cosine) ** 1.5)
    lit_length = np.zeros(end.shape)
    for i in range(steps):
        t = (i + 0.5) / steps * end
        sunlit = ~np.isfinite(_box_distance(rays * t[..., None], SUN_DIRECTION))
        lit_length += sunlit * np.exp(-EXTINCTION * t) * end / steps
    return EXTINCTION * phase * lit_length


def angular_profile(layer, light_xy, open_sky, inner, outer, bins=24):
    """Mean of `layer` `(H, W)` per angle about the light over open sky `inner..outer` px away, divided by its mean."""
    height, width = layer.shape
    y, x = np.mgrid[0:height, 0:width] + 0.5
    radius = np.hypot(x - light_xy[0], y - light_xy[1])
    angle = np.arctan2(y - light_xy[1], x - light_xy[0])
    ring = (radius >= inner) & (radius < outer) & open_sky
    index = ((angle[ring] + np.pi) / (2 * np.pi) * bins).astype(int) % bins
    profile = np.bincount(index, layer[ring], bins) / np.bincount(index, None, bins)
    return profile / profile.mean()


def render_frame(width: int, height: int) -> tuple[gr.Buffers, gr.Camera, np.ndarray, np.ndarray, float]:
    """The scene rendered (no glow pass): `(buffers, camera, light_xy, open_sky, silhouette)`, the silhouette
    being the box's largest distance from the light in pixels."""
    scene, camera = scene_and_camera(width, height)
    buffers = gr.render(scene, camera, with_glow_pass=False)
    light_xy = np.asarray(gr.light_pixel(scene, camera)[0])
    open_sky = np.asarray(buffers.coverage) < 0.5
    y, x = np.mgrid[0:height, 0:width] + 0.5
    silhouette = float(np.hypot(x - light_xy[0], y - light_xy[1])[~open_sky].max())
    return buffers, camera, light_xy, open_sky, silhouette
