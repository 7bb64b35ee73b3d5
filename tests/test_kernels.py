"""Kernels against the slow NumPy loops in reference.py: eager, jit, vmap, gradients, degenerate inputs."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import godrays_jax as gr
from godrays_jax.kernels import rays
from godrays_jax.kernels.copy_sums import cpu_loop
from godrays_jax.kernels.copy_sums.cpu_loop import copy_sums_cpu
from godrays_jax.kernels.copy_sums.gpu_loop import copy_sums_gpu
import reference

HEIGHT, WIDTH = 9, 13
LIGHTS = {
    "on_screen": (5.3, 3.7),
    "pixel_centre": (4.5, 2.5),
    "near_edge": (0.1, 8.9),
    "off_screen": (-6.0, 20.0),
    "far_off_screen": (300.0, -200.0),
}
RAY_OPTIONS = dict(density=0.8, decay=0.93, weight=0.9, exposure=0.2)


def assert_close(actual, expected, rtol):
    """Agreement relative to the output's largest magnitude, as the issue states it."""
    actual, expected = np.asarray(actual), np.asarray(expected)
    assert actual.shape == expected.shape
    assert np.all(np.isfinite(actual))
    scale = max(np.max(np.abs(expected)), 1e-30)
    assert np.max(np.abs(actual - expected)) <= rtol * scale, np.max(np.abs(actual - expected)) / scale


def random_image(rng, channels=3, height=HEIGHT, width=WIDTH):
    return rng.uniform(0.0, 2.0, size=(height, width, channels))


@pytest.mark.parametrize("light", LIGHTS.values(), ids=LIGHTS.keys())
def test_radial_rays_matches_loop_float64(x64, rng, light):
    image = random_image(rng)
    expected = reference.radial_rays(image, light, 12, **RAY_OPTIONS)
    actual = gr.radial_rays(jnp.asarray(image), jnp.asarray(light), num_samples=12, **RAY_OPTIONS)
    assert actual.dtype == jnp.float64
    assert_close(actual, expected, 1e-6)


@pytest.mark.parametrize("light", [LIGHTS["on_screen"], LIGHTS["off_screen"]])
def test_radial_rays_float32_eager_jit_vmap(rng, light):
    images = random_image(rng, channels=1)[None].repeat(2, 0) * np.array([1.0, 0.5])[:, None, None, None]
    expected = reference.radial_rays(images[0], light, 10, **RAY_OPTIONS)
    kernel = lambda image, light_xy: gr.radial_rays(image, light_xy, num_samples=10, **RAY_OPTIONS)
    image32 = jnp.asarray(images[0], jnp.float32)
    light32 = jnp.asarray(light, jnp.float32)
    assert_close(kernel(image32, light32), expected, 1e-4)
    assert_close(jax.jit(kernel)(image32, light32), expected, 1e-4)
    batched = jax.vmap(kernel, in_axes=(0, None))(jnp.asarray(images, jnp.float32), light32)
    assert_close(batched[1], 0.5 * expected, 1e-4)


def test_radial_rays_vmap_over_lights(rng):
    image = jnp.asarray(random_image(rng), jnp.float32)
    lights = jnp.asarray([LIGHTS["on_screen"], LIGHTS["near_edge"]], jnp.float32)
    batched = jax.vmap(lambda l: gr.radial_rays(image, l, num_samples=8, **RAY_OPTIONS))(lights)
    for index in range(2):
        assert_close(batched[index], reference.radial_rays(np.asarray(image), np.asarray(lights[index]), 8, **RAY_OPTIONS), 1e-4)


def test_radial_rays_gradients(x64, rng):
    image = jnp.asarray(random_image(rng, height=6, width=7))

    def rays(image, light, density, decay, weight, exposure):
        return gr.radial_rays(image, light, num_samples=6, density=density, decay=decay, weight=weight, exposure=exposure)

    args = (image, jnp.asarray([2.3, 1.6]), 0.7, 0.9, 1.1, 0.3)
    check_grads(jax.jit(rays), args, order=1, modes=("rev",), eps=1e-6)


def test_radial_rays_relaxed_count_equals_integer_kernel(x64, rng):
    image = jnp.asarray(random_image(rng))
    light = jnp.asarray(LIGHTS["on_screen"])
    exact = gr.radial_rays(image, light, num_samples=7, **RAY_OPTIONS)
    relaxed = gr.radial_rays(image, light, num_samples=jnp.asarray(7.0), max_samples=12, **RAY_OPTIONS)
    np.testing.assert_array_equal(np.asarray(exact), np.asarray(relaxed))


def test_radial_rays_relaxed_count_gradient_is_informative(x64, rng):
    image = jnp.asarray(random_image(rng))
    light = jnp.asarray(LIGHTS["on_screen"])

    def total(count):
        return jnp.sum(gr.radial_rays(image, light, num_samples=count, max_samples=12, **RAY_OPTIONS))

    gradient = jax.grad(total)(7.4)
    assert np.isfinite(gradient) and gradient != 0.0
    # More samples of a positive image add light: the sum grows between 7 and 8.
    assert total(8.0) > total(7.0)
    check_grads(jax.jit(total), (7.4,), order=1, modes=("rev", "fwd"), eps=1e-6)


def test_radial_rays_degenerate_cases_are_finite(rng):
    image = jnp.asarray(random_image(rng), jnp.float32)
    light = jnp.asarray(LIGHTS["pixel_centre"], jnp.float32)

    def total(light, density):
        return jnp.sum(gr.radial_rays(image, light, num_samples=8, density=density, decay=0.9, weight=1.0, exposure=0.1))

    for density in (0.8, 0.0):
        value, grads = jax.value_and_grad(total, argnums=(0, 1))(light, jnp.float32(density))
        assert np.isfinite(value) and all(np.all(np.isfinite(g)) for g in grads)
    # Zero-size step: every sample reads the pixel itself.
    zero_step = gr.radial_rays(image, light, num_samples=4, density=0.0, decay=0.5, weight=1.0, exposure=1.0)
    np.testing.assert_allclose(zero_step, image * (1 + 1 + 0.5 + 0.25 + 0.125), rtol=1e-6)
    # The pixel under the light samples only itself.
    centre = gr.radial_rays(image, light, num_samples=4, density=1.0, decay=0.5, weight=1.0, exposure=1.0)
    np.testing.assert_allclose(centre[2, 4], image[2, 4] * 2.875, rtol=1e-6)


WINDOW_LIGHTS = {
    "centre": (151.3, 80.6),
    "pixel_centre": (100.5, 40.5),
    "near_corner": (3.2, 156.9),
    "off_left_disc_visible": (-4.0, 80.0),
    "off_top_disc_visible": (150.0, -6.5),
    "far_off": (4000.0, -900.0),
}


@pytest.mark.parametrize("light", WINDOW_LIGHTS.values(), ids=WINDOW_LIGHTS.keys())
def test_radial_rays_on_a_window_around_a_compact_source_equal_the_full_loop(light):
    height, width, radius = 160, 300, 10.0
    light = jnp.asarray(light, jnp.float32)
    occluders = (np.indices((height, width)).sum(0) % 7 > 1).astype(np.float32)[..., None]
    image = gr.light_source_mask(height, width, light, flare_size=radius) * jnp.asarray(occluders) * jnp.ones(3)
    for density, num_samples, max_samples in [(0.5, 32, None), (0.7, 20.5, 24)]:
        options = dict(num_samples=num_samples, density=density, decay=0.95, weight=1.0, exposure=0.2,
                       max_samples=max_samples)  # fmt: skip
        full = gr.radial_rays(image, light, **options)
        windowed = jax.jit(lambda im, xy: gr.radial_rays(im, xy, source_radius=radius, **options))(image, light)
        np.testing.assert_allclose(windowed, full, rtol=1e-5, atol=1e-5 * float(jnp.max(full) + 1))
    # The window really is smaller than the frame here, also under jit with
    # the parameters closed over; traced or unbounded scales use the whole frame.
    # An image that breaks the promise (ones everywhere) shows the window: the rays are 0 outside it.
    ones, centre = jnp.ones((height, width, 3), jnp.float32), jnp.asarray(WINDOW_LIGHTS["centre"], jnp.float32)
    options = {"source_radius": radius, "decay": 0.95, "weight": 1.0, "exposure": 0.2}
    whole_frame = ((0, height), (0, width))

    def support(density, num_samples=32, max_samples=None):
        return nonzero_box(gr.radial_rays(ones, centre, density=density, num_samples=num_samples,
                                          max_samples=max_samples, **options))  # fmt: skip

    # Reach ceil((10 + 2) / 0.5) = 24 px around the light's pixel (151, 80), 50 px square.
    assert support(0.5) == ((80 - 24, 80 + 26), (151 - 24, 151 + 26))
    # Relaxed: the last live sample (21 of 24) sits at scale 1 - 21 * 0.5 / 20.5: reach 25 px.
    assert support(jnp.float32(0.5), jnp.float32(20.5), 24) == ((80 - 25, 80 + 27), (151 - 25, 151 + 27))
    assert support(1.0) == whole_frame, "the last sample lands on the light (scale 0): unbounded"
    assert support(-0.5) == whole_frame, "scales above 1: unbounded"
    traced = jax.jit(lambda d: gr.radial_rays(ones, centre, density=d, num_samples=32, **options))(0.5)
    assert nonzero_box(traced) == whole_frame
    density = jnp.float32(0.5)  # closed over, as an effect's fields are: concrete at trace time
    closed_over = jax.jit(lambda im, xy: gr.radial_rays(im, xy, density=density, num_samples=32, **options))
    assert nonzero_box(closed_over(ones, centre)) == ((80 - 24, 80 + 26), (151 - 24, 151 + 26))


def nonzero_box(image):
    """`((top, bottom), (left, right))`, bottom and right exclusive, of the box around the image's non-zero pixels."""
    rows, columns = np.nonzero(np.any(np.asarray(image) != 0, axis=-1))
    return (int(rows.min()), int(rows.max()) + 1), (int(columns.min()), int(columns.max()) + 1)


@pytest.mark.slow
def test_radial_rays_window_gradients(x64):
    height, width = 60, 90
    light = jnp.asarray([40.3, 22.6])
    image = gr.light_source_mask(height, width, light, flare_size=4.0, dtype=jnp.float64) * jnp.ones(2)
    options = dict(num_samples=8, density=0.5, decay=0.9, weight=1.0, exposure=0.3)

    def windowed(im, xy):
        return gr.radial_rays(im, xy, source_radius=4.0, **options)

    # Compiled: check_grads evaluates many times, and eagerly each evaluation runs op by op.
    check_grads(jax.jit(lambda im: windowed(im, light)), (image,), order=1, modes=["fwd", "rev"])
    # The light's derivative (bilinear sampling is only piecewise smooth in
    # the positions, so compare with the whole-frame loop, both modes).
    def loss(xy, **window):
        return jnp.sum(gr.radial_rays(image, xy, **window, **options) ** 2)

    full = jax.jit(jax.grad(loss))(light)
    assert np.all(np.abs(full) > 1e-3)
    windowed_loss = functools.partial(loss, source_radius=4.0)
    np.testing.assert_allclose(jax.jit(jax.grad(windowed_loss))(light), full, rtol=1e-9)
    np.testing.assert_allclose(jax.jit(jax.jacfwd(windowed_loss))(light), full, rtol=1e-9)
    with pytest.raises(ValueError, match="source_radius"):
        gr.radial_rays(image, light, source_radius=-1.0, **options)


def test_radial_rays_rejects_bad_arguments(rng):
    image = jnp.ones((4, 5, 3))
    options = dict(density=0.5, decay=0.9, weight=1.0, exposure=0.1)
    with pytest.raises(ValueError, match="image"):
        gr.radial_rays(jnp.ones((4, 5)), jnp.zeros(2), num_samples=4, **options)
    with pytest.raises(ValueError, match="light_xy"):
        gr.radial_rays(image, jnp.zeros(3), num_samples=4, **options)
    with pytest.raises(ValueError, match="num_samples"):
        gr.radial_rays(image, jnp.zeros(2), num_samples=0, **options)
    with pytest.raises(ValueError, match="max_samples"):
        gr.radial_rays(image, jnp.zeros(2), num_samples=4.5, **options)
    with pytest.raises(ValueError, match="density"):
        gr.radial_rays(image, jnp.zeros(2), num_samples=4, **{**options, "density": jnp.ones(2)})
    with pytest.raises(Exception, match="max_samples=8"):
        gr.radial_rays(image, jnp.zeros(2), num_samples=jnp.asarray(9.0), max_samples=8, **options).block_until_ready()


@pytest.mark.parametrize("light", LIGHTS.values(), ids=LIGHTS.keys())
def test_scale_iterated_flares_matches_loop(x64, rng, light):
    masked = random_image(rng)
    expected = reference.scale_iterated_flares(masked, light, 6, 1.13, decay=0.9)
    actual = gr.scale_iterated_flares(jnp.asarray(masked), jnp.asarray(light), num_iters=6, scale_step=1.13, decay=0.9)
    assert_close(actual, expected, 1e-6)


def test_scale_iterated_flares_jit_vmap_relaxed_and_gradients(x64, rng):
    masked = jnp.asarray(random_image(rng, height=6, width=7))
    light = jnp.asarray([3.2, 2.9])
    kernel = lambda m, l, step: gr.scale_iterated_flares(m, l, num_iters=5, scale_step=step)
    eager = kernel(masked, light, 1.1)
    np.testing.assert_allclose(jax.jit(kernel)(masked, light, 1.1), eager, rtol=1e-12)
    batched = jax.vmap(kernel, in_axes=(0, None, None))(jnp.stack([masked, 2 * masked]), light, 1.1)
    np.testing.assert_allclose(batched[1], 2 * eager, rtol=1e-12)
    relaxed = gr.scale_iterated_flares(masked, light, num_iters=jnp.asarray(5.0), max_iters=9, scale_step=1.1)
    np.testing.assert_array_equal(relaxed, eager)
    half = gr.scale_iterated_flares(masked, light, num_iters=jnp.asarray(5.5), max_iters=9, scale_step=1.1)
    six = gr.scale_iterated_flares(masked, light, num_iters=6, scale_step=1.1)
    np.testing.assert_allclose(half, 0.5 * (eager + six), rtol=1e-12)
    check_grads(jax.jit(kernel), (masked, light, 1.1), order=1, modes=("rev",), eps=1e-6)
    count_grad = jax.grad(
        lambda n: jnp.sum(gr.scale_iterated_flares(masked, light, num_iters=n, max_iters=9, scale_step=1.1))
    )(5.5)
    assert np.isfinite(count_grad) and count_grad > 0


def _flare_outs_into_loop(masked, light, target, num_iters, scale_step, decay):
    """Each target pixel's centre, in full-resolution pixels, read from every copy of the full-resolution texture."""
    height, width = masked.shape[:2]
    out = np.zeros((*target, masked.shape[2]))
    for row in range(target[0]):
        for col in range(target[1]):
            x, y = (col + 0.5) * width / target[1], (row + 0.5) * height / target[0]
            for k in range(num_iters):
                scale = scale_step**k
                out[row, col] += decay**k * reference.bilinear(
                    masked, light[0] + (x - light[0]) / scale, light[1] + (y - light[1]) / scale, addressing="zero"
                )
    return out


@pytest.mark.parametrize("target", [(5, 7), (3, 4)])
def test_flare_outs_into_a_smaller_target_match_loop_jit_vmap_and_gradients(x64, rng, target):
    """kbEngine's low-resolution target: the full-resolution texture sampled at the target's pixel centres."""
    masked = jnp.asarray(random_image(rng, height=11, width=15))
    light = jnp.asarray([6.2, 4.9])
    kernel = lambda m, l, step: rays.flare_outs_into(m, l, target_shape=target, num_iters=5, scale_step=step, decay=0.9)
    expected = _flare_outs_into_loop(np.asarray(masked), np.asarray(light), target, 5, 1.13, 0.9)
    assert_close(kernel(masked, light, 1.13), expected, 1e-10)
    np.testing.assert_allclose(jax.jit(kernel)(masked, light, 1.13), expected, rtol=1e-10)
    batched = jax.vmap(kernel, in_axes=(0, None, None))(jnp.stack([masked, 2 * masked]), light, 1.13)
    np.testing.assert_allclose(batched[1], 2 * expected, rtol=1e-10)
    check_grads(jax.jit(kernel), (masked, light, 1.13), order=1, modes=("rev",), eps=1e-6)
    grad_of_vmap = jax.grad(lambda step: jnp.sum(jax.vmap(kernel, in_axes=(0, None, None))(masked[None], light, step)))
    assert np.isfinite(float(grad_of_vmap(1.13)))
    relaxed = rays.flare_outs_into(masked, light, target_shape=target, num_iters=jnp.asarray(5.0), max_iters=9,
                              scale_step=1.13, decay=0.9)  # fmt: skip
    np.testing.assert_allclose(relaxed, expected, rtol=1e-10)


def test_scale_iterated_flares_copy_zero_is_the_texture(rng):
    masked = jnp.asarray(random_image(rng), jnp.float32)
    np.testing.assert_allclose(
        gr.scale_iterated_flares(masked, jnp.asarray([-40.0, 7.0]), num_iters=1, scale_step=1.5), masked, rtol=1e-6
    )


@pytest.mark.parametrize("passes", [1, 2])
def test_poisson_blur_matches_loop(x64, rng, passes):
    image = random_image(rng)
    expected = reference.poisson_blur(image, 0.07, passes)
    assert_close(gr.poisson_blur(jnp.asarray(image), blur_power=0.07, num_passes=passes), expected, 1e-6)
    assert_close(jax.jit(lambda i: gr.poisson_blur(i, blur_power=0.07, num_passes=passes))(jnp.asarray(image)), expected, 1e-6)


def test_poisson_blur_constant_vmap_relaxed_and_gradients(x64, rng):
    constant = jnp.full((5, 6, 3), 0.7)
    np.testing.assert_allclose(gr.poisson_blur(constant, blur_power=0.3, num_passes=3), constant, rtol=1e-12)
    image = jnp.asarray(random_image(rng, height=5, width=6))
    one = gr.poisson_blur(image, blur_power=0.05, num_passes=1)
    two = gr.poisson_blur(image, blur_power=0.05, num_passes=2)
    relaxed = lambda p: gr.poisson_blur(image, blur_power=0.05, num_passes=p, max_passes=3)
    np.testing.assert_array_equal(relaxed(jnp.asarray(2.0)), two)
    np.testing.assert_allclose(relaxed(jnp.asarray(1.25)), 0.75 * one + 0.25 * two, rtol=1e-12)
    np.testing.assert_array_equal(relaxed(jnp.asarray(0.0)), image)
    batched = jax.vmap(lambda i: gr.poisson_blur(i, blur_power=0.05))(jnp.stack([image, image * 3]))
    np.testing.assert_allclose(batched[1], 3 * one, rtol=1e-12)
    check_grads(jax.jit(lambda i, b: gr.poisson_blur(i, blur_power=b, num_passes=2)), (image, 0.05), order=1, modes=("rev",), eps=1e-6)
    check_grads(jax.jit(lambda p: jnp.sum(relaxed(p) ** 2)), (1.3,), order=1, modes=("rev",), eps=1e-6)


def test_gaussian_blur_matches_loop_and_keeps_constants(x64, rng):
    image = random_image(rng)
    assert_close(gr.gaussian_blur(jnp.asarray(image), sigma=1.3, reach=3), reference.gaussian_blur(image, 1.3, 3), 1e-6)
    constant = jnp.full((4, 3, 1), 2.5)
    np.testing.assert_allclose(gr.gaussian_blur(constant, sigma=2.0), constant, rtol=1e-12)
    check_grads(jax.jit(lambda i, s: gr.gaussian_blur(i, sigma=s, reach=2)), (jnp.asarray(image[:5, :6]), 0.9), order=1, modes=("rev",))
    with pytest.raises(ValueError, match="reach"):
        jax.jit(lambda s: gr.gaussian_blur(jnp.asarray(image), sigma=s))(1.0)


def test_sky_flare_coverage_and_depth_masks():
    depth = jnp.asarray([[1.0, jnp.inf], [5.0, 1e9]])
    np.testing.assert_array_equal(gr.sky_mask(depth), [[0, 1], [0, 0]])
    np.testing.assert_array_equal(gr.sky_mask(depth, sky_depth=1e9), [[0, 1], [0, 1]])
    np.testing.assert_allclose(gr.coverage_mask(jnp.asarray([[0.0, 0.25], [1.0, 1.5]])), [[1, 0.75], [0, 0]])
    flare = jnp.arange(12.0).reshape(2, 2, 3)
    np.testing.assert_array_equal(gr.flare_mask(flare, gr.sky_mask(depth)), flare * np.array([[0, 1], [0, 0]])[..., None])
    np.testing.assert_array_equal(gr.depth_test_mask(depth, light_depth=4.0, bias=0.5), [[0, 1], [1, 1]])
    with pytest.raises(ValueError, match="sky"):
        gr.flare_mask(flare, jnp.ones((3, 2)))
    with pytest.raises(ValueError, match="depth"):
        gr.sky_mask(jnp.ones((2, 2, 1)))


def test_light_source_mask_matches_loop_and_is_off_when_behind():
    light = (6.2, 3.1)
    mask = gr.light_source_mask(8, 11, jnp.asarray(light), flare_size=4.0)
    for row in range(8):
        for col in range(11):
            distance = np.hypot(col + 0.5 - light[0], row + 0.5 - light[1])
            expected = 2 * max(0.0, 1 - distance / 4.0) ** 2
            assert abs(float(mask[row, col, 0]) - expected) < 1e-5
    assert float(jnp.max(gr.light_source_mask(8, 11, jnp.asarray(light), flare_size=4.0, light_in_front=False))) == 0.0
    # A texture covers the square light +- radius.
    texture = jnp.ones((4, 4, 3)) * 0.5
    textured = gr.light_source_mask(8, 11, jnp.asarray(light), flare_size=4.0, texture=texture)
    np.testing.assert_allclose(textured[3, 6], [0.5, 0.5, 0.5])
    off = gr.light_source_mask(8, 11, jnp.asarray([-50.0, 3.0]), flare_size=4.0)
    assert float(jnp.max(off)) == 0.0
    grad = jax.grad(lambda l, r: jnp.sum(gr.light_source_mask(8, 11, l, flare_size=r)), argnums=(0, 1))(
        jnp.asarray([6.5, 3.5]), 4.0
    )
    assert all(np.all(np.isfinite(g)) for g in grad)


def test_bright_pass():
    image = jnp.asarray([[[0.1, 0.5, 2.0]]])
    np.testing.assert_allclose(gr.bright_pass(image, threshold=0.25), [[[0.0, (0.5 - 0.25) / 0.75, 1.0]]], rtol=1e-6)


def test_blend_modes():
    scene = jnp.asarray([[[0.2, 0.4, 0.6, 0.5]]])
    layer = jnp.asarray([[[0.5, 0.5, 0.5]]])
    np.testing.assert_allclose(gr.add(scene, layer), [[[0.7, 0.9, 1.1, 0.5]]], rtol=1e-6)
    np.testing.assert_allclose(gr.multiply(scene, layer), [[[0.1, 0.2, 0.3, 0.5]]], rtol=1e-6)
    np.testing.assert_allclose(gr.screen(scene, layer), [[[0.6, 0.7, 0.8, 0.5]]], rtol=1e-6)
    rgba = jnp.asarray([[[1.0, 0.0, 0.0, 0.25]]])
    np.testing.assert_allclose(
        gr.alpha_over(scene, rgba), [[[0.25 + 0.15, 0.3, 0.45, 0.25 + 0.5 * 0.75]]], rtol=1e-6
    )
    grey = gr.add(scene[..., :3], jnp.asarray([[[1.0]]]))
    np.testing.assert_allclose(grey, [[[1.2, 1.4, 1.6]]], rtol=1e-6)
    np.testing.assert_allclose(gr.blend(scene, layer, mode="multiply"), gr.multiply(scene, layer))
    with pytest.raises(ValueError, match="mode"):
        gr.blend(scene, layer, mode="overlay")
    with pytest.raises(ValueError, match="layer"):
        gr.add(scene, jnp.ones((2, 1, 3)))


def test_sample_bilinear_pixel_centres_and_addressing():
    image = jnp.arange(6.0).reshape(2, 3, 1)
    x = jnp.asarray([0.5, 2.5, 1.0, -5.0, 3.0])
    y = jnp.asarray([0.5, 1.5, 0.5, 0.5, 0.5])
    np.testing.assert_allclose(gr.sample_bilinear(image, x, y)[:, 0], [0.0, 5.0, 0.5, 0.0, 2.0])
    np.testing.assert_allclose(gr.sample_bilinear(image, x, y, addressing="zero")[:, 0], [0.0, 5.0, 0.5, 0.0, 1.0])
    with pytest.raises(ValueError, match="addressing"):
        gr.sample_bilinear(image, x, y, addressing="wrap")


@pytest.mark.parametrize(
    "shape, copies",
    [((2, 3, 1), 3), ((2, 2, 2), 6), pytest.param((6, 7, 3), 6, marks=pytest.mark.slow)],
    ids=["tiny_image_few_copies", "tiny_image_many_weights", "large_image_many_weights"],
)
def test_scaled_copies_gradients_of_every_argument(x64, rng, shape, copies):
    """Inputs of few numbers are differentiated inside the sample loop (forward mode), the others by a
    tangent loop that reverse mode transposes; the shapes here take each path for the image and weights."""
    image = jnp.asarray(rng.uniform(0.2, 2.0, size=shape))
    args = (image, jnp.asarray([1.37, 0.81]), jnp.asarray([0.97, 0.83, 0.61, 0.47, 1.21, 0.33][:copies]),
            jnp.asarray([0.9, 0.5, 0.7, 0.3, 0.2, 0.6][:copies]))  # fmt: skip
    for addressing in ("clamp", "zero"):
        kernel = jax.jit(lambda *a, addressing=addressing: gr.scaled_copies(*a, addressing=addressing))
        check_grads(kernel, args, order=1, modes=("fwd", "rev"), eps=1e-6)


# Each count (below, between and at multiples of the step) and each addressing at least once; at a multiple both.
@pytest.mark.parametrize(
    ("copies", "addressing"),
    [
        (1, "clamp"),
        *(pytest.param(*case, marks=pytest.mark.slow) for case in [(11, "zero"), (16, "clamp"), (16, "zero")]),
    ],
)
def test_gpu_copy_sums_equal_cpu_copy_sums(x64, rng, copies, addressing):
    """A GPU sums `COPIES_PER_STEP` copies per loop step from 2-D corner gathers, a CPU one copy per step through
    transposes (`lax.platform_dependent` picks): every sum the derivatives use must agree, here on the CPU, for
    copy counts below, between and at multiples of the step, lights on and off screen, jitted and under vmap
    (the CPU loop eagerly)."""

    image = jnp.asarray(random_image(rng))
    derivative_image = jnp.asarray(random_image(rng, channels=2))
    scales = jnp.asarray(rng.uniform(-0.3, 1.4, copies))
    weights = jnp.asarray(rng.uniform(0.1, 1.0, copies))
    jacobians = (jnp.asarray(rng.normal(size=(copies, 2))), jnp.asarray(rng.normal(size=(copies, 3))))
    # One compiled function per loop and output set, shared by both lights (the light is traced).
    with_derivatives, values_only = (
        {loop: jax.jit(functools.partial(loop, addressing, derivatives)) for loop in (copy_sums_gpu, copy_sums_cpu)}
        for derivatives in (True, False)
    )  # fmt: skip
    for light in (LIGHTS["on_screen"], LIGHTS["off_screen"]):
        args = (image, derivative_image, jnp.asarray(light), scales, weights, jacobians)
        expected = with_derivatives[copy_sums_cpu](*args)
        actual = with_derivatives[copy_sums_gpu](*args)
        total, derivative_total, scale_sums, weight_sums, light_sums = expected
        assert total.shape == (WIDTH, 3 * HEIGHT) and scale_sums.shape == (WIDTH, 3 * HEIGHT, 2)
        assert weight_sums.shape == (WIDTH, 3 * HEIGHT, 3)
        for got, want in zip(jax.tree.leaves(actual), jax.tree.leaves(expected), strict=True):
            assert_close(got, want, 1e-12)
        without = values_only[copy_sums_gpu](image, None, *args[2:5], (None, None))
        assert without[1:] == (None, None, None, None)
        assert_close(without[0], total, 1e-12)
        for only in ((jacobians[0], None), (None, jacobians[1])):
            for loop in (copy_sums_gpu, copy_sums_cpu):
                sums = values_only[loop](image, None, *args[2:5], only)
                assert (sums[2] is None, sums[3] is None) == (only[0] is None, only[1] is None)
                assert_close(sums[2] if only[1] is None else sums[3], scale_sums if only[1] is None else weight_sums,
                             1e-12)  # fmt: skip
    lights = jnp.asarray([LIGHTS["on_screen"], LIGHTS["off_screen"]])
    batched = jax.vmap(lambda light: copy_sums_gpu(addressing, True, image, derivative_image, light, scales,
                                                        weights, jacobians))(lights)  # fmt: skip
    for index, light in enumerate(lights):
        expected = copy_sums_cpu(addressing, True, image, derivative_image, light, scales, weights, jacobians)
        for got, want in zip(jax.tree.leaves(batched), jax.tree.leaves(expected), strict=True):
            assert_close(got[index], want, 1e-12)


def test_scales_and_weights_share_the_few_numbers_budget():
    """The scales and weights are differentiated in the loop (a sum per number) only up to `FEW_NUMBERS` numbers
    together; a weight per copy beyond that takes the tangent loop. Eight scales and eight weights: 17 images of
    temporaries for value and gradient; 24 when each vector got its own budget (16 sums). The CPU loop's figures:
    compiled for the CPU on any machine."""
    with jax.default_device(jax.devices("cpu")[0]):
        image = jnp.ones((64, 128, 3), jnp.float32)

        def total(scales, weights):
            return gr.scaled_copies(image, jnp.asarray([30.2, 20.7]), scales, weights).sum()

        args = (jnp.linspace(1.0, 0.5, 8), jnp.linspace(1.0, 0.3, 8))
        compiled = jax.jit(jax.value_and_grad(total, argnums=(0, 1))).lower(*args).compile()
    assert compiled.memory_analysis().temp_size_in_bytes < 20 * image.nbytes


@pytest.mark.slow
def test_cpu_blocks_of_rows_store_nothing_per_copy(monkeypatch):
    """Summed in blocks of rows, a gradient's memory must not grow by an image's worth per copy: a loop value
    that is the same for every block (once, a zero output of a never-taken branch) was stored once per copy."""
    monkeypatch.setattr(cpu_loop, "BLOCKED_SIZE", 0)
    monkeypatch.setattr(cpu_loop, "ROWS_PER_BLOCK", 8)
    jax.clear_caches()
    temporaries = []
    with jax.default_device(jax.devices("cpu")[0]):  # the CPU loop, on any machine
        image = jnp.ones((64, 128, 3), jnp.float32)
        for copies in (32, 256):

            def loss(density, decay, copies=copies):
                rays_image = gr.radial_rays(image, jnp.asarray([13.3, 9.1]), num_samples=20.0, max_samples=copies,
                                            density=density, decay=decay, weight=0.5, exposure=1.0)  # fmt: skip
                return rays_image.sum()

            compiled = jax.jit(jax.value_and_grad(loss, argnums=(0, 1))).lower(0.5, 0.9).compile()
            temporaries.append(compiled.memory_analysis().temp_size_in_bytes)
    jax.clear_caches()
    # Per copy only its taps are kept (about (H + W) numbers each): well under a tenth of the image.
    assert (temporaries[1] - temporaries[0]) / (256 - 32) < 0.15 * image.nbytes


@pytest.mark.slow
def test_cpu_copy_sums_in_blocks_of_rows_equal_the_whole(x64, rng, monkeypatch):
    """Large images are summed block by block of output rows on a CPU (`BLOCKED_SIZE`); forced here on small ones,
    with blocks of 3 rows, every sum equals the GPU loop's and the kernels' values and gradients are unchanged."""

    image = jnp.asarray(random_image(rng, height=12, width=7))
    copies = 11
    args = (image, jnp.asarray(random_image(rng, channels=2, height=12, width=7)), jnp.asarray(LIGHTS["on_screen"]),
            jnp.asarray(rng.uniform(-0.3, 1.4, copies)), jnp.asarray(rng.uniform(0.1, 1.0, copies)),
            (jnp.asarray(rng.normal(size=(copies, 1))), jnp.asarray(rng.normal(size=(copies, 2)))))  # fmt: skip
    light, scales, weights = args[2:5]

    def kernel(image, light, scales, weights):
        return gr.scaled_copies(image, light, scales, weights, addressing="zero")

    unblocked = kernel(image, light, scales, weights)
    assert cpu_loop.rows_per_block(1080, 1920, 3) == 60
    assert cpu_loop.rows_per_block(1091, 1920, 3) == 1091, "a prime height is one block, not 1091 blocks of a row"
    monkeypatch.setattr(cpu_loop, "BLOCKED_SIZE", 0)
    monkeypatch.setattr(cpu_loop, "ROWS_PER_BLOCK", 3)
    assert cpu_loop.rows_per_block(12, 7, 3) == 3
    jax.clear_caches()  # traced loops are cached by shape
    for addressing in ("clamp", "zero"):
        blocked = jax.jit(lambda *a, addressing=addressing: copy_sums_cpu(addressing, True, *a))(*args)
        expected = copy_sums_gpu(addressing, True, *args)
        for got, want in zip(jax.tree.leaves(blocked), jax.tree.leaves(expected), strict=True):
            assert_close(got, want, 1e-12)
    assert_close(jax.jit(kernel)(image, light, scales, weights), unblocked, 1e-12)
    check_grads(jax.jit(kernel), (image, light, scales[:3], weights[:3]), order=1, modes=("fwd", "rev"), eps=1e-6)
    jax.clear_caches()

