"""Seed 001's bloom pyramid and the dilate / erode of the image-space overcast, against NumPy loops."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import godrays_jax as gr
import reference


def _gauss(image, sigma, radius):
    kernel = np.array([math.exp(-0.5 * (t / sigma) ** 2) for t in range(-radius, radius + 1)])
    kernel /= kernel.sum()
    height, width, _ = image.shape
    rows = np.zeros_like(image)
    for row in range(height):
        for col in range(width):
            for t in range(-radius, radius + 1):
                rows[row, col] += kernel[t + radius] * image[min(max(row + t, 0), height - 1), col]
    out = np.zeros_like(image)
    for row in range(height):
        for col in range(width):
            for t in range(-radius, radius + 1):
                out[row, col] += kernel[t + radius] * rows[row, min(max(col + t, 0), width - 1)]
    return out


def _draw(image, height, width):
    """A full-screen quad into a `height x width` target: each pixel reads `image` at its own UV."""
    out = np.zeros((height, width, image.shape[2]))
    for row in range(height):
        for col in range(width):
            x, y = (col + 0.5) * image.shape[1] / width, (row + 0.5) * image.shape[0] / height
            out[row, col] = reference.bilinear(image, x, y)
    return out


def _reference_bloom(image, threshold, weights, sigma, radius):
    """Levels of whole pixels `H // f x W // f`, each drawn from the one before by UV, blurred, drawn back by UV."""
    height, width = image.shape[:2]
    level = np.maximum(image - threshold, 0.0)
    out = np.zeros_like(image)
    for index, factor in enumerate((2, 4, 8, 16)):
        level = _draw(level, max(1, height // factor), max(1, width // factor))
        out += weights[index] * _draw(_gauss(level, sigma, radius), height, width)
    return out


def _reference_dilate(mask, radius, max_radius):
    height, width = mask.shape
    out = np.zeros_like(mask)
    for row in range(height):
        for col in range(width):
            best = mask[row, col]
            for dy in range(-max_radius, max_radius + 1):
                for dx in range(-max_radius, max_radius + 1):
                    weight = min(max(radius + 0.5 - math.hypot(dx, dy), 0.0), 1.0)
                    value = mask[min(max(row + dy, 0), height - 1), min(max(col + dx, 0), width - 1)]
                    best = max(best, value * weight)
            out[row, col] = best
    return out


@pytest.fixture
def hdr(rng):
    image = rng.uniform(0, 1, (11, 19, 3))
    image[3:6, 10:13] = 12.0  # a sun
    return image


def test_bloom_matches_numpy_loop_eager_jit_vmap(hdr):
    weights = (1.0, 0.5, 0.25, 2.0)
    expected = _reference_bloom(hdr, 0.8, np.array(weights), 1.5, 3)
    options = dict(threshold=0.8, weights=weights, sigma=1.5, reach=3)
    np.testing.assert_allclose(gr.bloom(jnp.asarray(hdr, jnp.float32), **options), expected, rtol=1e-4, atol=1e-5)
    jitted = jax.jit(lambda image: gr.bloom(image, **options))(jnp.asarray(hdr, jnp.float32))
    np.testing.assert_allclose(jitted, expected, rtol=1e-4, atol=1e-5)
    batch = jax.vmap(lambda image: gr.bloom(image, **options))(jnp.stack([jnp.asarray(hdr), jnp.asarray(hdr) * 0]))
    np.testing.assert_allclose(batch[0], expected, rtol=1e-4, atol=1e-5)
    assert float(jnp.abs(batch[1]).max()) == 0.0


def test_bloom_of_a_constant_is_the_weighted_bright_pass_and_spreads_far():
    bloom = jax.jit(lambda image: gr.bloom(image, threshold=1.0, weights=(1.0, 2.0, 0.5, 0.25), reach=3))
    constant = bloom(jnp.full((13, 21, 3), 3.0))
    np.testing.assert_allclose(constant, np.full((13, 21, 3), 2.0 * 3.75), rtol=1e-5)
    image = jnp.zeros((32, 32, 1)).at[15:17, 15:17].set(5.0)
    glow = jax.jit(lambda image: gr.bloom(image, threshold=1.0, sigma=2.0, reach=6))(image)
    assert float(glow[0, 16, 0]) > 0.01  # the 1/16 level carries the glow 15 px away
    np.testing.assert_allclose(gr.downsample_box(jnp.ones((5, 7, 2)), 4), np.ones((2, 2, 2)))


def test_bloom_and_gaussian_presets_differ_in_shape(hdr):
    buffers = gr.Buffers(color=jnp.asarray(hdr, jnp.float32), depth=jnp.full(hdr.shape[:2], jnp.inf), coverage=jnp.zeros(hdr.shape[:2]))
    light = jnp.array([0.0, 0.0])
    pyramid = gr.preset("vbex_bloom").layer(buffers, light)
    gaussian = gr.preset("gaussian_bloom").layer(buffers, light)
    assert pyramid.shape == gaussian.shape == hdr.shape
    assert float(pyramid.max()) > 0 and float(gaussian.max()) > 0 and float(jnp.abs(pyramid - gaussian).max()) > 1e-3


@pytest.mark.slow
def test_bloom_gradients(x64, hdr):
    image = jnp.asarray(hdr[:8, 4:16])

    @jax.jit
    def glow(threshold, weights, sigma):
        return gr.bloom(image, threshold=threshold, weights=weights, sigma=sigma, reach=2)

    check_grads(glow, (0.5, jnp.array([1.0, 0.5, 0.3, 0.2]), 1.2), order=1, modes=["rev"], eps=1e-5)
    flat = gr.bloom(jnp.zeros((4, 4, 1)), threshold=1.0)  # nothing passes: zero glow, finite gradients
    assert float(jnp.abs(flat).max()) == 0.0
    grads = jax.grad(lambda t: gr.bloom(jnp.zeros((4, 4, 1)), threshold=t).sum())(1.0)
    assert bool(jnp.isfinite(grads))


@pytest.mark.parametrize("radius", [0.0, 1.0, 1.7, 3.0])
def test_dilate_erode_match_numpy_loop(rng, radius):
    mask = (rng.uniform(0, 1, (11, 13)) > 0.8) * rng.uniform(0.5, 1, (11, 13))
    expected = _reference_dilate(mask, radius, 3)
    np.testing.assert_allclose(gr.dilate(jnp.asarray(mask, jnp.float32), radius=radius, max_radius=3), expected, atol=1e-6)
    jitted = jax.jit(lambda m, r: gr.erode(m, radius=r, max_radius=3))(jnp.asarray(1 - mask, jnp.float32), radius)
    np.testing.assert_allclose(jitted, 1 - expected, atol=1e-6)
    if radius == 0.0:
        np.testing.assert_allclose(expected, mask)


def test_dilate_gradients_and_limits(x64, rng):
    mask = jnp.asarray(rng.uniform(0, 1, (7, 8)) > 0.7, jnp.float64)
    check_grads(jax.jit(lambda r: gr.dilate(mask, radius=r, max_radius=2)), (1.3,), order=1, modes=["rev"], eps=1e-5)
    with pytest.raises(ValueError, match="max_radius"):
        gr.dilate(mask, radius=1.0, max_radius=-1)
    with pytest.raises(Exception, match="radius must lie"):
        jax.block_until_ready(jax.jit(lambda r: gr.dilate(mask, radius=r, max_radius=2))(2.5))  # a GPU raises on use


def test_image_space_overcast_grows_into_occluders():
    coverage = jnp.zeros((24, 32)).at[:, 14:18].set(1.0)  # a pillar through the light
    buffers = gr.Buffers(color=jnp.zeros((24, 32, 3)), depth=jnp.where(coverage > 0, 5.0, jnp.inf), coverage=coverage)
    light = jnp.array([16.0, 12.0])
    plain = gr.SunOvercast(units="px", morphology_reach=4, source_radius=8.0).glow(buffers, light)
    shrunk = gr.SunOvercast(units="px", morphology_reach=4, source_radius=8.0, occluder_shrink=1.0).glow(buffers, light)
    grown = gr.SunOvercast(units="px", morphology_reach=4, source_radius=8.0, source_grow=3.0).glow(buffers, light)
    assert float(plain[12, 14, 3]) == 0.0 and float(shrunk[12, 14, 3]) > 0.3  # the glow seeps into the outline
    assert float(plain[12, 6, 3]) == 0.0 and float(grown[12, 6, 3]) > 0.3  # the source disc grew by 3 px
    effect = gr.SunOvercast(units="px", morphology_reach=4, source_radius=8.0, occluder_shrink=1.5, source_grow=1.5)
    grads = jax.grad(lambda e: e.layer(buffers, light).sum())(effect)
    assert float(grads.occluder_shrink) > 0 and float(grads.source_grow) > 0
