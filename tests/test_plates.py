"""Frames without depth: the open sky from the frame's bright parts or its alpha; which presets run on them."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from frames import slow_where

import godrays_jax as gr
from godrays_jax.effects.base import needs_depth
from godrays_jax.effects.plates import buffers_without_depth
from godrays_jax.effects.presets import PRESETS, presets_without_depth
from godrays_jax.kernels.masks import bright_sky


def _bright_sky_loop(luminance, light_xy, threshold=0.5, softness=0.2, window=0.15):
    """Slow and obvious: the window's pixels listed one by one, their percentiles, each pixel's place on the log scale."""
    height, width = luminance.shape
    cx = min(max(light_xy[0], 0.5), width - 0.5)
    cy = min(max(light_xy[1], 0.5), height - 0.5)
    radius = window * max(height, width)
    near = [luminance[r, c] for r in range(height) for c in range(width)
            if (c + 0.5 - cx) ** 2 + (r + 0.5 - cy) ** 2 <= radius**2]  # fmt: skip
    low, high = np.quantile(near, [0.05, 0.9])
    low = min(max(low, high / 1000), high / 16)
    out = np.zeros_like(luminance, dtype=np.float64)
    for r in range(height):
        for c in range(width):
            if high <= 0 or luminance[r, c] <= 0:
                continue
            place = math.log(luminance[r, c] / low) / math.log(high / low)
            t = min(max((place - (threshold - softness / 2)) / softness, 0.0), 1.0)
            out[r, c] = t * t * (3 - 2 * t)
    return out


def _scene(rng, height=24, width=40):
    """A bright sky with a sun, dark trunks across it, a dark ground."""
    luminance = rng.uniform(0.3, 0.6, (height, width))
    luminance[:, 8:11] = luminance[:, 25:27] = 0.01
    luminance[16:, :] = 0.02
    luminance[5:8, 18:21] = 5.0
    return luminance


@pytest.mark.parametrize("light", [(19.5, 6.5), (9.5, 12.0), (-30.0, 4.0), (20.0, 200.0)])
def test_bright_sky_matches_loop(rng, light):
    luminance = _scene(rng)
    expected = _bright_sky_loop(luminance, light)
    got = np.asarray(bright_sky(jnp.asarray(luminance, jnp.float32), jnp.asarray(light)))
    np.testing.assert_allclose(got, expected, atol=2e-5)


def test_bright_sky_finds_sky_and_occluders(rng):
    luminance = _scene(rng)
    sky = np.asarray(bright_sky(jnp.asarray(luminance, jnp.float32), jnp.asarray([19.5, 6.5])))
    assert np.all(sky[:16, 12:24] > 0.99) and np.all(sky[:, 8:11] < 0.01) and np.all(sky[16:] < 0.01)


def test_bright_sky_degenerate(rng):
    black = np.asarray(bright_sky(jnp.zeros((6, 9)), jnp.asarray([4.5, 3.0])))
    assert np.all(black == 0)
    flat = np.asarray(bright_sky(jnp.full((6, 9), 0.7), jnp.asarray([4.5, 3.0])))
    np.testing.assert_allclose(flat, 1.0)  # a window of open sky alone
    under_jit = jax.jit(bright_sky)(jnp.asarray(_scene(rng), jnp.float32), jnp.asarray([4.0, 3.0]))
    assert np.all(np.isfinite(np.asarray(under_jit)))
    with pytest.raises(ValueError, match="luminance"):
        bright_sky(jnp.zeros((2, 3, 3)), jnp.asarray([1.0, 1.0]))


def _photo(rng):
    luminance = _scene(rng)
    return np.repeat(luminance[..., None], 3, axis=-1).astype(np.float32) * np.asarray([1.0, 0.9, 0.7], np.float32)


def test_alpha_is_coverage(rng):
    photo = _photo(rng)
    alpha = np.ones(photo.shape[:2], np.float32)
    alpha[:10] = 0.25
    plate = buffers_without_depth(photo, (19.5, 6.5), alpha=alpha)
    assert plate.depth is None
    np.testing.assert_array_equal(np.asarray(plate.coverage), alpha)
    opaque = buffers_without_depth(photo, (19.5, 6.5), alpha=np.ones_like(alpha))
    luminance = photo @ np.asarray([0.2126, 0.7152, 0.0722], np.float32)
    np.testing.assert_allclose(np.asarray(opaque.coverage), 1 - _bright_sky_loop(luminance, (19.5, 6.5)), atol=2e-5)


def test_presets_without_depth():
    """The shaft presets run without depth; the medium and the lens dirt measure distance."""
    without = presets_without_depth()
    assert {"gpu_gems", "xna_crepuscular", "kbengine_flares", "galaxy_vls", "sun_overcast"} <= set(without)
    assert {"participating_media", "physically_based", "vbex_lens_dirt"}.isdisjoint(without)
    assert all(needs_depth(PRESETS[name]()) != (name in without) for name in PRESETS)


@pytest.mark.parametrize(
    "name", slow_where(["gpu_gems", "xna_crepuscular", "kbengine_flares", "sun_overcast"], {"gpu_gems"})
)
def test_shaft_presets_run_on_a_photo(rng, name):
    photo = _photo(rng)
    light = jnp.asarray([19.5, 6.5])
    plate = buffers_without_depth(photo, light)
    effect = gr.preset(name)
    image = eqx.filter_jit(lambda e, b: e(b, light, light_depth=30.0))(effect, plate)
    assert np.all(np.isfinite(np.asarray(image)))
    added = np.asarray(image) - photo
    assert added[:16, 12:24].mean() > 1e-3  # light added around the sun
    grads = jax.grad(lambda e: jnp.mean(e.layer(plate, light)))(effect)
    assert all(np.all(np.isfinite(np.asarray(g))) for g in jax.tree.leaves(eqx.filter(grads, eqx.is_inexact_array)))


def test_effects_that_need_depth_say_so(rng):
    plate = buffers_without_depth(_photo(rng), (19.5, 6.5))
    with pytest.raises(ValueError, match=r"ScatteringFog needs the frame's depth.*GodRays"):
        gr.preset("participating_media")(plate, jnp.asarray([19.5, 6.5]))
    with pytest.raises(ValueError, match=r"LensDirt needs the frame's depth"):
        gr.preset("vbex_lens_dirt")(plate, jnp.asarray([19.5, 6.5]))
