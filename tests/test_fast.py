"""Fast variants (godrays_jax.kernels.fast) against NumPy loops, and the O(image) gradients of the exact kernels."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from frames import slow_where
from jax.test_util import check_grads

import godrays_jax as gr
import reference
from godrays_jax.kernels import fast

RAYS = dict(density=0.45, decay=0.93, weight=0.8, exposure=0.3)


def psnr(actual, expected):
    actual, expected = np.asarray(actual, np.float64), np.asarray(expected, np.float64)
    return 10 * math.log10(expected.max() ** 2 / np.mean((actual - expected) ** 2))


def disc_scene(height, width, light, radius):
    """A bright disc at the light behind a few black occluders (seed 003's occlusion image)."""
    y, x = np.mgrid[0:height, 0:width] + 0.5
    disc = 2 * np.clip(1 - np.hypot(x - light[0], y - light[1]) / radius, 0, 1) ** 2
    occluders = (np.hypot(x - light[0] - 0.3 * radius, y - light[1] - 0.8 * radius) > 0.4 * radius) & (y < 0.8 * height)
    return np.repeat((disc * occluders)[..., None], 3, axis=-1).astype(np.float32)


def multipass_reference(image, light, scale_sets, weight_sets):
    """Each pass: a loop over pixels and taps of `reference.bilinear` on the previous pass."""
    height, width = image.shape[:2]
    for scales, weights in zip(scale_sets, weight_sets):
        out = np.zeros_like(image)
        for row in range(height):
            for col in range(width):
                px, py = col + 0.5, row + 0.5
                for scale, w in zip(scales, weights):
                    out[row, col] += w * reference.bilinear(image, light[0] + (px - light[0]) * scale, light[1] + (py - light[1]) * scale)
        image = out
    return image


def test_scaled_copies_composes_passes_like_the_loop(x64, rng):
    image = rng.random((7, 9, 2))
    light = np.array([3.2, 2.7])
    scale_sets = [np.array([1.0, 0.9, 0.8]), np.array([1.0, 0.7])]
    weight_sets = [np.array([0.5, 0.3, 0.2]), np.array([1.0, 0.6])]
    actual = jnp.asarray(image)
    for scales, weights in zip(scale_sets, weight_sets):
        actual = gr.scaled_copies(actual, light, scales, weights)
    np.testing.assert_allclose(actual, multipass_reference(image, light, scale_sets, weight_sets), rtol=1e-10, atol=1e-12)
    zero = gr.scaled_copies(jnp.asarray(image), light, [1.0, 1.3], [0.5, 1.0], addressing="zero")
    expected = 0.5 * image + np.array([[reference.bilinear(image, 3.2 + (c + 0.5 - 3.2) * 1.3, 2.7 + (r + 0.5 - 2.7) * 1.3, "zero")
                                        for c in range(9)] for r in range(7)])  # fmt: skip
    np.testing.assert_allclose(zero, expected, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("light", [(12.3, 9.1), (31.0, 2.5)], ids=["centre", "near_edge"])
def test_multipass_matches_exact_loop(light):
    image = jnp.asarray(disc_scene(20, 32, light, 6.0))
    light = jnp.asarray(light, jnp.float32)
    exact = gr.radial_rays(image, light, num_samples=128, **RAYS)
    kernel = lambda i, l: fast.radial_rays_multipass(i, l, num_samples=128, **RAYS)
    eager = kernel(image, light)
    assert psnr(eager, exact) > 35
    np.testing.assert_allclose(jax.jit(kernel)(image, light), eager, rtol=1e-5, atol=1e-6)
    batched = jax.vmap(kernel, in_axes=(0, None))(jnp.stack([image, 2 * image]), light)
    np.testing.assert_allclose(batched[1], 2 * eager, rtol=1e-5, atol=1e-6)
    # One pass of one tap is a single comb sample: far worse than 3 x 8.
    single = fast.radial_rays_multipass(image, light, num_samples=128, num_passes=1, num_taps=1, **RAYS)
    assert psnr(single, exact) < psnr(eager, exact) - 10


def test_multipass_total_weight_is_exact_at_zero_density(x64, rng):
    image = jnp.asarray(rng.random((5, 6, 1)))
    options = dict(RAYS, density=0.0)
    exact = gr.radial_rays(image, jnp.array([2.0, 2.0]), num_samples=20, **options)
    approx = fast.radial_rays_multipass(image, jnp.array([2.0, 2.0]), num_samples=20, num_passes=2, num_taps=3, **options)
    np.testing.assert_allclose(approx, exact, rtol=1e-9)


def test_fast_path_quality_and_resolution(rng):
    light = (30.2, 18.7)
    image = jnp.asarray(disc_scene(48, 64, light, 10.0))
    light = jnp.asarray(light, jnp.float32)
    exact = gr.radial_rays(image, light, num_samples=128, **RAYS)
    assert psnr(fast.fast_radial_rays(image, light, num_samples=128, **RAYS), exact) > 35
    half = fast.at_reduced_resolution(image, light, kernel=gr.radial_rays, resolution_factor=2, num_samples=128, **RAYS)
    assert half.shape == image.shape and psnr(half, exact) > 30
    np.testing.assert_array_equal(
        fast.at_reduced_resolution(image, light, kernel=gr.radial_rays, resolution_factor=1, num_samples=8, **RAYS),
        gr.radial_rays(image, light, num_samples=8, **RAYS),
    )


def test_upsample_bilinear_matches_loop_and_keeps_constants(x64, rng):
    small = rng.random((3, 4, 2))
    up = fast.upsample_bilinear(jnp.asarray(small), 2, 5, 7)
    expected = np.array([[reference.bilinear(small, (c + 0.5) / 2, (r + 0.5) / 2) for c in range(7)] for r in range(5)])
    np.testing.assert_allclose(up, expected, rtol=1e-12)
    constant = jnp.full((9, 11, 3), 0.7)
    np.testing.assert_allclose(fast.at_reduced_resolution(constant, jnp.zeros(2), kernel=lambda i, l: i, resolution_factor=4), constant)


def test_jittered_rays_match_loop(x64, rng):
    image = rng.random((6, 7, 3))
    light = np.array([1.3, 4.6])
    noise = np.asarray(fast.interleaved_gradient_noise(6, 7, seed=3, dtype=jnp.float64))
    assert noise.min() >= 0 and noise.max() < 1 and noise.std() > 0.2
    expected = np.zeros_like(image)
    for row in range(6):
        for col in range(7):
            p = np.array([col + 0.5, row + 0.5])
            delta = (p - light) * RAYS["density"] / 5
            colour = image[row, col].copy()
            for i in range(1, 6):
                q = p - (i + noise[row, col] - 0.5) * delta
                colour += RAYS["weight"] * RAYS["decay"] ** (i - 1) * reference.bilinear(image, *q)
            expected[row, col] = colour * RAYS["exposure"]
    actual = fast.radial_rays_jittered(jnp.asarray(image), light, num_samples=5, seed=3, **RAYS)
    np.testing.assert_allclose(actual, expected, rtol=1e-10)


LIGHTS = {
    "on_screen": (4.3, 3.6),
    "near_edge": (8.9, -0.4),
    "off_screen": (-13.0, 20.0),
}


@pytest.mark.parametrize("light", slow_where(list(LIGHTS.values()), {LIGHTS["on_screen"]}), ids=list(LIGHTS))
def test_radial_rays_gradients_float64(x64, rng, light):
    image = jnp.asarray(rng.random((7, 8, 2)))

    def rays(image, light, density, decay, weight, exposure, count):
        return gr.radial_rays(image, light, num_samples=count, max_samples=6, density=density, decay=decay, weight=weight, exposure=exposure)

    args = (image, jnp.asarray(light), 0.37, 0.9, 0.8, 0.6, 4.6)
    check_grads(jax.jit(rays), args, order=1, modes=("rev", "fwd"), eps=1e-6)
    check_grads(jax.jit(lambda i, l, d: gr.radial_rays(i, l, num_samples=5, density=d, decay=0.9, weight=1.0, exposure=1.0)),
                args[:3], order=1, modes=("rev",), eps=1e-6)  # fmt: skip


def test_radial_rays_gradients_with_light_on_a_pixel_centre(x64, rng):
    image = jnp.asarray(rng.random((7, 8, 1)))
    light = jnp.array([3.5, 2.5])
    scalars = lambda i, d, dec, w, e, n: gr.radial_rays(i, light, num_samples=n, max_samples=5, density=d, decay=dec, weight=w, exposure=e)
    check_grads(jax.jit(scalars), (image, 0.37, 0.9, 0.8, 0.6, 3.3), order=1, modes=("rev",), eps=1e-6)
    # Bilinear sampling has kinks at texel centres; a linear ramp has none, so the light gradient is checkable there.
    y, x = np.mgrid[0:7, 0:8] + 0.5
    ramp = jnp.asarray((0.3 * x + 0.2 * y)[..., None])
    check_grads(jax.jit(lambda l: gr.radial_rays(ramp, l, num_samples=4, **RAYS)), (light,), order=1, modes=("rev", "fwd"), eps=1e-6)


@pytest.mark.slow
def test_flare_and_fast_path_gradients_float64(x64, rng):
    masked = jnp.asarray(rng.random((6, 7, 2)))
    light = jnp.array([2.2, 4.1])
    flares = lambda m, l, step, decay, n: gr.scale_iterated_flares(m, l, num_iters=n, max_iters=5, scale_step=step, decay=decay)
    # Compiled once: check_grads evaluates each function many times, and eagerly every evaluation runs op by op.
    check_grads(jax.jit(flares), (masked, light, 1.13, 0.9, 3.4), order=1, modes=("rev", "fwd"), eps=1e-6)
    rays = lambda i, l, d, dec, n: fast.fast_radial_rays(i, l, num_samples=n, density=d, decay=dec, weight=1.0, exposure=0.5, num_passes=2, num_taps=3)
    check_grads(jax.jit(rays), (masked, light, 0.4, 0.92, 7.3), order=1, modes=("rev",), eps=1e-6)


def test_degenerate_inputs_give_finite_values_and_gradients(rng):
    image = jnp.asarray(rng.random((5, 6, 3)), jnp.float32)

    def total(image, light, density, decay, count):
        exact = gr.radial_rays(image, light, num_samples=count, max_samples=4, density=density, decay=decay, weight=1.0, exposure=1.0)
        multipass = fast.radial_rays_multipass(image, light, num_samples=count, density=density, decay=decay, weight=1.0, exposure=1.0, num_passes=2, num_taps=2)
        return jnp.sum(exact) + jnp.sum(multipass)

    # Compiled once for the three cases (eager equals jit: the kernel checklist).
    grad = jax.jit(jax.grad(total, argnums=(0, 1, 2, 3, 4)))
    total = jax.jit(total)
    for light, density, decay, count in [((2.5, 2.5), 0.0, 0.0, 0.0), ((2.5, 2.5), 1.0, 1.0, 4.0), ((1e6, -1e6), 3.0, 0.5, 2.5)]:
        args = (image, jnp.asarray(light, jnp.float32), jnp.float32(density), jnp.float32(decay), jnp.float32(count))
        assert np.isfinite(total(*args))
        assert all(np.all(np.isfinite(g)) for g in jax.tree_util.tree_leaves(grad(*args)))


def _temporary_bytes(function, *args):
    return jax.jit(function).lower(*args).compile().memory_analysis().temp_size_in_bytes


def test_gradient_memory_does_not_grow_with_samples():
    image = jnp.ones((64, 64, 3), jnp.float32)
    light = jnp.array([20.0, 30.0], jnp.float32)

    def grad_of(samples):
        def loss(image, light, density, count):
            rays = gr.radial_rays(image, light, num_samples=count, max_samples=samples, density=density, decay=0.95, weight=1.0, exposure=0.2)
            return jnp.sum(rays**2)

        return jax.grad(loss, argnums=(0, 1, 2, 3))

    image_bytes = image.size * 4
    few, many = (_temporary_bytes(grad_of(n), image, light, 0.5, float(n)) for n in (4, 64))
    assert many < few + 2 * image_bytes, (few, many)
    assert many < 40 * image_bytes


def test_godrays_method_selects_the_fast_path(rng):
    buffers = gr.Buffers(
        color=jnp.asarray(rng.random((24, 32, 3)), jnp.float32),
        depth=jnp.full((24, 32), jnp.inf, jnp.float32),
        coverage=jnp.zeros((24, 32), jnp.float32),
    )
    light = jnp.array([12.0, 9.0], jnp.float32)
    exact = gr.GodRays(flare_size=6.0, units="px").layer(buffers, light)
    quick = gr.GodRays(flare_size=6.0, units="px", method="fast").layer(buffers, light)
    assert psnr(quick, exact) > 30
    assert gr.effect_from_dict(gr.effect_to_dict(gr.GodRays(method="fast"))).method == "fast"
    with pytest.raises(ValueError, match="method"):
        gr.GodRays(method="quick")


def test_fast_kernels_reject_bad_static_options():
    image = jnp.ones((4, 4, 3))
    with pytest.raises(ValueError, match="num_passes"):
        fast.radial_rays_multipass(image, jnp.zeros(2), num_samples=8, num_passes=0, **RAYS)
    with pytest.raises(ValueError, match="factor"):
        fast.fast_radial_rays(image, jnp.zeros(2), num_samples=8, resolution_factor=1.5, **RAYS)
    with pytest.raises(ValueError, match="num_samples"):
        fast.radial_rays_multipass(image, jnp.zeros(2), num_samples=jnp.ones(2), **RAYS)
