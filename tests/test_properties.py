"""Property-based tests (hypothesis) of the kernels and effects, and validation of bad input.

Over image sizes from 1x1, channel counts 1-4, lights on screen, on a pixel
centre, off screen and far off screen, and parameter ranges: outputs and
gradients are finite, jit equals eager, vmap equals a loop, rays are linear
in the image, blurs keep a constant image constant. Then the library's
answers to bad input: shapes, ranks, dtypes, out-of-range parameters, NaN and
infinite values, lights behind the camera.
"""

import dataclasses
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from frames import at_fit_counts, slow_where
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads

import godrays_jax as gr

SETTINGS = settings(
    max_examples=5, deadline=None, database=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow]
)
MAX_SAMPLES = 6


SHAPES = [(1, 1, 1), (4, 1, 3), (5, 6, 4)]
"""Image shapes from 1x1 up, every channel count; a fixed few, so each compiles once for the whole file."""


@st.composite
def images(draw):
    height, width, channels = draw(st.sampled_from(SHAPES))
    seed = draw(st.integers(0, 2**31 - 1))
    values = np.random.default_rng(seed).uniform(0.0, 4.0, (height, width, channels))
    return jnp.asarray(values, jnp.float32)


@st.composite
def lights(draw, height: int, width: int):
    """On screen, exactly on a pixel centre, off screen, or far off screen."""
    kind = draw(st.sampled_from(["on", "centre", "off", "far"]))
    if kind == "on":
        xy = (draw(st.floats(0, width)), draw(st.floats(0, height)))
    elif kind == "centre":
        xy = (draw(st.integers(0, width - 1)) + 0.5, draw(st.integers(0, height - 1)) + 0.5)
    elif kind == "off":
        xy = (draw(st.floats(-3 * width, 4 * width)), draw(st.floats(-3 * height, 4 * height)))
    else:
        xy = (draw(st.sampled_from([-1e6, 1e6])) * draw(st.floats(0.5, 2)), draw(st.floats(-1e6, 1e6)))
    return jnp.asarray(xy, jnp.float32)


@st.composite
def ray_cases(draw):
    image = draw(images())
    light = draw(lights(image.shape[0], image.shape[1]))
    relaxed = draw(st.booleans())
    if relaxed:
        num_samples = jnp.float32(draw(st.floats(0.0, MAX_SAMPLES)))
    else:
        num_samples = draw(st.sampled_from([1, MAX_SAMPLES]))
    params = dict(
        num_samples=num_samples,
        max_samples=MAX_SAMPLES if relaxed else None,
        density=jnp.float32(draw(st.floats(0.0, 2.0))),
        decay=jnp.float32(draw(st.floats(0.0, 1.0))),
        weight=jnp.float32(draw(st.floats(0.0, 10.0))),
        exposure=jnp.float32(draw(st.floats(0.0, 5.0))),
    )
    return image, light, params


def _finite(tree) -> bool:
    return all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree.leaves(tree))


def _close(a, b, rtol=1e-5, atol=1e-5):
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=rtol, atol=atol)


def _split_static(params):
    """Static counts stay Python values; traced ones become arguments."""
    static = {k: v for k, v in params.items() if k == "max_samples" or isinstance(v, int)}
    return static, {k: v for k, v in params.items() if k not in static}


@functools.cache
def _jitted_rays(static_items):
    """`radial_rays` and its gradient, jitted once per static configuration (and shape)."""
    static = dict(static_items)

    def rays(image, light, traced):
        return gr.radial_rays(image, light, **static, **traced)

    def loss(image, light, traced):
        cotangent = jnp.cos(jnp.arange(image.size, dtype=image.dtype)).reshape(image.shape)
        return jnp.sum(rays(image, light, traced) * cotangent)

    return rays, jax.jit(rays), jax.jit(jax.grad(loss, argnums=(0, 1, 2)))


# ------------------------------------------------------------------------------ radial rays


@pytest.mark.slow
@SETTINGS
@given(ray_cases())
def test_radial_rays_finite_jit_eager_and_gradients(case):
    image, light, params = case
    static, traced = _split_static(params)
    rays, jitted, gradient = _jitted_rays(tuple(sorted(static.items())))
    with jax.disable_jit():  # truly op by op: no compilation, the loop runs in Python
        eager = rays(image, light, traced)
    assert eager.shape == image.shape and _finite(eager)
    _close(jitted(image, light, traced), eager)
    assert _finite(gradient(image, light, traced))


@SETTINGS
@given(ray_cases(), st.floats(-3.0, 3.0), st.floats(-3.0, 3.0), st.integers(0, 2**31 - 1))
def test_radial_rays_linear_in_the_image(case, a, b, seed):
    image, light, params = case
    static, traced = _split_static(params)
    _, rays, _ = _jitted_rays(tuple(sorted(static.items())))
    other = jnp.asarray(np.random.default_rng(seed).normal(size=image.shape), jnp.float32)
    combined = rays(a * image + b * other, light, traced)
    separate = a * rays(image, light, traced) + b * rays(other, light, traced)
    scale = 1.0 + float(jnp.max(jnp.abs(separate)))
    _close(combined, separate, rtol=1e-4, atol=1e-5 * scale)


@SETTINGS
@given(images(), st.sampled_from([1, 3]), st.integers(0, 2**31 - 1))
def test_radial_rays_vmap_equals_loop(image, count, seed):
    rng = np.random.default_rng(seed)
    lights_xy = jnp.asarray(rng.uniform(-10, 10, (count, 2)), jnp.float32)
    decays = jnp.asarray(rng.uniform(0.5, 1.0, count), jnp.float32)
    samples = jnp.asarray(rng.uniform(0, MAX_SAMPLES, count), jnp.float32)

    batched = _vmapped_rays(image, lights_xy, decays, samples)
    for i in range(count):
        _close(batched[i], _one_ray_image_jit(image, lights_xy[i], decays[i], samples[i]))


def _one_ray_image(image, light, decay, num_samples):
    return gr.radial_rays(image, light, num_samples=num_samples, max_samples=MAX_SAMPLES, density=0.8, decay=decay,
                          weight=1.0, exposure=0.5)  # fmt: skip


_vmapped_rays = jax.jit(jax.vmap(_one_ray_image, in_axes=(None, 0, 0, 0)))
_one_ray_image_jit = jax.jit(_one_ray_image)


def test_radial_rays_gradients_match_finite_differences():
    """In float64, away from the kinks of bilinear sampling: image and the smooth scalars."""
    with jax.enable_x64(True):
        rng = np.random.default_rng(3)
        image = jnp.asarray(rng.uniform(0, 2, (4, 5, 3)))
        light = jnp.asarray([1.3, 2.7])

        def rays(image, decay, weight, exposure, num_samples):
            return gr.radial_rays(image, light, num_samples=num_samples, max_samples=MAX_SAMPLES, density=0.7,
                                  decay=decay, weight=weight, exposure=exposure)  # fmt: skip

        check_grads(jax.jit(rays), (image, 0.9, 1.2, 0.3, 3.4), order=1, modes=("rev", "fwd"), eps=1e-5)


def test_kernels_accept_numpy_images():
    """NumPy inputs (what `read_buffers` users and `check_grads` pass) work like JAX arrays."""
    image = np.ones((3, 4, 2), np.float32)
    rays = gr.radial_rays(image, np.array([1.0, 2.0]), num_samples=2, density=0.5, decay=0.9, weight=1.0, exposure=1.0)
    _close(rays, gr.radial_rays(jnp.asarray(image), jnp.array([1.0, 2.0]), num_samples=2, density=0.5, decay=0.9,
                                weight=1.0, exposure=1.0))  # fmt: skip


# ------------------------------------------------------------------------------ flare-outs


@pytest.mark.slow
@SETTINGS
@given(images(), st.data())
def test_scale_iterated_flares_properties(image, data):
    light = data.draw(lights(image.shape[0], image.shape[1]))
    scale_step = jnp.float32(data.draw(st.floats(0.8, 1.5)))
    decay = jnp.float32(data.draw(st.floats(0.0, 1.0)))
    num_iters = jnp.float32(data.draw(st.floats(0.0, 5.0)))

    args = (image, light, scale_step, decay, num_iters)
    with jax.disable_jit():
        eager = _flares(*args)
    assert eager.shape == image.shape and _finite(eager)
    jitted = _flares_jit(*args)
    _close(jitted, eager)
    assert _finite(_flares_grad(*args))
    _close(_flares_jit(3.0 * image, *args[1:]), 3.0 * jitted, rtol=1e-5, atol=1e-4)
    batched = _flares_vmap(image, jnp.stack([light, light + 1.0]), *args[2:])
    _close(batched[1], _flares_jit(image, light + 1.0, *args[2:]))


def _flares(image, light, scale_step, decay, num_iters):
    return gr.scale_iterated_flares(image, light, num_iters=num_iters, max_iters=5, scale_step=scale_step, decay=decay)


_flares_jit = jax.jit(_flares)
_flares_grad = jax.jit(jax.grad(lambda *a: jnp.sum(_flares(*a) ** 2), argnums=(0, 1, 2, 3, 4)))
_flares_vmap = jax.jit(jax.vmap(_flares, in_axes=(None, 0, None, None, None)))


# ------------------------------------------------------------------------------ blurs


@SETTINGS
@given(images(), st.floats(0.0, 0.3), st.floats(0.0, 3.0), st.floats(-5.0, 50.0))
def test_blurs_keep_a_constant_image_constant(image, blur_power, passes, level):
    constant = jnp.full_like(image, level)
    _close(_blur_jit(constant, jnp.float32(blur_power), jnp.float32(passes), jnp.float32(blur_power * 10)),
           2.0 * constant, rtol=1e-5, atol=1e-4)  # fmt: skip


@SETTINGS
@given(images(), st.floats(0.0, 0.3), st.floats(0.0, 3.0), st.floats(0.0, 4.0))
@pytest.mark.slow
def test_blurs_finite_jit_vmap_and_gradients(image, blur_power, passes, sigma):
    args = (image, jnp.float32(blur_power), jnp.float32(passes), jnp.float32(sigma))
    with jax.disable_jit():
        eager = _blur(*args)
    assert _finite(eager)
    _close(_blur_jit(*args), eager)
    assert _finite(_blur_grad(*args))
    batched = _blur_vmap(jnp.stack([image, 2.0 * image]), *args[1:])
    _close(batched[1], _blur_jit(2.0 * image, *args[1:]), rtol=1e-5, atol=1e-4)


def _blur(image, blur_power, passes, sigma):
    """Both blurs, summed: seed 000's Poisson blur (relaxed passes) and the Gaussian."""
    return gr.poisson_blur(image, blur_power=blur_power, num_passes=passes, max_passes=3) + gr.gaussian_blur(image, sigma=sigma, reach=4)


_blur_jit = jax.jit(_blur)
_blur_grad = jax.jit(jax.grad(lambda *a: jnp.sum(_blur(*a) ** 2), argnums=(0, 1, 2, 3)))
_blur_vmap = jax.jit(jax.vmap(_blur, in_axes=(0, None, None, None)))


# ------------------------------------------------------------------------------ whole effects


@st.composite
def frames(draw):
    height, width = draw(st.sampled_from([(1, 1), (5, 6)]))  # (5, 6) shares compilations with the vmap test
    rng = np.random.default_rng(draw(st.integers(0, 2**31 - 1)))
    depth = rng.uniform(0.5, 10.0, (height, width))
    depth[rng.random((height, width)) < 0.5] = np.inf  # sky: +inf depth is valid input
    coverage = np.isfinite(depth) * rng.uniform(0.5, 1.0, (height, width))
    return gr.Buffers(
        color=jnp.asarray(rng.uniform(0, 3, (height, width, 3)), jnp.float32),
        depth=jnp.asarray(depth, jnp.float32),
        coverage=jnp.asarray(coverage, jnp.float32),
        light_pass=jnp.asarray(1.0 - coverage, jnp.float32),
    )


def _small(name: str) -> gr.Effect:
    """The preset with few samples, so that tests stay fast; the algorithm is the preset's."""
    effect = gr.preset(name)
    fields = {field.name: getattr(effect, field.name) for field in dataclasses.fields(effect)}
    if isinstance(effect, gr.GodRays):
        return type(effect)(**{**fields, "num_samples": 5.0, "max_samples": 5})
    if isinstance(effect, gr.FlareOuts):
        return type(effect)(**{**fields, "num_iters": 4.0, "max_iters": 4})
    return at_fit_counts(effect)


@settings(SETTINGS, max_examples=4)  # each preset compiles once (its gradient and frame) per frame size
@given(frames(), st.sampled_from(sorted(gr.PRESETS)), st.booleans(), st.data())
@pytest.mark.slow
def test_effects_finite_values_and_gradients_anywhere(buffers, name, in_front, data):
    light = data.draw(lights(buffers.height, buffers.width))
    effect = _small(name)
    gradient, out = _effect_grad((effect, light), buffers, jnp.asarray(in_front))
    assert out.shape == buffers.color.shape and _finite(out)
    assert _finite(gradient)
    # Documented: a light behind the camera gives no screen-space effect. Bloom does not depend on the light,
    # ScatteringFog keeps its backward-scattering lobe and VolumetricFog its medium, lit from behind.
    if not in_front and not isinstance(effect, (gr.Bloom, gr.ScatteringFog, gr.VolumetricFog)):
        _close(out, buffers.color, rtol=0, atol=0)


def _effect_on_frame(effect, buffers, light, in_front):
    return effect(buffers, light, light_in_front=in_front)


@eqx.filter_jit
@functools.partial(eqx.filter_grad, has_aux=True)
def _effect_grad(effect_and_light, buffers, in_front):
    """The gradient of a loss of the frame, and the frame: one program per frame size."""
    effect, light = effect_and_light
    out = effect(buffers, light, light_in_front=in_front)
    return jnp.sum(out**2), out


FOGS = ("participating_media", "volumetric_haze", "physically_based")
"""The fog presets, whose lights, far ones among them, are drawn at every distance and side by their own test below."""


@st.composite
def any_finite_lights(draw, height: int, width: int):
    """Anywhere up to 1e30 px away on either axis, or exactly on the screen's edge (where the fade starts)."""
    if draw(st.booleans()):
        return jnp.asarray((draw(st.sampled_from([0.0, width])), draw(st.floats(-1e30, 1e30))), jnp.float32)

    def coordinate():
        return draw(st.sampled_from([-1.0, 1.0])) * 10.0 ** draw(st.floats(-2.0, 30.0))

    return jnp.asarray((coordinate(), coordinate()), jnp.float32)


@pytest.mark.parametrize("name", slow_where(sorted(set(gr.PRESETS) - set(FOGS)), {"vbex_sun_spot"}))
@settings(SETTINGS, max_examples=6)
@given(st.data())
def test_every_preset_finite_values_and_gradients_for_any_finite_light(name, data):
    """Far lights once overflowed float32 in squared pixel distances (offscreen fade, disc) and made gradients NaN.
    The fogs draw these lights too, with every other property of a light, in the next test."""
    buffers = data.draw(frames())
    light = data.draw(any_finite_lights(buffers.height, buffers.width))
    effect = _small(name)
    (effect_grad, light_grad), out = _effect_grad((effect, light), buffers, jnp.asarray(True))
    assert out.shape == buffers.color.shape and _finite(out)
    checked = [field for field in ("offscreen_fade", "flare_size") if hasattr(effect, field)]
    for field in checked:
        assert _finite(getattr(effect_grad, field)), (field, light)
    assert _finite(light_grad) and _finite(effect_grad), light


LIGHT_DEPTHS = (0.0, 1e-30, 1e-3, 1.0, 1e3, 1e12, 1e30, np.inf)
"""A point light at the camera, within a hair of it, near, far, beyond float32's squares, and the sun."""


@eqx.filter_jit
@functools.partial(eqx.filter_grad, has_aux=True)
def _fog_grad(effect_and_light, buffers, in_front, light_depth):
    """The gradient of a loss of the fogged frame, and the frame: one program per frame size."""
    effect, light = effect_and_light
    out = effect(buffers, light, light_in_front=in_front, light_depth=light_depth)
    return jnp.sum(out**2), out


@pytest.mark.parametrize("name", slow_where(FOGS))
@settings(SETTINGS, max_examples=6)
@given(st.data())
def test_fog_presets_finite_values_and_gradients_for_any_light_and_distance(name, data):
    """Every fog preset, any light position (on screen, far off it), in front or behind, at any distance from the
    camera (a point light at the camera once gave every pixel NaN), on frames with surfaces at the eye (depth 0,
    whose gradients were NaN) or not: finite frames and gradients."""
    buffers = data.draw(frames())
    if data.draw(st.booleans()):  # some surfaces at the eye
        at_eye = np.random.default_rng(data.draw(st.integers(0, 2**31 - 1))).random(buffers.depth.shape) < 0.5
        buffers = dataclasses.replace(buffers, depth=jnp.where(jnp.asarray(at_eye), 0.0, buffers.depth))
    light = data.draw(st.one_of(lights(buffers.height, buffers.width), any_finite_lights(buffers.height, buffers.width)))
    in_front = jnp.asarray(data.draw(st.booleans()))
    light_depth = jnp.float32(data.draw(st.sampled_from(LIGHT_DEPTHS)))
    effect = _small(name)
    (effect_grad, light_grad), out = _fog_grad((effect, light), buffers, in_front, light_depth)
    assert out.shape == buffers.color.shape and _finite(out), (light, light_depth)
    assert _finite(effect_grad) and _finite(light_grad), (light, light_depth, in_front)


@pytest.mark.parametrize("name", slow_where(sorted(gr.PRESETS)))
def test_effects_vmap_over_frames_equals_loop(name):
    rng = np.random.default_rng(5)
    stacked = gr.Buffers(
        color=jnp.asarray(rng.uniform(0, 2, (3, 5, 6, 3)), jnp.float32),
        depth=jnp.where(jnp.asarray(rng.random((3, 5, 6))) < 0.5, jnp.inf, 3.0),
        coverage=jnp.asarray(rng.uniform(0, 1, (3, 5, 6)), jnp.float32),
        light_pass=jnp.asarray(rng.uniform(0, 1, (3, 5, 6)), jnp.float32),
    )  # a batch of frames: leading axes are allowed on every field
    lights_xy = jnp.asarray([[1.5, 2.0], [-4.0, 3.0], [6.5, 5.5]], jnp.float32)
    effect = _small(name)
    visible = jnp.ones(3, bool)
    batched = eqx.filter_jit(jax.vmap(_effect_on_frame, in_axes=(None, 0, 0, 0)))(effect, stacked, lights_xy, visible)
    one_frame = eqx.filter_jit(_effect_on_frame)  # compiled too: what differs is the batching, not XLA's fusion
    for i in range(3):
        frame = jax.tree.map(lambda leaf: leaf[i], stacked)
        # VolumetricFog's march amplifies float32 rounding (up to 3e-5 here, by the light on the frame's corner);
        # in float64 the batch and the loop agree to 1e-16.
        _close(batched[i], one_frame(effect, frame, lights_xy[i], visible[i]),
               rtol=1e-4 if isinstance(effect, gr.VolumetricFog) else 1e-5)  # fmt: skip


# ------------------------------------------------------------------------------ validation of bad input


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda: gr.radial_rays(jnp.ones((4, 4)), jnp.zeros(2), num_samples=2, density=1.0, decay=0.9,
                                weight=1.0, exposure=1.0), "image must have shape"),  # fmt: skip
        (lambda: gr.radial_rays(jnp.ones((4, 4, 5)), jnp.zeros(2), num_samples=2, density=1.0, decay=0.9,
                                weight=1.0, exposure=1.0), "image must have shape"),  # fmt: skip
        (lambda: gr.radial_rays(jnp.ones((4, 4, 3)), jnp.zeros(3), num_samples=2, density=1.0, decay=0.9,
                                weight=1.0, exposure=1.0), "light_xy"),  # fmt: skip
        (lambda: gr.radial_rays(jnp.ones((4, 4, 3)), jnp.zeros(2), num_samples=0, density=1.0, decay=0.9,
                                weight=1.0, exposure=1.0), "num_samples must be >= 1"),  # fmt: skip
        (lambda: gr.radial_rays(jnp.ones((4, 4, 3)), jnp.zeros(2), num_samples=2.5, density=1.0, decay=0.9,
                                weight=1.0, exposure=1.0), "max_samples"),  # fmt: skip
        (lambda: gr.radial_rays(jnp.ones((4, 4, 3)), jnp.zeros(2), num_samples=2, density=jnp.ones(2), decay=0.9,
                                weight=1.0, exposure=1.0), "density must be a scalar"),  # fmt: skip
        (lambda: gr.scale_iterated_flares(jnp.ones((0, 4, 3)), jnp.zeros(2), num_iters=2, scale_step=1.1),
         "masked must be at least 1x1"),
        (lambda: gr.poisson_blur(jnp.ones((4, 4, 3)), blur_power=0.1, num_passes=-1), "num_passes must be >= 0"),
        (lambda: gr.gaussian_blur(jnp.ones((4, 4, 3)), sigma=jnp.float32(1.0)), "reach must be given"),
        (lambda: gr.Buffers(color=jnp.ones((4, 4)), depth=jnp.ones((4, 4)), coverage=jnp.ones((4, 4))),
         "buffers.color must have shape"),
        (lambda: gr.Buffers(color=jnp.ones((4, 4, 3)), depth=jnp.ones((4, 5)), coverage=jnp.ones((4, 4))),
         r"buffers.depth must have shape \(4, 4\)"),
        (lambda: gr.Buffers(color=jnp.ones((4, 4, 3), jnp.int32), depth=jnp.ones((4, 4)), coverage=jnp.ones((4, 4))),
         "buffers.color must have a floating-point dtype"),
        (lambda: gr.Buffers(color=jnp.ones((4, 4, 3)), depth=jnp.ones((4, 4)), coverage=jnp.ones((4, 4)),
                            object_id=jnp.ones((4, 4))), "buffers.object_id must have an integer dtype"),  # fmt: skip
    ],
)
def test_bad_shapes_ranks_dtypes_and_counts_name_the_argument(call, message):
    with pytest.raises(ValueError, match=message):
        call()


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda: gr.GodRays(decay=-0.5), r"GodRays.decay must lie in \[0.5, 1\], got -0.5"),
        (lambda: gr.GodRays(num_samples=0.0), r"GodRays.num_samples must lie in \[1, 4096\]"),
        (lambda: gr.FlareOuts(intensity=float("nan")), "FlareOuts.intensity must lie in"),
        (lambda: gr.SunOvercast(tint=(0.8, 0.5, -1.0, 0.65)), "SunOvercast.tint must lie in"),
        (lambda: gr.effect_from_dict({"effect": "GodRays", "exposure": float("inf")}), "GodRays.exposure"),
    ],
)
def test_out_of_range_effect_parameters_are_rejected(make, message):
    with pytest.raises(ValueError, match=message):
        make()


def test_effects_built_from_traced_values_are_not_checked_at_trace_time():
    decay = jax.jit(lambda d: gr.GodRays(decay=d).decay)(jnp.float32(0.9))
    assert float(decay) == pytest.approx(0.9)


def test_relaxed_count_outside_its_range_is_a_runtime_error():
    rays = jax.jit(lambda n: gr.radial_rays(jnp.ones((3, 3, 1)), jnp.zeros(2), num_samples=n, max_samples=4,
                                            density=1.0, decay=0.9, weight=1.0, exposure=1.0))  # fmt: skip
    with pytest.raises(Exception, match="num_samples must lie in"):
        rays(jnp.float32(5.0)).block_until_ready()


def test_nan_and_inf_colour_reported_and_inf_depth_is_sky():
    color = np.ones((3, 4, 3), np.float32)
    depth = np.full((3, 4), np.inf, np.float32)  # all sky: valid
    gr.check_buffers(gr.Buffers(color=color, depth=depth, coverage=np.zeros((3, 4), np.float32)), name="sky")
    color[0, 1, 2], color[2, 2, 0] = np.nan, np.inf
    depth[1, 1] = -1.0
    with pytest.raises(ValueError, match="'f7'.*color has 2 pixels with NaN or infinite.*depth has 1 pixel with negative"):
        gr.check_buffers(gr.Buffers(color=color, depth=depth, coverage=np.zeros((3, 4), np.float32)), name="f7")


def test_every_integer_static_field_declares_its_range_and_every_cap_is_a_static_field():
    for cls in sorted({type(gr.preset(name)) for name in gr.PRESETS}, key=lambda cls: cls.__name__):  # new effects join
        infos = gr.field_metadata(cls)
        for field in dataclasses.fields(cls):
            if field.metadata.get("kind") == "static" and field.type is int:
                assert field.metadata.get("bounds"), f"{cls.__name__}.{field.name}: declare static(..., low=, high=)"
                low, high = infos[field.name].bounds
                assert low <= field.default <= high
        for info in infos.values():
            if info.cap is not None:
                assert infos[info.cap].kind == "static", f"{cls.__name__}.{info.name} is capped by {info.cap}"
            assert not info.count or info.cap is not None, f"{cls.__name__}.{info.name}: a count needs its cap"


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda: gr.GodRays(density="0.5"), r"GodRays.density must be a number .*got '0.5'"),
        (lambda: gr.GodRays(tint=[[1], [1, 2], 3]), r"GodRays.tint must be a number"),
        (lambda: gr.GodRays(exposure=True), r"GodRays.exposure must be a number"),
        (lambda: gr.GodRays(use_bright_pass="false"), r"GodRays.use_bright_pass must be true or false"),
        (lambda: gr.GodRays(max_samples=10**8), r"GodRays.max_samples must lie in \[1, 4096\]"),
        (lambda: gr.GodRays(num_samples=8.0, max_samples=8.0), r"GodRays.max_samples must be an integer, got 8.0"),
        (lambda: gr.GodRays(source=["disc"]), r"GodRays.source must be one of disc, sky, light_pass"),
        (lambda: gr.FlareOuts(max_iters=0), r"FlareOuts.max_iters must lie in \[1, 64\]"),
        (lambda: gr.LensDirt(dirt_seed=-1), r"LensDirt.dirt_seed must lie in"),
        (lambda: gr.Bloom(blend_mode=1), r"Bloom.blend_mode must be one of add, screen"),
    ],
)
def test_constructors_refuse_values_of_the_wrong_type_or_range(make, message):
    with pytest.raises(ValueError, match=message):
        make()
