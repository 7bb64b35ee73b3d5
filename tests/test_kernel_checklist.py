"""Every public kernel through what research code does with it, in the manner of dm-pix's variants and kornia's tests.

One table (`CASES`) holds a call of each kernel on one example's array inputs (images, depths, lights and one
fittable scalar or more); each test checks one property over the whole table: eager equals `jit`, `vmap` equals a
loop, `grad` of a loss over `vmap` equals the per-example gradients (eager and under `jit`), `vmap` of `grad` too,
the gradients are finite, the dtype is kept, NumPy input is accepted. A kernel added to the package without a row
fails `test_every_public_kernel_has_a_case`.
"""

import collections
import dataclasses
import inspect
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from closeness import assert_trees_close
from frames import slow_where

import godrays_jax as gr

HEIGHT, WIDTH = 11, 14  # SSIM needs 11x11
BATCH = 3


@dataclasses.dataclass(frozen=True)
class Case:
    """`call(*inputs)` on one example; `inputs(rng, dtype)` draws that example's arrays (every one differentiated)."""

    call: Callable
    inputs: Callable


def _image(rng, dtype, channels=3):
    return rng.uniform(0.0, 2.0, size=(HEIGHT, WIDTH, channels)).astype(dtype)


def _plane(rng, dtype, low=0.0, high=1.0):
    return rng.uniform(low, high, size=(HEIGHT, WIDTH)).astype(dtype)


def _light(rng, dtype):
    # Off pixel centres and inside the frame, where every kernel is smooth in the light.
    return np.asarray([rng.uniform(2.1, WIDTH - 2.1), rng.uniform(2.1, HEIGHT - 2.1)], dtype)


def _scalar(rng, dtype, low, high):
    return np.asarray(rng.uniform(low, high), dtype)


def _depth(rng, dtype):
    return _plane(rng, dtype, 1.0, 40.0)


# A roof of slats seen from a sun straight above (its camera looks down the frame's -y from 10 units above it), 5.5
# units above the frame's camera: its shadow falls on the points below, some within its ramp (`light_view_visibility`).
LIGHT_VIEW_DEPTH = np.where(np.logical_and.outer(np.arange(16) % 5 < 3, np.arange(16) % 4 < 2), 4.5, np.inf).astype(np.float32)
LIGHT_VIEW_FROM_CAMERA = np.asarray([[1, 0, 0, 0], [0, 0, 1, -5], [0, -1, 0, 10]], np.float32)

RAYS = dict(num_samples=6, weight=1.0, exposure=0.3)

CASES = {
    "add": Case(gr.add, lambda r, t: (_image(r, t), _image(r, t))),
    "alpha_over": Case(gr.alpha_over, lambda r, t: (_image(r, t), _image(r, t, 4) / 2)),
    "apply_fog": Case(
        lambda image, depth, light, extinction: gr.apply_fog(
            image, depth, light, fov_x_deg=50.0, extinction=extinction, max_distance=60.0,
            ambient_color=(0.1, 0.1, 0.1), light_color=(1.0, 0.9, 0.8), anisotropy=0.7),
        lambda r, t: (_image(r, t), _depth(r, t), _light(r, t), _scalar(r, t, 0.01, 0.05)),
    ),  # fmt: skip
    "at_reduced_resolution": Case(
        lambda image, light, decay: gr.at_reduced_resolution(
            image, light, kernel=gr.radial_rays, resolution_factor=2, density=0.8, decay=decay, **RAYS),
        lambda r, t: (_image(r, t), _light(r, t), _scalar(r, t, 0.8, 0.95)),
    ),  # fmt: skip
    "blend": Case(lambda scene, layer: gr.blend(scene, layer, mode="screen"), lambda r, t: (_image(r, t), _image(r, t) / 2)),
    "bloom": Case(
        lambda image, threshold: gr.bloom(image, threshold=threshold, sigma=1.0, reach=3),
        lambda r, t: (_image(r, t), _scalar(r, t, 0.5, 1.0)),
    ),
    "bright_pass": Case(
        lambda image, threshold: gr.bright_pass(image, threshold=threshold),
        lambda r, t: (_image(r, t), _scalar(r, t, 0.1, 0.5)),
    ),
    "charbonnier_loss": Case(gr.charbonnier_loss, lambda r, t: (_image(r, t), _image(r, t))),
    "coverage_mask": Case(gr.coverage_mask, lambda r, t: (_plane(r, t),)),
    "depth_test_mask": Case(
        lambda depth, light_depth: gr.depth_test_mask(depth, light_depth=light_depth, bias=0.5),
        lambda r, t: (_depth(r, t), _scalar(r, t, 10.0, 30.0)),
    ),
    # The reach of 1 (the four nearest offsets, each weighted radius - 1/2) is the loop of any reach, unrolled less.
    "dilate": Case(
        lambda mask, radius: gr.dilate(mask, radius=radius, max_radius=1), lambda r, t: (_plane(r, t), _scalar(r, t, 0.6, 0.95))
    ),
    "erode": Case(
        lambda mask, radius: gr.erode(mask, radius=radius, max_radius=1), lambda r, t: (_plane(r, t), _scalar(r, t, 0.6, 0.95))
    ),
    "fast_radial_rays": Case(
        lambda image, light, decay: gr.fast_radial_rays(image, light, density=0.8, decay=decay, num_passes=2, num_taps=3,
                                                        **RAYS),
        lambda r, t: (_image(r, t), _light(r, t), _scalar(r, t, 0.8, 0.95)),
    ),  # fmt: skip
    "flare_image": Case(
        lambda light, size: gr.flare_image(HEIGHT, WIDTH, light, flare_size=size, dtype=size.dtype),
        lambda r, t: (_light(r, t), _scalar(r, t, 2.0, 4.0)),
    ),
    "flare_mask": Case(gr.flare_mask, lambda r, t: (_image(r, t), _plane(r, t))),
    "gaussian_blur": Case(
        lambda image, sigma: gr.gaussian_blur(image, sigma=sigma, reach=3), lambda r, t: (_image(r, t), _scalar(r, t, 0.7, 1.5))
    ),
    "henyey_greenstein": Case(
        lambda cosine, anisotropy: gr.henyey_greenstein(cosine, anisotropy=anisotropy),
        lambda r, t: (_plane(r, t, -1.0, 1.0), _scalar(r, t, -0.5, 0.8)),
    ),
    "in_scattering": Case(
        lambda depth, light, extinction: gr.in_scattering(
            depth, light, fov_x_deg=50.0, extinction=extinction, max_distance=60.0, ambient_color=(0.1, 0.1, 0.1),
            light_color=(1.0, 0.9, 0.8), anisotropy=0.7),
        lambda r, t: (_depth(r, t), _light(r, t), _scalar(r, t, 0.01, 0.05)),
    ),  # fmt: skip
    "l1_loss": Case(gr.l1_loss, lambda r, t: (_image(r, t), _image(r, t))),
    "light_view_visibility": Case(
        lambda points, scale: gr.light_view_visibility(points, light_view=gr.LightView(
            depth=LIGHT_VIEW_DEPTH, from_camera=LIGHT_VIEW_FROM_CAMERA, scale=scale)),
        lambda r, t: (r.uniform([-3.0, 1.0, 2.0], [3.0, 5.0, 8.0], size=(HEIGHT, WIDTH, 3)).astype(t),
                      _scalar(r, t, 1.5, 2.5)),
    ),  # fmt: skip
    "lens_dirt": Case(
        lambda dirt, depth, light, fov: gr.lens_dirt(dirt, depth, light, fov_x_deg=fov, far_plane=50.0, power=4.0),
        lambda r, t: (_image(r, t, 1), _depth(r, t), _light(r, t), _scalar(r, t, 40.0, 70.0)),
    ),
    "lens_dirt_intensity": Case(
        lambda depth, light, fov: gr.lens_dirt_intensity(depth, light, fov_x_deg=fov, far_plane=50.0, power=4.0),
        lambda r, t: (_depth(r, t), _light(r, t), _scalar(r, t, 40.0, 70.0)),
    ),
    "light_direction": Case(
        lambda light, fov: gr.light_direction(light, HEIGHT, WIDTH, fov_x_deg=fov, dtype=fov.dtype),
        lambda r, t: (_light(r, t), _scalar(r, t, 40.0, 70.0)),
    ),
    "light_source_mask": Case(
        lambda light, size: gr.light_source_mask(HEIGHT, WIDTH, light, flare_size=size, dtype=size.dtype),
        lambda r, t: (_light(r, t), _scalar(r, t, 2.0, 4.0)),
    ),
    "mse_loss": Case(gr.mse_loss, lambda r, t: (_image(r, t), _image(r, t))),
    "multiply": Case(gr.multiply, lambda r, t: (_image(r, t), _image(r, t))),
    "poisson_blur": Case(
        lambda image, power: gr.poisson_blur(image, blur_power=power, num_passes=2),
        lambda r, t: (_image(r, t), _scalar(r, t, 0.02, 0.08)),
    ),
    "radial_rays": Case(
        lambda image, light, decay: gr.radial_rays(image, light, density=0.8, decay=decay, **RAYS),
        lambda r, t: (_image(r, t), _light(r, t), _scalar(r, t, 0.8, 0.95)),
    ),
    "radial_rays_jittered": Case(
        lambda image, light, decay: gr.radial_rays_jittered(image, light, density=0.8, decay=decay, **RAYS),
        lambda r, t: (_image(r, t), _light(r, t), _scalar(r, t, 0.8, 0.95)),
    ),
    "radial_rays_multipass": Case(
        lambda image, light, decay: gr.radial_rays_multipass(image, light, density=0.8, decay=decay, num_passes=2, num_taps=3,
                                                             **RAYS),
        lambda r, t: (_image(r, t), _light(r, t), _scalar(r, t, 0.8, 0.95)),
    ),  # fmt: skip
    "scale_iterated_flares": Case(
        lambda image, light, step: gr.scale_iterated_flares(image, light, num_iters=4, scale_step=step, decay=0.9),
        lambda r, t: (_image(r, t), _light(r, t), _scalar(r, t, 1.05, 1.3)),
    ),
    "scaled_copies": Case(
        gr.scaled_copies,
        lambda r, t: (_image(r, t), _light(r, t), r.uniform(0.5, 1.2, 3).astype(t), r.uniform(0.2, 1.0, 3).astype(t)),
    ),
    "screen": Case(gr.screen, lambda r, t: (_image(r, t) / 2, _image(r, t) / 2)),
    "sky_mask": Case(lambda depth, sky_depth: gr.sky_mask(depth, sky_depth=sky_depth), lambda r, t: (_depth(r, t), _scalar(r, t, 20.0, 30.0))),
    "ssim": Case(gr.ssim, lambda r, t: (_image(r, t), _image(r, t))),
    "ssim_loss": Case(gr.ssim_loss, lambda r, t: (_image(r, t), _image(r, t))),
    "sun_spot": Case(
        lambda light, fov: gr.sun_spot(HEIGHT, WIDTH, light, fov_x_deg=fov, sun_distance=0.002, sun_sharpness=1.0,
                                       dtype=fov.dtype),
        lambda r, t: (_light(r, t), _scalar(r, t, 40.0, 70.0)),
    ),  # fmt: skip
    "transmittance": Case(
        lambda depth, extinction: gr.transmittance(depth, extinction=extinction, max_distance=30.0),
        lambda r, t: (_depth(r, t), _scalar(r, t, 0.01, 0.05)),
    ),
    "view_directions": Case(
        lambda fov: gr.view_directions(HEIGHT, WIDTH, fov_x_deg=fov, dtype=fov.dtype), lambda r, t: (_scalar(r, t, 40.0, 70.0),)
    ),
    "apply_volumetric_fog": Case(
        lambda image, depth, light, extinction: gr.apply_volumetric_fog(
            image, depth, light, light_color=(1.0, 0.9, 0.8), ambient_color=(0.1, 0.1, 0.1), fov_x_deg=50.0,
            medium=gr.BoundedMedium(extinction=extinction, max_distance=60.0, anisotropy=0.7), ambient_rise=0.1,
            num_view_steps=4, shadows=gr.ShadowSamples(6)),
        lambda r, t: (_image(r, t), _depth(r, t), _light(r, t), _scalar(r, t, 0.01, 0.05)),
    ),  # fmt: skip
    "composite_fog": Case(
        lambda image, surface, light: gr.composite_fog(image, surface, light),
        lambda r, t: (_image(r, t), _plane(r, t, 0.0, 1.0), r.uniform(0.0, 1.0, (HEIGHT, WIDTH, 3)).astype(t)),
    ),
    "scattered_aside": Case(
        lambda image, surface, share: gr.scattered_aside(image, surface, surface_blur=share, sigma=4.5),
        lambda r, t: (_image(r, t), _plane(r, t, 0.0, 1.0), _scalar(r, t, 0.1, 0.5)),
    ),
    "scattered_again": Case(
        lambda scattered, share: gr.scattered_again(scattered, scattered_blur=share, sigma=4.5),
        lambda r, t: (_plane(r, t, 0.0, 1.0), _scalar(r, t, 0.1, 0.5)),
    ),
    "fog_light": Case(
        lambda scattered, ambient, warmth: gr.fog_light(
            scattered, ambient, light_color=jnp.stack([1.0, warmth, 0.5]), ambient_color=(0.1, 0.2, 0.3)),
        lambda r, t: (_plane(r, t, 0.0, 1.0), _plane(r, t, 0.0, 1.0), _scalar(r, t, 0.5, 0.9)),
    ),  # fmt: skip
    "bright_sky": Case(
        lambda luminance, light, threshold: gr.bright_sky(luminance, light, threshold=threshold),
        lambda r, t: (_plane(r, t), _light(r, t), _scalar(r, t, 0.3, 0.7)),
    ),
    "clip_space_depth": Case(
        lambda depth: gr.clip_space_depth(depth, near_plane=0.5, far_plane=100.0), lambda r, t: (_depth(r, t),)
    ),
    "hardware_depth": Case(lambda depth: gr.hardware_depth(depth, near_plane=0.5, far_plane=100.0), lambda r, t: (_depth(r, t),)),
    "light_transmittance": Case(
        lambda points, toward, extinction: gr.light_transmittance(
            points, toward / jnp.linalg.norm(toward), light_depth=jnp.inf, extinction=extinction, max_distance=60.0),
        lambda r, t: (r.uniform(-10.0, 10.0, (HEIGHT, WIDTH, 3)).astype(t), np.asarray([0.2, 0.5, -1.0], t) + r.uniform(
            0.0, 0.1, 3).astype(t), _scalar(r, t, 0.01, 0.05)),
    ),  # fmt: skip
    "optical_depth": Case(
        lambda origin, direction, start, length, extinction: gr.optical_depth(
            origin, direction / jnp.linalg.norm(direction, axis=-1, keepdims=True), start, start + length,
            extinction=extinction, height_falloff=0.05),
        lambda r, t: (r.uniform(-5.0, 5.0, (HEIGHT, WIDTH, 3)).astype(t), r.uniform(0.5, 1.0, (HEIGHT, WIDTH, 3)).astype(t),
                      _plane(r, t, 0.0, 5.0), _plane(r, t, 1.0, 20.0), _scalar(r, t, 0.01, 0.05)),
    ),  # fmt: skip
    "segment_visibility": Case(
        lambda depth, light, distances, thickness: gr.segment_visibility(
            depth, light, jnp.stack(jnp.meshgrid(jnp.arange(WIDTH) + 0.5, jnp.arange(HEIGHT) + 0.5), -1).astype(depth.dtype),
            distances, fov_x_deg=50.0, thickness=thickness, edge_softness=0.05, num_shadow_samples=6),
        lambda r, t: (_depth(r, t), _light(r, t), r.uniform(1.0, 40.0, (HEIGHT, WIDTH, 4)).astype(t),
                      _scalar(r, t, 0.1, 0.3)),
    ),  # fmt: skip
    "segment_visibility_by_lines": Case(
        lambda depth, light, bounds, thickness: gr.segment_visibility_by_lines(
            depth, light, jnp.stack(jnp.meshgrid(jnp.arange(WIDTH) + 0.5, jnp.arange(HEIGHT) + 0.5), -1).astype(depth.dtype),
            bounds[..., :-1], bounds[..., 1:], fov_x_deg=50.0, thickness=thickness, edge_softness=0.05,
            max_distance=50.0, num_lines=32, num_bins=24),
        lambda r, t: (_depth(r, t), _light(r, t), np.cumsum(r.uniform(1.0, 10.0, (HEIGHT, WIDTH, 5)), -1).astype(t),
                      _scalar(r, t, 0.1, 0.3)),
    ),  # fmt: skip
    "volumetric_fog_terms": Case(
        lambda depth, light, extinction: jnp.stack(gr.volumetric_fog_terms(
            depth, light, fov_x_deg=50.0, medium=gr.BoundedMedium(extinction=extinction, max_distance=60.0,
            anisotropy=0.7), ambient_rise=0.1, num_view_steps=4, shadows=gr.ShadowLines(num_lines=16, num_bins=12)),
            axis=-1),
        lambda r, t: (_depth(r, t), _light(r, t), _scalar(r, t, 0.01, 0.05)),
    ),  # fmt: skip
}

WITHOUT_ARRAY_INPUTS = {"dirt_texture", "procedural_flare"}
"""Kernels that take only a size and static options (nothing to batch or differentiate): `test_texture_generators`."""

PUBLIC_KERNELS = sorted(
    name
    for name in dir(gr)
    if inspect.isfunction(getattr(gr, name)) and getattr(gr, name).__module__.startswith("godrays_jax.kernels.")
)


def _example(name, seed, dtype=np.float32):
    return CASES[name].inputs(np.random.default_rng(seed), dtype)


def _batch(name, dtype=np.float32):
    examples = [_example(name, seed, dtype) for seed in range(BATCH)]
    return examples, tuple(jnp.stack(column) for column in zip(*examples))


def _assert_close(actual, expected, rtol=2e-4, scale=None):
    assert_trees_close(actual, expected, rtol=rtol, scale=scale)


def _assert_gradients_close(batched_gradients, gradient, cotangents, examples):
    """Each example's slice of `batched_gradients` equals `gradient(cotangent, *example)`, to within `_assert_close`'s
    tolerance of the gradient or, where larger, of the gradient against `|cotangent|`: a gradient in a scalar sums
    every output element's derivative, and against random signs that sum can cancel by chance (view_directions'
    first example: 8.6e-5 of terms summing to 1.3 in magnitude), while float32 rounding, which batching reorders,
    scales with the terms. Several batched results may be given: each example's own gradient is computed once."""
    for i, example in enumerate(examples):
        expected, scale = gradient(cotangents[i], *example), gradient(jnp.abs(cotangents[i]), *example)
        for batched in batched_gradients:
            _assert_close([g[i] for g in batched], expected, scale=scale)


def _loss_of(call):
    """A scalar of one example's output against a fixed cotangent (every output element weighted differently)."""

    def loss(cotangent, *inputs):
        return jnp.sum(cotangent * call(*inputs))

    return loss


def _cotangent(name, inputs, seed):
    shape = jax.eval_shape(CASES[name].call, *inputs).shape
    return jnp.asarray(np.random.default_rng(100 + seed).normal(size=shape), jnp.float32)


def test_every_public_kernel_has_a_case():
    assert sorted([*CASES, *WITHOUT_ARRAY_INPUTS]) == PUBLIC_KERNELS


# Programs lowered to XLA (counted before the persistent cache is looked up, which would hide a program compiled
# again as one read back).
_programs_lowered = collections.Counter()
jax.monitoring.register_event_duration_secs_listener(
    lambda event, duration, **_: _programs_lowered.update([event == "/jax/core/compile/jaxpr_to_mlir_module_duration"])
)


@pytest.mark.parametrize("name", slow_where(sorted(CASES), {"fast_radial_rays"}))
def test_jit_equals_eager_and_eager_compiles_once(name):
    """Compiled equals op by op; and a second eager call on other values of the same shapes compiles nothing (a
    loop over a function defined in the call is traced and compiled again on every call unless it is jitted with
    its static arguments: benchmarks/bench_eager.py)."""
    inputs = _example(name, 0)
    _assert_close(jax.jit(CASES[name].call)(*inputs), CASES[name].call(*inputs))
    before = _programs_lowered[True]
    jax.block_until_ready(CASES[name].call(*_example(name, 1)))
    assert _programs_lowered[True] == before


@pytest.mark.parametrize("name", slow_where(sorted(CASES), {"volumetric_fog_terms", "apply_volumetric_fog"}))
def test_vmap_equals_a_loop(name):
    examples, batched = _batch(name)
    looped = jnp.stack([CASES[name].call(*example) for example in examples])
    _assert_close(jax.vmap(CASES[name].call)(*batched), looped)


def _batched_gradients(name):
    """A batch of examples, their cotangents, the gradient of one example's loss in its inputs, and the gradient of
    the batch's summed loss (a training loop's step)."""
    examples, batched = _batch(name)
    cotangents = jnp.stack([_cotangent(name, example, seed) for seed, example in enumerate(examples)])
    loss = _loss_of(CASES[name].call)
    gradient = jax.grad(loss, argnums=tuple(range(1, len(examples[0]) + 1)))

    def batch_loss(cotangents, *inputs):
        return jnp.sum(jax.vmap(loss)(cotangents, *inputs))

    return examples, batched, cotangents, gradient, jax.grad(batch_loss, argnums=tuple(range(1, len(batched) + 1)))


SLOW_GRADIENTS = {
    "volumetric_fog_terms", "fast_radial_rays", "radial_rays_multipass", "segment_visibility_by_lines",
    "apply_volumetric_fog", "at_reduced_resolution", "radial_rays", "radial_rays_jittered", "scaled_copies",
    "scale_iterated_flares",
}
"""The kernels whose gradients of `vmap` take about five seconds or more on an empty-cache run: run with the slow
tests (README)."""


@pytest.mark.parametrize("name", slow_where(sorted(CASES), SLOW_GRADIENTS))
def test_grad_of_vmap_and_vmap_of_grad_equal_per_example_gradients(name):
    """Under `jit`, as a training step runs them: the gradient of a batched loss in every input, and the per-example
    gradient mapped over the batch, each equal to every example's own gradient (eager equals jit: the first test
    above). One test for both, so that the per-example gradient is traced and compiled once."""
    examples, batched, cotangents, gradient, batch_gradient = _batched_gradients(name)
    grad_of_vmap = jax.jit(batch_gradient)(cotangents, *batched)
    vmap_of_grad = jax.jit(jax.vmap(gradient))(cotangents, *batched)
    _assert_gradients_close([grad_of_vmap, vmap_of_grad], jax.jit(gradient), cotangents, examples)


WITH_OWN_PRIMITIVE = ("radial_rays", "scale_iterated_flares", "scaled_copies")
"""The kernels that call the scaled copies' own primitive (`kernels/copy_sums`), whose eager implementation differs from
its compiled one; every other kernel is JAX's own operations, the same eager or under `jit` once traced (as the
issue's `grad` of `vmap` crash was, at trace time, with or without `jit`). Their gradient of `vmap` runs eager too."""


@pytest.mark.parametrize("name", slow_where(WITH_OWN_PRIMITIVE, {"radial_rays"}))
def test_eager_grad_of_vmap_equals_per_example_gradients(name):
    examples, batched, cotangents, gradient, batch_gradient = _batched_gradients(name)
    _assert_gradients_close([batch_gradient(cotangents, *batched)], jax.jit(gradient), cotangents, examples)


@pytest.mark.parametrize("name", sorted(CASES))
def test_dtype_is_kept(name, x64):
    for dtype in (np.float32, np.float64):
        inputs = _example(name, 0, dtype)
        assert jax.eval_shape(CASES[name].call, *inputs).dtype == dtype, dtype  # traced, as every call is


@pytest.mark.parametrize("name", sorted(CASES))
def test_numpy_input_is_accepted(name):
    inputs = _example(name, 0)
    _assert_close(CASES[name].call(*inputs), CASES[name].call(*map(jnp.asarray, inputs)), rtol=1e-6)


def test_texture_generators():
    """The kernels without array inputs: deterministic, jit-compatible where they are JAX, the dtype asked for."""
    dirt = gr.dirt_texture(HEIGHT, WIDTH, seed=3)
    assert dirt.dtype == jnp.float32 and dirt.shape == (HEIGHT, WIDTH, 1)
    _assert_close(jax.jit(gr.dirt_texture, static_argnums=(0, 1), static_argnames="seed")(HEIGHT, WIDTH, seed=3), dirt)
    assert not np.allclose(gr.dirt_texture(HEIGHT, WIDTH, seed=4), dirt)
    flare = gr.procedural_flare(HEIGHT, WIDTH)
    assert flare.shape == (HEIGHT, WIDTH, 1) and np.all(np.isfinite(flare))
    np.testing.assert_array_equal(gr.procedural_flare(HEIGHT, WIDTH), flare)
