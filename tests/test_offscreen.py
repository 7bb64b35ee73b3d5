"""The off-screen fade and behind-camera rule, for every effect a light drives."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from frames import slow_where

import godrays_jax as gr
from godrays_jax.primitives.checks import MAX_LIGHT_PX, check_light

H, W = 16, 24


def _reference_visibility(light, fade, in_front):
    outside_x = max(-light[0], light[0] - W, 0.0)
    outside_y = max(-light[1], light[1] - H, 0.0)
    t = min((outside_x**2 + outside_y**2) ** 0.5 / (fade * max(W, H)), 1.0)
    return (1 - t * t * (3 - 2 * t)) * in_front


@pytest.mark.parametrize(
    "light", [(12.0, 8.0), (0.0, 0.0), (24.0, 16.0), (-3.0, 8.0), (30.0, -4.0), (-50.0, 40.0), (1e6, -1e6)]
)
def test_visibility_matches_formula(light):
    for in_front in (True, False):
        got = gr.light_visibility(jnp.asarray(light), H, W, fade=0.5, light_in_front=in_front)
        np.testing.assert_allclose(float(got), _reference_visibility(light, 0.5, in_front), atol=1e-6)


def test_visibility_is_continuous_monotone_with_finite_gradients():
    xs = jnp.linspace(-40.0, 60.0, 201)
    values = jax.vmap(lambda x: gr.light_visibility(jnp.stack([x, 8.0]), H, W, fade=0.5))(xs)
    assert float(jnp.abs(jnp.diff(values)).max()) < 0.07  # steps of 0.5 px: no jump at the edge
    assert float(values[0]) == 0.0 and float(values[100]) == 1.0
    grads = jax.vmap(jax.grad(lambda x: gr.light_visibility(jnp.stack([x, 8.0]), H, W, fade=0.5)))(xs)
    assert bool(jnp.all(jnp.isfinite(grads))) and float(grads[70]) > 0  # x = -5: fading in from the left


def _buffers():
    depth = jnp.full((H, W), jnp.inf).at[10:, :].set(20.0).at[:, 11:13].set(15.0)
    coverage = jnp.isfinite(depth).astype(jnp.float32)
    light_pass = jnp.zeros((H, W)).at[3:6, 5:8].set(1.0) * (1 - coverage)
    return gr.Buffers(color=jnp.full((H, W, 3), 0.3), depth=depth, coverage=coverage, light_pass=light_pass)


# The screen-space effects; a volumetric medium (ScatteringFog) legitimately scatters a light behind the camera.
SCREEN_SPACE = (gr.GodRays, gr.FlareOuts, gr.SunOvercast, gr.LensDirt, gr.SunSpot)
LIGHT_DRIVEN = [name for name in gr.PRESETS if isinstance(gr.preset(name), SCREEN_SPACE)]


@pytest.mark.parametrize("name", LIGHT_DRIVEN)
def test_every_light_driven_effect_fades_off_screen_and_vanishes_behind(name):
    effect = gr.preset(name)
    buffers = _buffers()
    layer = jax.jit(lambda light, front: effect.layer(buffers, light, light_in_front=front))
    on_screen = layer(jnp.array([6.5, 4.5]), True)
    assert float(jnp.abs(on_screen).max()) > 0
    assert float(jnp.abs(layer(jnp.array([6.5, 4.5]), False)).max()) == 0.0
    far_away = layer(jnp.array([-W * 2.0, 4.5]), True)  # beyond the default fade (half the larger side)
    assert float(jnp.abs(far_away).max()) == 0.0
    on_axis = layer(jnp.array([W / 2, H / 2]), True)
    assert bool(jnp.all(jnp.isfinite(on_axis)))


def test_fade_distance_is_fittable_for_god_rays():
    buffers = _buffers()
    light = jnp.array([-6.0, 4.5])  # just off the left edge
    effect = gr.preset("kbengine_flares")
    grad = jax.grad(lambda e: e.layer(buffers, light).sum())(effect).offscreen_fade
    assert np.isfinite(float(grad)) and float(grad) > 0  # a longer fade keeps more of the flare


def test_bloom_ignores_the_light():
    buffers = _buffers()
    bloom = gr.preset("vbex_bloom")
    buffers = gr.Buffers(color=buffers.color.at[2:4, 2:4].set(9.0), depth=buffers.depth, coverage=buffers.coverage)
    np.testing.assert_array_equal(
        bloom.layer(buffers, jnp.array([5.0, 5.0])), bloom.layer(buffers, jnp.array([-1e4, 0.0]), light_in_front=False)
    )


FAR_LIGHTS = [(1e38, 5.0), (-3.4e38, 5.0), (3.4e38, -3.4e38), (5.0, 1e39), (2e9, 1e9)]
"""Beyond what float32 arithmetic on pixel distances keeps finite; the last, past `MAX_LIGHT_PX` without overflow."""


@pytest.mark.parametrize("name", slow_where(sorted(gr.PRESETS)))
@pytest.mark.filterwarnings("ignore:overflow encountered in cast:RuntimeWarning")  # 1e39 becomes inf, on purpose
def test_lights_beyond_float32_reach_are_drawn_as_at_the_bound(name):
    """A light past `MAX_LIGHT_PX` is moved along its direction to it: finite values and gradients, faded out."""
    effect = gr.preset(name)
    buffers = _buffers()

    def loss(light):
        drawn = effect.layer(buffers, light)
        return jnp.sum(drawn**2), drawn

    grad_and_layer = jax.jit(jax.grad(loss, has_aux=True))  # one program: the layer and its gradient
    for light in FAR_LIGHTS:
        grad, drawn = grad_and_layer(jnp.asarray(light))
        assert bool(jnp.all(jnp.isfinite(drawn))) and bool(jnp.all(jnp.isfinite(grad))), light
        if isinstance(effect, SCREEN_SPACE):
            assert float(jnp.abs(drawn).max()) == 0.0, light


def test_the_light_is_moved_along_its_direction_and_near_lights_are_kept_exactly():
    bounded = check_light
    np.testing.assert_array_equal(bounded(jnp.asarray([12.5, -3.0])), [12.5, -3.0])
    np.testing.assert_allclose(bounded(jnp.asarray([4e9, -2e9])), [MAX_LIGHT_PX, -MAX_LIGHT_PX / 2], rtol=1e-6)
    np.testing.assert_allclose(bounded((1e39, 5.0)), [MAX_LIGHT_PX, 5e-30], atol=1e-35)  # bounded in float64
    np.testing.assert_array_equal(bounded(jnp.asarray([jnp.inf, 5.0])), [MAX_LIGHT_PX, 0.0])  # along the axis
    rays = jnp.ones((H, W, 3))
    far = gr.radial_rays(rays, jnp.asarray([1e38, 1e37]), num_samples=4, density=1.0, decay=0.9, weight=1.0,
                         exposure=1.0)  # fmt: skip
    at_bound = gr.radial_rays(rays, jnp.asarray([MAX_LIGHT_PX, MAX_LIGHT_PX / 10]), num_samples=4, density=1.0,
                              decay=0.9, weight=1.0, exposure=1.0)  # fmt: skip
    np.testing.assert_array_equal(far, at_bound)
