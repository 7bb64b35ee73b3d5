"""The presets beyond the articles: `gpu_gems` (Babylon.js' GPU Gems 3 constants, shafts that reach
across the frame) and `physically_based` (VolumetricFog fitted to a path-traced fog frame), whose halo
must stay smooth when an object hides the sun, as a path tracer's does."""

import sys
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
from skimage.measure import label

import godrays_jax as gr
from godrays_jax.effects.presets import GPU_GEMS_SAMPLE_SPREAD

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
HERO_FRAME = EXAMPLES / "data" / "forest_hero.exr"
sys.path.insert(0, str(EXAMPLES))
import hidden_sun  # noqa: E402 (examples/hidden_sun.py: the scene file, its reference and the halo measure)


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


# --- physically_based: the sun hidden behind a box (examples/scenes/hidden_sun.json) -------------

@pytest.fixture(scope="module")
def hidden_sun_frame():
    buffers, camera, light_xy, open_sky, silhouette = hidden_sun.render_frame(160, 90)
    assert np.asarray(buffers.light_pass).max() == 0.0  # the whole sun is hidden
    return buffers, light_xy, open_sky, silhouette, hidden_sun.single_scattering(camera)


def _halo_error(effect, hidden_sun_frame, inner, outer):
    """RMS difference between the effect's and the reference's angular profiles in a ring around the silhouette."""
    buffers, light_xy, open_sky, silhouette, reference = hidden_sun_frame
    layer = np.asarray(eqx.filter_jit(lambda e, b, l: e.layer(b, l))(effect, buffers, jnp.asarray(light_xy)))
    layer = layer[..., :3].mean(-1)
    assert np.all(np.isfinite(layer))
    ring = (inner * silhouette, outer * silhouette)
    expected = hidden_sun.angular_profile(reference, light_xy, open_sky, *ring)
    return float(np.sqrt(np.mean((hidden_sun.angular_profile(layer, light_xy, open_sky, *ring) - expected) ** 2)))


def test_reference_halo_is_smooth_but_not_flat(hidden_sun_frame):
    """The path tracer's halo varies gently around the silhouette (a flat reference would let anything pass)."""
    _, light_xy, open_sky, silhouette, reference = hidden_sun_frame
    profile = hidden_sun.angular_profile(reference, light_xy, open_sky, silhouette, 1.25 * silhouette)
    assert 0.02 < profile.std() < 0.1


def test_physically_based_halo_has_no_spikes_when_the_sun_is_hidden(hidden_sun_frame):
    """Just outside the silhouette, the fitted haze follows the reference's angular profile within 7 %."""
    assert _halo_error(gr.preset("physically_based"), hidden_sun_frame, 1.0, 1.25) < 0.07
    assert _halo_error(gr.preset("physically_based"), hidden_sun_frame, 1.25, 1.6) < 0.04


def test_full_shadowing_or_a_sky_emitter_spikes_from_the_corners(hidden_sun_frame):
    """The measure sees spikes: shadowing the haze wholly, or summing the open sky, doubles the error."""
    fully_shadowed = eqx.tree_at(lambda e: e.shadow_strength, gr.preset("participating_media"), jnp.asarray(1.0))
    assert _halo_error(fully_shadowed, hidden_sun_frame, 1.0, 1.25) > 0.1
    assert _halo_error(gr.preset("gpu_gems"), hidden_sun_frame, 1.0, 1.25) > 0.1
