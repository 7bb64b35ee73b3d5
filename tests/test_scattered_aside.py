"""The frame's own light scattered aside by the medium (`kernels.volumetric.scattered_aside`, `VolumetricFog`'s
`surface_blur`) and the light scattered again (`scattered_again`, its `scattered_blur`) against slow NumPy loops,
and in the effect."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import godrays_jax as gr
from godrays_jax.effects.volumetric import SCATTERED_BLUR_SIGMA, SURFACE_BLUR_SIGMA
from godrays_jax.kernels.blur import gaussian_blur, pooled_gaussian_matrices
from godrays_jax.kernels.volumetric import scattered_again, scattered_aside
from godrays_jax.primitives.resample import downsample_box, upsample_bilinear

HEIGHT, WIDTH = 9, 13


def _gaussian_loop(image: np.ndarray, sigma: float) -> np.ndarray:
    """A separable Gaussian of `sigma` pixels, `ceil(3 sigma)` taps each side, normalised, clamp-to-edge."""
    reach = max(1, math.ceil(3 * sigma))
    weights = [math.exp(-0.5 * (k / sigma) ** 2) for k in range(-reach, reach + 1)]
    total = sum(weights)
    height, width = image.shape[:2]
    rows = np.zeros_like(image)
    for y in range(height):
        for x in range(width):
            for k, w in zip(range(-reach, reach + 1), weights):
                rows[y, x] += w / total * image[y, min(max(x + k, 0), width - 1)]
    out = np.zeros_like(image)
    for y in range(height):
        for x in range(width):
            for k, w in zip(range(-reach, reach + 1), weights):
                out[y, x] += w / total * rows[min(max(y + k, 0), height - 1), x]
    return out


def _blurred_loop(image: np.ndarray, sigma: float) -> np.ndarray:
    """The blur as the docstring says: box averages of `floor(sigma / 2)`-pixel blocks (edge pixels completing the
    last), the Gaussian of `sigma / factor` on them, read back bilinearly at each pixel's centre (clamp-to-edge)."""
    factor = max(1, int(sigma // 2))
    height, width = image.shape[:2]
    low_h, low_w = -(-height // factor), -(-width // factor)
    low = np.zeros((low_h, low_w, image.shape[2]))
    for j in range(low_h):
        for i in range(low_w):
            for dy in range(factor):
                for dx in range(factor):
                    low[j, i] += image[min(j * factor + dy, height - 1), min(i * factor + dx, width - 1)]
    low = _gaussian_loop(low / factor**2, sigma / factor)
    out = np.zeros_like(image)
    for y in range(height):
        for x in range(width):
            u, v = (x + 0.5) / factor - 0.5, (y + 0.5) / factor - 0.5
            i0, j0 = math.floor(u), math.floor(v)
            fu, fv = u - i0, v - j0
            for j, wj in ((j0, 1 - fv), (j0 + 1, fv)):
                for i, wi in ((i0, 1 - fu), (i0 + 1, fu)):
                    out[y, x] += wj * wi * low[min(max(j, 0), low_h - 1), min(max(i, 0), low_w - 1)]
    return out


def _loop(image, surface, surface_blur, sigma):
    colour = image[..., : min(image.shape[-1], 3)]
    taken = (1.0 - surface)[..., None] * colour
    return surface_blur * np.broadcast_to(_blurred_loop(taken, sigma), (*image.shape[:2], 3))


def _inputs(rng, channels=3):
    image = rng.uniform(0.0, 3.0, (HEIGHT, WIDTH, channels))
    image[2:5, 4:8] = 20.0  # a bright patch, whose light the medium spreads around it
    return image, rng.uniform(0.0, 1.0, (HEIGHT, WIDTH))


@pytest.mark.parametrize("sigma", [1.3, 3.7, 4.0, 6.5])  # the blur at full resolution, then on blocks of 2 and 3
@pytest.mark.parametrize("channels", [1, 3, 4])
def test_matches_loop(x64, rng, sigma, channels):
    image, surface = _inputs(rng, channels)
    got = scattered_aside(jnp.asarray(image), jnp.asarray(surface), surface_blur=0.3, sigma=sigma)
    assert got.shape == (HEIGHT, WIDTH, 3)
    np.testing.assert_allclose(np.asarray(got), _loop(image, surface, 0.3, sigma), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize(("height", "width", "sigma"), [(9, 13, 1.3), (17, 10, 4.0), (31, 47, 6.5), (12, 12, 9.9)])
def test_the_blurs_matrices_are_the_pooled_gaussian_of_the_librarys_resamplers(x64, rng, height, width, sigma):
    """`pooled_gaussian_matrices` along both axes equals `downsample_box`, `gaussian_blur` on the blocks and
    `upsample_bilinear`, ragged last blocks included."""
    image = rng.uniform(0.0, 1.0, (height, width, 2))
    factor = max(1, int(sigma // 2))
    expected = upsample_bilinear(
        gaussian_blur(downsample_box(jnp.asarray(image), factor), sigma=sigma / factor), factor, height, width
    )
    (pool_h, read_h), (pool_w, read_w) = (pooled_gaussian_matrices(size, sigma) for size in (height, width))
    assert pool_h.shape == (-(-height // factor), height) and read_w.shape == (width, -(-width // factor))
    got = np.einsum("yj,jxc->yxc", read_h, np.einsum("xi,jic->jxc", read_w, np.einsum("iw,jwc->jic", pool_w,
                    np.einsum("jh,hwc->jwc", pool_h, image))))  # fmt: skip
    np.testing.assert_allclose(got, np.asarray(expected), rtol=1e-12, atol=1e-14)
    for matrix in (pool_h, read_h, pool_w, read_w):  # a constant stays constant
        np.testing.assert_allclose(matrix.sum(axis=1), 1.0, rtol=1e-12)


def test_the_blurs_matrices_name_a_bad_argument():
    for size, sigma, name in ((0, 2.0, "size"), (4.0, 2.0, "size"), (8, 0.0, "sigma"), (8, True, "sigma")):
        with pytest.raises(ValueError, match=name):
            pooled_gaussian_matrices(size, sigma)


def test_spreads_a_patchs_light_around_it_and_keeps_its_amount_away_from_the_edges(x64):
    """The light a bright patch in the middle loses to the medium comes back around it, as much as was taken times
    `surface_blur` (a blur of sum 1 whose reach stays inside the frame)."""
    image = np.zeros((41, 41, 3))
    image[19:22, 19:22] = 10.0
    surface = np.full((41, 41), 0.25)
    aside = np.asarray(scattered_aside(jnp.asarray(image), jnp.asarray(surface), surface_blur=0.5, sigma=2.5))
    assert aside[20, 20, 0] < 0.5 * 0.75 * 10.0  # spread out: less than the patch's own
    assert aside[20, 26, 0] > 0.0 and aside[20, 32, 0] < aside[20, 26, 0]  # and falling off beside it
    np.testing.assert_allclose(aside.sum(axis=(0, 1)), 0.5 * 0.75 * image.sum(axis=(0, 1)), rtol=1e-6)


def test_nothing_is_scattered_aside_without_a_medium_or_a_share(x64, rng):
    image, surface = _inputs(rng)
    for share, plane in ((0.4, np.ones_like(surface)), (0.0, surface)):
        aside = scattered_aside(jnp.asarray(image), jnp.asarray(plane), surface_blur=share, sigma=3.0)
        np.testing.assert_array_equal(np.asarray(aside), 0.0)


def test_a_share_known_to_be_zero_leaves_the_blur_out_and_a_traced_one_keeps_its_derivative(rng):
    """A constant 0 (every preset's, in `apply`'s program) compiles no matrix products; a traced 0 keeps them,
    and its derivative is the blur of the light taken out."""
    image, surface = (jnp.asarray(a, jnp.float32) for a in _inputs(rng))

    def products(function, *args):
        return [e for e in jax.make_jaxpr(function)(*args).jaxpr.eqns if e.primitive.name == "dot_general"]

    assert not products(lambda i, s: scattered_aside(i, s, surface_blur=0.0, sigma=3.0), image, surface)
    assert len(products(lambda i, s, b: scattered_aside(i, s, surface_blur=b, sigma=3.0), image, surface, 0.0)) == 4
    derivative = jax.jacfwd(lambda b: scattered_aside(image, surface, surface_blur=b, sigma=3.0))(jnp.float32(0.0))
    expected = scattered_aside(image, surface, surface_blur=1.0, sigma=3.0)
    np.testing.assert_allclose(np.asarray(derivative), np.asarray(expected), rtol=1e-6, atol=1e-7)
    assert float(jnp.max(derivative)) > 0.0


def test_gradients_float64(x64, rng):
    image, surface = _inputs(rng)

    def aside(image, surface, share):
        return scattered_aside(image, surface, surface_blur=share, sigma=4.5)

    check_grads(aside, (jnp.asarray(image), jnp.asarray(surface), jnp.asarray(0.3)), order=1, modes=("fwd", "rev"))


def test_bad_options_name_the_argument(rng):
    image, surface = (jnp.asarray(a, jnp.float32) for a in _inputs(rng))
    bad = [(dict(sigma=0.0), "sigma"), (dict(sigma=jnp.asarray(2.0)), "sigma")]
    bad.append((dict(surface_blur=jnp.ones(2)), "surface_blur"))
    for options, name in bad:
        with pytest.raises(ValueError, match=name):
            scattered_aside(image, surface, **{"surface_blur": 0.2, "sigma": 2.0, **options})
    with pytest.raises(ValueError, match="surface"):
        scattered_aside(image, surface[:-1], surface_blur=0.2, sigma=2.0)


def _fog_frame(rng):
    depth = np.full((24, 40), 30.0, np.float32)
    depth[:8] = np.inf  # sky above a wall
    color = rng.uniform(0.0, 1.0, (24, 40, 3)).astype(np.float32)
    color[14:18, 10:20] = 12.0  # a lit patch on the wall
    coverage = np.isfinite(depth).astype(np.float32)
    buffers = gr.Buffers(color=jnp.asarray(color), depth=jnp.asarray(depth), coverage=jnp.asarray(coverage))
    return buffers, jnp.asarray([30.5, 3.5], jnp.float32)


def test_the_fog_adds_its_surfaces_light_scattered_aside(rng):
    """`VolumetricFog` with `surface_blur` is the fog without it plus `scattered_aside` of its frame and its surface
    term, spread over `SURFACE_BLUR_SIGMA` of the frame's larger side; its layer holds that light too, and at 0 (the
    presets') the frame is the fog's of single scattering alone, to the bit."""
    buffers, light = _fog_frame(rng)
    plain = gr.VolumetricFog(medium=gr.Medium(extinction=0.05, max_distance=40.0), num_view_steps=4)
    blurred = dataclasses.replace(plain, surface_blur=jnp.asarray(0.4, jnp.float32))
    surface, scattered, ambient = plain.terms(buffers, light)
    single = gr.composite_fog(buffers.color, surface, plain.layer(buffers, light))
    np.testing.assert_array_equal(np.asarray(plain(buffers, light)), np.asarray(single))
    aside = scattered_aside(buffers.color, surface, surface_blur=0.4, sigma=SURFACE_BLUR_SIGMA * 40)
    np.testing.assert_allclose(np.asarray(blurred(buffers, light)), np.asarray(single + aside), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(
        np.asarray(blurred.layer(buffers, light)), np.asarray(plain.layer(buffers, light) + aside), rtol=1e-5, atol=1e-6
    )
    lit = gr.lit_by(blurred, buffers, [gr.Light(xy=light)])
    np.testing.assert_allclose(np.asarray(lit), np.asarray(blurred(buffers, light)), rtol=1e-5, atol=1e-6)


def test_the_fogs_surface_blur_is_fittable_with_finite_gradients(rng):
    buffers, light = _fog_frame(rng)
    fog = gr.VolumetricFog(medium=gr.Medium(extinction=0.05, max_distance=40.0), num_view_steps=4)
    assert "surface_blur" in gr.parameter_bounds(fog) and gr.parameter_bounds(fog)["surface_blur"] == (0.0, 1.0)

    def loss(share):
        return jnp.mean(dataclasses.replace(fog, surface_blur=share)(buffers, light))

    gradient = jax.grad(loss)(jnp.asarray(0.2, jnp.float32))
    assert np.isfinite(gradient) and gradient > 0  # more of the frame's light comes back


@pytest.mark.slow
def test_a_fit_finds_the_surface_blur_in_its_polish(rng):
    """`fit` holds `surface_blur` where it starts while it races and descends (`Effect.POLISH_FIELDS`) and fits it
    in the polish: from 0 it finds the share the target was drawn with."""
    buffers, light = _fog_frame(rng)
    start = gr.VolumetricFog(medium=gr.Medium(extinction=0.05, max_distance=40.0), num_view_steps=4)
    truth = dataclasses.replace(start, surface_blur=jnp.asarray(0.3, jnp.float32))
    target = truth(buffers, light)
    fixed = [name for name in gr.parameter_bounds(start) if name not in ("surface_blur", "medium.light_color")]
    result = gr.fit(start, buffers, light, target, fixed=fixed, max_steps=20)
    assert abs(float(result.effect.surface_blur) - 0.3) < 0.01
    assert result.polish_steps > 0


def _again_loop(scattered, scattered_blur, sigma):
    return (1.0 - scattered_blur) * scattered + scattered_blur * _blurred_loop(scattered[..., None], sigma)[..., 0]


@pytest.mark.parametrize("sigma", [1.3, 4.0, 6.5])
def test_the_light_scattered_again_matches_loop(x64, rng, sigma):
    _, scattered = _inputs(rng)
    scattered[3:5, 6:8] = 5.0  # a beam's bright core
    got = scattered_again(jnp.asarray(scattered), scattered_blur=0.35, sigma=sigma)
    assert got.shape == (HEIGHT, WIDTH)
    np.testing.assert_allclose(np.asarray(got), _again_loop(scattered, 0.35, sigma), rtol=1e-10, atol=1e-12)


def test_the_light_scattered_again_moves_light_beside_a_beam_and_adds_none(x64):
    scattered = np.zeros((41, 41))
    scattered[:, 19:22] = 2.0  # a vertical beam
    again = np.asarray(scattered_again(jnp.asarray(scattered), scattered_blur=0.5, sigma=2.5))
    assert again[20, 20] < 2.0 and again[20, 25] > 0.0 and again[20, 30] < again[20, 25]  # a glow beside it
    np.testing.assert_allclose(again.sum(), scattered.sum(), rtol=1e-6)


def test_a_share_of_zero_scattered_again_leaves_the_blur_out_and_a_traced_one_keeps_its_derivative(rng):
    scattered = jnp.asarray(_inputs(rng)[1], jnp.float32)

    def products(function, *args):
        return [e for e in jax.make_jaxpr(function)(*args).jaxpr.eqns if e.primitive.name == "dot_general"]

    assert scattered_again(scattered, scattered_blur=0.0, sigma=3.0) is scattered
    assert len(products(lambda s, b: scattered_again(s, scattered_blur=b, sigma=3.0), scattered, 0.0)) == 4
    traced = jax.jit(lambda s, b: scattered_again(s, scattered_blur=b, sigma=3.0))(scattered, jnp.float32(0.0))
    np.testing.assert_array_equal(np.asarray(traced), np.asarray(scattered))  # a traced 0 changes nothing either
    derivative = jax.jacfwd(lambda b: scattered_again(scattered, scattered_blur=b, sigma=3.0))(jnp.float32(0.0))
    expected = scattered_again(scattered, scattered_blur=1.0, sigma=3.0) - scattered
    np.testing.assert_allclose(np.asarray(derivative), np.asarray(expected), rtol=1e-5, atol=1e-6)


def test_the_light_scattered_again_gradients_float64(x64, rng):
    scattered = jnp.asarray(_inputs(rng)[1])
    again = lambda s, share: scattered_again(s, scattered_blur=share, sigma=4.5)  # noqa: E731
    check_grads(again, (scattered, jnp.asarray(0.3)), order=1, modes=("fwd", "rev"))


def test_the_light_scattered_again_names_a_bad_argument(rng):
    scattered = jnp.asarray(_inputs(rng)[1], jnp.float32)
    for options, name in ((dict(sigma=0.0), "sigma"), (dict(scattered_blur=jnp.ones(2)), "scattered_blur")):
        with pytest.raises(ValueError, match=name):
            scattered_again(scattered, **{"scattered_blur": 0.2, "sigma": 2.0, **options})
    with pytest.raises(ValueError, match="scattered"):
        scattered_again(scattered[..., None], scattered_blur=0.2, sigma=2.0)


def test_the_fog_scatters_its_beams_light_again(rng):
    """`VolumetricFog` with `scattered_blur` draws the light it scatters toward the camera through
    `scattered_again`, spread over `SCATTERED_BLUR_SIGMA` of the frame's larger side, for every light alike
    (`lit_by`); at 0 (the presets') the frame is single scattering's to the bit."""
    buffers, light = _fog_frame(rng)
    plain = gr.VolumetricFog(medium=gr.Medium(extinction=0.05, max_distance=40.0), num_view_steps=4)
    again = dataclasses.replace(plain, scattered_blur=jnp.asarray(0.4, jnp.float32))
    surface, scattered, ambient = plain.terms(buffers, light)
    spread = scattered_again(scattered, scattered_blur=0.4, sigma=SCATTERED_BLUR_SIGMA * 40)
    expected = gr.composite_fog(buffers.color, surface, plain._light(spread, ambient))
    np.testing.assert_allclose(np.asarray(again(buffers, light)), np.asarray(expected), rtol=1e-5, atol=1e-6)
    assert float(jnp.max(jnp.abs(again(buffers, light) - plain(buffers, light)))) > 1e-3
    traced_zero = jax.jit(lambda share: dataclasses.replace(plain, scattered_blur=share)(buffers, light))
    single = jax.jit(lambda: plain(buffers, light))
    np.testing.assert_array_equal(np.asarray(traced_zero(jnp.float32(0.0))), np.asarray(single()))
    lit = gr.lit_by(again, buffers, [gr.Light(xy=light)])
    np.testing.assert_allclose(np.asarray(lit), np.asarray(again(buffers, light)), rtol=1e-5, atol=1e-6)
    assert "scattered_blur" in type(plain).POLISH_FIELDS and gr.parameter_bounds(plain)["scattered_blur"] == (0.0, 1.0)
