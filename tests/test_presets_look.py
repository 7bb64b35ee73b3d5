"""The presets beyond the articles: `gpu_gems` (Babylon.js' GPU Gems 3 constants, shafts that reach
across the frame) and `physically_based` (ScatteringFog fitted to a path-traced fog frame), whose halo
must stay smooth when an object hides the sun, as a path tracer's does."""

from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
from skimage.measure import label

import godrays_jax as gr
from godrays_jax.effects.presets import GPU_GEMS_SAMPLE_SPREAD

HERO_FRAME = Path(__file__).resolve().parents[1] / "examples" / "data" / "forest_hero.exr"


def test_hero_frame_cuts_the_sky_around_the_sun_into_many_gaps():
    """The shipped hero frame: the sun on screen, partly seen, and dozens of sky gaps within 0.2 frame-widths of it."""
    buffers = gr.read_buffers(HERO_FRAME)
    (x, y), in_front = gr.read_light(HERO_FRAME)
    assert in_front and 0 < x < buffers.width and 0 < y < buffers.height
    assert buffers.light_pass is not None and buffers.glow_pass is not None
    assert 0 < float(buffers.light_pass.sum()) < 0.01 * buffers.height * buffers.width
    rows, columns = np.mgrid[0 : buffers.height, 0 : buffers.width] + 0.5
    near_sun = np.hypot(columns - x, rows - y) < 0.2 * buffers.width
    gaps = label((np.asarray(buffers.coverage) < 0.5) & near_sun, connectivity=1)
    assert (np.bincount(gaps.ravel())[1:] >= 4).sum() >= 30

# --- gpu_gems -------------------------------------------------------------------------------


def test_gpu_gems_holds_babylons_constants():
    effect = gr.preset("gpu_gems")
    assert isinstance(effect, gr.GodRays)
    # Each of Babylon's 100 samples spread over a few: the same weights along the ray, a shorter step.
    spread = GPU_GEMS_SAMPLE_SPREAD
    assert effect.max_samples == 100 * spread and float(effect.num_samples) == 100.0 * spread
    assert float(effect.density) == pytest.approx(0.926, rel=1e-6)
    assert float(effect.decay) ** spread == pytest.approx(0.96815, rel=1e-6)
    assert float(effect.weight) * spread == pytest.approx(0.58767, rel=1e-6)
    # Babylon's exposure .3 times the 0.4 its shader puts on every sample.
    assert float(effect.exposure) == pytest.approx(0.3 * 0.4, rel=1e-6)


def _sky_hole_frame(height: int, width: int, light_xy, hole_radius: float) -> gr.Buffers:
    """Everything covered except a disc of open sky around the light."""
    y, x = np.mgrid[0:height, 0:width] + 0.5
    open_sky = np.hypot(x - light_xy[0], y - light_xy[1]) < hole_radius
    coverage = jnp.asarray(np.where(open_sky, 0.0, 1.0), jnp.float32)
    depth = jnp.asarray(np.where(open_sky, np.inf, 5.0), jnp.float32)
    return gr.Buffers(color=jnp.zeros((height, width, 3), jnp.float32), depth=depth, coverage=coverage)


def test_gpu_gems_shafts_reach_across_the_frame():
    """Light let through a hole around the sun still lights pixels 0.6 frame-widths away (the articles' loops stop short)."""
    height, width = 90, 160
    light = (40.0, 45.0)
    frame = _sky_hole_frame(height, width, light, hole_radius=0.08 * width)

    def brightness(effect, distance):
        layer = np.asarray(eqx.filter_jit(lambda e, b: e.layer(b, jnp.asarray(light)))(effect, frame))
        return layer[int(light[1]), int(light[0] + distance)].sum()

    near, far = 0.15 * width, 0.6 * width
    gems = gr.preset("gpu_gems")
    assert brightness(gems, far) > 0.01 * brightness(gems, near) > 0.0
    # The XNA article's loop (density .5) stops every pixel's samples halfway to the light.
    article = eqx.tree_at(lambda e: (e.density, e.decay, e.weight), gems, (jnp.asarray(0.5), jnp.asarray(0.95), jnp.asarray(1.0)))
    assert brightness(article, near) > 0.0
    assert brightness(article, far) == 0.0


# --- physically_based: the sun hidden behind a box ----------------------------------------------

SUN = np.array([-5.0, 1.5, -100.0])
SUN_DIRECTION = SUN / np.linalg.norm(SUN)
BOX_CENTRE = SUN_DIRECTION * 19.0  # on the line to the sun: the box hides the whole disc
BOX_HALF_SIZE = 1.4
# The medium of the path-traced frame the preset was fitted to (shared/data/README.md).
EXTINCTION, ANISOTROPY, MEDIUM_RADIUS = 0.02, 0.8, 40.0


def _box_rotation() -> np.ndarray:
    """A tilt that shows three faces: the silhouette is a hexagon with sharp corners."""
    ax, ay, az = np.deg2rad([20.0, 30.0, 35.0])
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    return rz @ ry @ rx


def _hidden_sun(width: int, height: int) -> tuple[gr.Scene, gr.Camera]:
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float) * BOX_HALF_SIZE
    faces = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
             [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]  # fmt: skip
    box = gr.Mesh(vertices=corners @ _box_rotation().T + BOX_CENTRE, faces=faces, double_sided=True)
    sun = gr.Sphere(center=SUN, radius=2.5, material=gr.Material(albedo=(0.0, 0.0, 0.0), emission=(400.0, 300.0, 180.0)))
    scene = gr.Scene(objects=(sun, box), light=gr.DirectionalLight(direction=SUN_DIRECTION),
                     sky=gr.Sky(zenith_color=(0.05, 0.06, 0.08), horizon_color=(0.05, 0.06, 0.08)), sun=0)  # fmt: skip
    camera = gr.Camera(position=(0.0, 0.0, 0.0), target=SUN, up=(0.0, 1.0, 0.0), fov_x_deg=50.0, width=width, height=height)
    return scene, camera


def _box_distance(origins, direction):
    """Distance along rays to the box (slab test in its frame), inf where they miss."""
    rotation = _box_rotation()
    local_origin = (origins - BOX_CENTRE) @ rotation
    local_direction = direction @ rotation
    with np.errstate(divide="ignore", invalid="ignore"):
        near = (-BOX_HALF_SIZE - local_origin) / local_direction
        far = (BOX_HALF_SIZE - local_origin) / local_direction
    enter = np.nanmax(np.minimum(near, far), axis=-1)
    leave = np.nanmin(np.maximum(near, far), axis=-1)
    return np.where(leave >= np.maximum(enter, 0.0), np.maximum(enter, 0.0), np.inf)


def _single_scattering(camera: gr.Camera, steps: int = 200) -> np.ndarray:
    """Sun light scattered once toward the camera (slow NumPy march; only the box casts shadows)."""
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


def _angular_profile(layer, light_xy, open_sky, inner, outer, bins=24):
    """Mean of `layer` per angle about the light over open sky `inner..outer` px away, divided by its mean."""
    height, width = layer.shape
    y, x = np.mgrid[0:height, 0:width] + 0.5
    radius = np.hypot(x - light_xy[0], y - light_xy[1])
    angle = np.arctan2(y - light_xy[1], x - light_xy[0])
    ring = (radius >= inner) & (radius < outer) & open_sky
    index = ((angle[ring] + np.pi) / (2 * np.pi) * bins).astype(int) % bins
    profile = np.bincount(index, layer[ring], bins) / np.bincount(index, None, bins)
    return profile / profile.mean()


@pytest.fixture(scope="module")
def hidden_sun():
    scene, camera = _hidden_sun(160, 90)
    buffers = gr.render(scene, camera, with_glow_pass=False)
    light_xy = np.asarray(gr.light_pixel(scene, camera)[0])
    open_sky = np.asarray(buffers.coverage) < 0.5
    assert np.asarray(buffers.light_pass).max() == 0.0  # the whole sun is hidden
    y, x = np.mgrid[0:90, 0:160] + 0.5
    silhouette = np.hypot(x - light_xy[0], y - light_xy[1])[~open_sky].max()
    return buffers, light_xy, open_sky, silhouette, _single_scattering(camera)


def _halo_error(effect, hidden_sun, inner, outer):
    """RMS difference between the effect's and the reference's angular profiles in a ring around the silhouette."""
    buffers, light_xy, open_sky, silhouette, reference = hidden_sun
    layer = np.asarray(eqx.filter_jit(lambda e, b, l: e.layer(b, l))(effect, buffers, jnp.asarray(light_xy)))
    layer = layer[..., :3].mean(-1)
    assert np.all(np.isfinite(layer))
    ring = (inner * silhouette, outer * silhouette)
    expected = _angular_profile(reference, light_xy, open_sky, *ring)
    return float(np.sqrt(np.mean((_angular_profile(layer, light_xy, open_sky, *ring) - expected) ** 2)))


def test_reference_halo_is_smooth_but_not_flat(hidden_sun):
    """The path tracer's halo varies gently around the silhouette (a flat reference would let anything pass)."""
    _, light_xy, open_sky, silhouette, reference = hidden_sun
    profile = _angular_profile(reference, light_xy, open_sky, silhouette, 1.25 * silhouette)
    assert 0.02 < profile.std() < 0.1


def test_physically_based_halo_has_no_spikes_when_the_sun_is_hidden(hidden_sun):
    """Just outside the silhouette, the fitted haze follows the reference's angular profile within 7 %."""
    assert _halo_error(gr.preset("physically_based"), hidden_sun, 1.0, 1.25) < 0.07
    assert _halo_error(gr.preset("physically_based"), hidden_sun, 1.25, 1.6) < 0.04


def test_full_shadowing_or_a_sky_emitter_spikes_from_the_corners(hidden_sun):
    """The measure sees spikes: shadowing the haze wholly, or summing the open sky, doubles the error."""
    fully_shadowed = eqx.tree_at(lambda e: e.shadow_strength, gr.preset("physically_based"), jnp.asarray(1.0))
    assert _halo_error(fully_shadowed, hidden_sun, 1.0, 1.25) > 0.1
    assert _halo_error(gr.preset("gpu_gems"), hidden_sun, 1.0, 1.25) > 0.1
