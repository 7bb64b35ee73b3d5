"""A sun fully hidden behind a box, seen through haze: the scene and a single-scattering reference.

A path tracer shows a smooth halo around such a silhouette; screen-space
shafts that sum the open sky toward the light show spikes from its corners
instead. `readme_pictures.py` draws the reference beside the presets, and the
medium is the one of the path-traced fog frame the `physically_based` preset
was fitted to (extinction 0.02 per unit, Henyey-Greenstein g = 0.8, a sphere
of radius 40 around the camera).
"""

import numpy as np

import godrays_jax as gr

SUN = np.array([-5.0, 1.5, -100.0])
SUN_DIRECTION = SUN / np.linalg.norm(SUN)
BOX_CENTRE = SUN_DIRECTION * 19.0  # on the line to the sun: it hides the whole disc
BOX_HALF_SIZE = 1.4
EXTINCTION, ANISOTROPY, MEDIUM_RADIUS = 0.02, 0.8, 40.0
FOV_X_DEG = 50.0


def _box_rotation() -> np.ndarray:
    """A fixed tilt that shows three faces, so the silhouette is a hexagon with sharp corners."""
    ax, ay, az = np.deg2rad([20.0, 30.0, 35.0])
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    return rz @ ry @ rx


def scene_and_camera(width: int, height: int) -> tuple[gr.Scene, gr.Camera]:
    """The box between the camera and the sun, a dim sky; the camera looks at the sun."""
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float) * BOX_HALF_SIZE
    faces = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
             [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]  # fmt: skip
    box = gr.Mesh(vertices=corners @ _box_rotation().T + BOX_CENTRE, faces=faces, double_sided=True,
                  material=gr.Material(albedo=(0.3, 0.3, 0.3)))  # fmt: skip
    sun = gr.Sphere(center=SUN, radius=2.5, material=gr.Material(albedo=(0.0, 0.0, 0.0), emission=(400.0, 300.0, 180.0)))
    scene = gr.Scene(objects=(sun, box), light=gr.DirectionalLight(direction=SUN_DIRECTION, color=(4.0, 3.0, 1.8)),
                     sky=gr.Sky(zenith_color=(0.05, 0.06, 0.08), horizon_color=(0.05, 0.06, 0.08)),
                     ambient=(0.05, 0.05, 0.05), sun=0)  # fmt: skip
    camera = gr.Camera(position=(0.0, 0.0, 0.0), target=SUN, up=(0.0, 1.0, 0.0), fov_x_deg=FOV_X_DEG, width=width, height=height)
    return scene, camera


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
