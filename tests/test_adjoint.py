"""The image's adjoint of scaled copies (kernels/copy_sums/adjoint.py) against a slow loop, and through every transformation."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from frames import slow_where
from jax.test_util import check_grads

import godrays_jax as gr
from godrays_jax.kernels.copy_sums import adjoint, copies, cpu_loop
from godrays_jax.kernels.copy_sums.planes import Planes

HEIGHT, WIDTH = 9, 13
LIGHTS = {
    "on_screen": (5.3, 3.7),
    "pixel_centre": (4.5, 2.5),
    "near_edge": (0.1, 8.9),
    "off_screen": (-6.0, 20.0),
    "far_off_screen": (3e4, -2e5),
}
# Scales in each band (runs of 2, 4, 8 outputs), above 1, mirrored, near 0 and 0 (the scatter), on a band's limit.
SCALES = [1.0, 0.93, 0.5, 0.62, 1.7, -0.8, 0.3, -0.2, 0.13, 1e-7, 0.0]


def transposed_copies_loop(cotangent, light, scales, weights, addressing):
    """`sum_k weights[k] * A_k^T cotangent`: every output pixel hands its cotangent to its four bilinear texels."""
    height, width = cotangent.shape[:2]
    adjoint_image = np.zeros_like(cotangent)
    for scale, weight in zip(scales, weights):
        for row in range(height):
            for col in range(width):
                u = light[0] + (col + 0.5 - light[0]) * scale - 0.5
                v = light[1] + (row + 0.5 - light[1]) * scale - 0.5
                left, top = math.floor(u), math.floor(v)
                fu, fv = u - left, v - top
                for texel_col, wu in ((left, 1 - fu), (left + 1, fu)):
                    for texel_row, wv in ((top, 1 - fv), (top + 1, fv)):
                        inside = 0 <= texel_col < width and 0 <= texel_row < height
                        if addressing == "zero" and not inside:
                            continue
                        target = (min(max(texel_row, 0), height - 1), min(max(texel_col, 0), width - 1))
                        adjoint_image[target] += weight * wu * wv * cotangent[row, col]
    return adjoint_image


def assert_close(actual, expected, rtol):
    actual, expected = np.asarray(actual), np.asarray(expected)
    assert actual.shape == expected.shape
    assert np.all(np.isfinite(actual))
    assert np.max(np.abs(actual - expected)) <= rtol * np.max(np.abs(expected)), np.max(np.abs(actual - expected))


def loops():
    """The CPU loop, the GPU loop (run here on the CPU) and the dispatch."""
    return {"cpu": adjoint.copy_adjoint_cpu, "gpu": adjoint.copy_adjoint_gpu, "dispatch": adjoint.copy_adjoint}


@pytest.mark.parametrize("addressing", ["clamp", "zero"])
@pytest.mark.parametrize("light", slow_where(LIGHTS.values(), {LIGHTS["on_screen"]}), ids=LIGHTS.keys())
def test_adjoint_matches_the_transposed_loop(x64, rng, light, addressing):
    cotangent = rng.normal(size=(HEIGHT, WIDTH, 2))
    weights = rng.uniform(0.1, 1.0, len(SCALES))
    expected = transposed_copies_loop(cotangent, light, SCALES, weights, addressing)
    args = (jnp.asarray(cotangent), jnp.asarray(light), jnp.asarray(SCALES), jnp.asarray(weights))
    for name, loop in loops().items():
        assert_close(jax.jit(loop, static_argnums=0)(addressing, *args), expected, 1e-12)


def test_adjoint_in_blocks_of_rows_matches_the_loop(x64, rng, monkeypatch):
    """Large images are transposed block by block of texel rows on a CPU; forced here, blocks of 3 rows."""
    monkeypatch.setattr(cpu_loop, "BLOCKED_SIZE", 0)
    monkeypatch.setattr(cpu_loop, "ROWS_PER_BLOCK", 3)
    jax.clear_caches()
    cotangent = rng.normal(size=(12, 7, 3))
    weights = rng.uniform(0.1, 1.0, len(SCALES))
    for light in (LIGHTS["on_screen"], LIGHTS["off_screen"]):
        for addressing in ("clamp", "zero"):
            expected = transposed_copies_loop(cotangent, light, SCALES, weights, addressing)
            actual = adjoint.copy_adjoint_cpu(
                addressing, jnp.asarray(cotangent), jnp.asarray(light), jnp.asarray(SCALES), jnp.asarray(weights)
            )
            assert_close(actual, expected, 1e-12)
    jax.clear_caches()


def test_adjoint_equals_the_transpose_of_the_copies_sum(x64, rng):
    """The gradient in the image equals JAX's own transpose of the forward loop (the scatter it replaced)."""
    image = jnp.asarray(rng.uniform(size=(HEIGHT, WIDTH, 3)))
    cotangent = jnp.asarray(rng.normal(size=image.shape))
    light, scales, weights = jnp.asarray(LIGHTS["near_edge"]), jnp.asarray(SCALES), jnp.asarray(rng.uniform(size=len(SCALES)))

    def forward_loop(image):
        total = copies.copy_sums("clamp", False, image, None, light, scales, weights, (None, None))[0]
        return Planes(image.shape).image_from_columns(total)

    (scattered,) = jax.linear_transpose(forward_loop, image)(cotangent)
    _, vjp = jax.vjp(lambda image: gr.scaled_copies(image, light, scales, weights), image)
    assert_close(vjp(cotangent)[0], scattered, 1e-12)


SLOW_LIGHTS = {LIGHTS[name] for name in ("on_screen", "near_edge", "far_off_screen")}


@pytest.mark.parametrize("light", slow_where(LIGHTS.values(), SLOW_LIGHTS), ids=LIGHTS.keys())
def test_kernel_gradients_in_the_image_forward_and_reverse(x64, rng, light):
    image = jnp.asarray(rng.uniform(size=(HEIGHT, WIDTH, 2)))
    light = jnp.asarray(light)
    rays = jax.jit(lambda image: gr.radial_rays(image, light, num_samples=7, density=1.0, decay=0.9, weight=0.8,
                                                exposure=0.5))  # fmt: skip
    check_grads(rays, (image,), order=1, modes=("fwd", "rev"), eps=1e-6)
    relaxed = jax.jit(lambda image: gr.radial_rays(image, light, num_samples=5.5, max_samples=7, density=0.7,
                                                   decay=0.9, weight=0.8, exposure=0.5))  # fmt: skip
    check_grads(relaxed, (image,), order=1, modes=("fwd", "rev"), eps=1e-6)
    flares = jax.jit(lambda image: gr.scale_iterated_flares(image, light, num_iters=4, scale_step=1.3, decay=0.8))
    check_grads(flares, (image,), order=1, modes=("fwd", "rev"), eps=1e-6)


@pytest.mark.slow
def test_gradients_in_the_image_and_every_scalar_together(x64, rng):
    image = jnp.asarray(rng.uniform(size=(HEIGHT, WIDTH, 3)))

    def rays(image, light, density, decay, weight, exposure, count):
        return gr.radial_rays(image, light, num_samples=count, max_samples=6, density=density, decay=decay,
                              weight=weight, exposure=exposure)  # fmt: skip

    args = (image, jnp.asarray(LIGHTS["on_screen"]), 0.6, 0.9, 0.8, 0.5, 4.6)
    check_grads(jax.jit(rays), args, order=1, modes=("fwd", "rev"), eps=1e-6)
    flares = lambda image, light, step, decay: gr.scale_iterated_flares(image, light, num_iters=5, scale_step=step,
                                                                        decay=decay)  # noqa: E731  # fmt: skip
    check_grads(jax.jit(flares), (image, jnp.asarray(LIGHTS["off_screen"]), 1.2, 0.9), order=1,
                modes=("fwd", "rev"), eps=1e-6)  # fmt: skip


@pytest.mark.slow
def test_gradient_in_the_image_eager_jit_vmap(rng):
    images = jnp.asarray(rng.uniform(size=(2, HEIGHT, WIDTH, 3)), jnp.float32)
    lights = jnp.asarray([LIGHTS["on_screen"], LIGHTS["off_screen"]], jnp.float32)

    def loss(image, light):
        return jnp.sum(gr.radial_rays(image, light, num_samples=6, density=0.9, decay=0.9, weight=1.0, exposure=0.3) ** 2)

    grad = jax.grad(loss)
    expected = [np.asarray(jax.jit(grad)(images[i], lights[i])) for i in range(2)]
    assert_close(grad(images[0], lights[0]), expected[0], 1e-5)
    # A batch of images under one light (summed as more channels) and a batch of lights (one at a time).
    same_light = jax.jit(jax.vmap(grad, in_axes=(0, None)))(images, lights[0])
    assert_close(same_light[1], jax.jit(grad)(images[1], lights[0]), 1e-5)
    for i, batched in enumerate(jax.jit(jax.vmap(grad))(images, lights)):
        assert_close(batched, expected[i], 1e-5)


KERNELS_OF_AN_IMAGE = {
    "radial_rays": lambda image, light: gr.radial_rays(image, light, num_samples=6, density=0.9, decay=0.9, weight=1.0,
                                                       exposure=0.3),
    "scale_iterated_flares": lambda image, light: gr.scale_iterated_flares(image, light, num_iters=5, scale_step=1.2,
                                                                           decay=0.9),
}


@pytest.mark.slow
@pytest.mark.parametrize("kernel", KERNELS_OF_AN_IMAGE)
@pytest.mark.parametrize("compiled", [False, True])
def test_gradient_of_a_batch(kernel, compiled, rng):
    """`grad` of a loss over `vmap` (a training loop's first step) equals the per-example gradients.

    The batching rule of the image's adjoint primitive runs here: one light for the batch (the images summed as more
    channels) and a light per image (one at a time).
    """
    kernel = KERNELS_OF_AN_IMAGE[kernel]
    images = jnp.asarray(rng.uniform(size=(3, HEIGHT, WIDTH, 2)), jnp.float32)
    lights = jnp.asarray([LIGHTS["on_screen"], LIGHTS["off_screen"], LIGHTS["pixel_centre"]], jnp.float32)
    transform = jax.jit if compiled else (lambda function: function)

    def example_loss(image, light):
        return jnp.sum(kernel(image, light) ** 2)

    per_light = transform(jax.grad(lambda images: jnp.sum(jax.vmap(example_loss)(images, lights))))(images)
    one_light = transform(jax.grad(lambda images: jnp.sum(jax.vmap(example_loss, in_axes=(0, None))(images, lights[0]))))
    one_light = one_light(images)
    for i in range(3):
        assert_close(per_light[i], jax.grad(example_loss)(images[i], lights[i]), 1e-5)
        assert_close(one_light[i], jax.grad(example_loss)(images[i], lights[0]), 1e-5)


@pytest.mark.slow
def test_second_derivatives_through_the_adjoint(x64, rng):
    """The primitive's own JVP (the copies' derivative in the light) serves forward-over-reverse, e.g. a Hessian."""
    image = jnp.asarray(rng.uniform(size=(HEIGHT, WIDTH, 1)))

    def loss(image, light):
        return jnp.sum(gr.scaled_copies(image, light, jnp.asarray([0.9, 0.6]), jnp.asarray([1.0, 0.5])) ** 2)

    image_gradient = jax.grad(loss)
    check_grads(jax.jit(lambda light: image_gradient(image, light)), (jnp.asarray(LIGHTS["on_screen"]),), order=1,
                modes=("fwd",), eps=1e-6)  # fmt: skip


def test_gradient_memory_in_the_image_does_not_grow_with_copies():
    """Value and gradient in the image keep O(image) temporaries whatever the number of copies."""
    with jax.default_device(jax.devices("cpu")[0]):
        image = jnp.ones((64, 128, 3), jnp.float32)
        temporaries = []
        for copies_count in (16, 256):

            def loss(image, copies_count=copies_count):
                rays = gr.radial_rays(image, jnp.asarray([80.3, -9.1]), num_samples=copies_count, density=1.0,
                                      decay=0.99, weight=0.5, exposure=1.0)  # fmt: skip
                return jnp.sum(rays**2)

            compiled = jax.jit(jax.value_and_grad(loss)).lower(image).compile()
            temporaries.append(compiled.memory_analysis().temp_size_in_bytes)
    assert temporaries[1] - temporaries[0] < 0.1 * image.nbytes * (256 - 16) / 16, temporaries
    assert temporaries[1] < 20 * image.nbytes, temporaries


def test_bands_cover_the_kernels_scales():
    """Radial rays of density 1/2 and flare-outs of step 1.03 over 20 copies take the narrowest band (but the copy at
    scale 1/2 exactly, whose runs may round to 3 outputs); density 1 takes the scatter only below scale 1/8."""
    size, light = (1080, 1920), jnp.asarray((1100.0, 300.0), jnp.float32)
    for scales in (1 - jnp.arange(1, 129) * 0.5 / 128, 1.03 ** -jnp.arange(20.0)):
        which, _ = adjoint.band_of_copies(size, light, scales.astype(jnp.float32), "clamp")
        assert int(np.sum(np.asarray(which) > 0)) <= 1
    scales = 1 - jnp.arange(1, 129, dtype=jnp.float32) / 128
    which = np.asarray(adjoint.band_of_copies(size, light, scales, "clamp")[0])
    assert np.all(which[np.asarray(scales) > 0.13] < len(adjoint.BANDS))
    assert np.all(which[np.asarray(scales) < 0.12] == len(adjoint.BANDS))
