"""Participating media (media.py, effects.ScatteringFog) against a per-pixel NumPy loop."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads
from reference import radial_rays as reference_rays

import godrays_jax as gr
from godrays_jax.effects.fields import field_value
from godrays_jax.kernels.media import apply_fog, henyey_greenstein, in_scattering, transmittance

HEIGHT, WIDTH = 6, 8
LIGHT = (3.3, 1.7)
MEDIUM = dict(extinction=0.05, max_distance=30.0, ambient_color=(0.1, 0.2, 0.3), light_color=(2.0, 1.5, 1.0), anisotropy=0.7)
FOG = dict(fov_x_deg=60.0, **MEDIUM)
"""The kernels' options; the effect holds `MEDIUM` in its `medium` part (`_fog`)."""


def _fog(**fields):
    return gr.ScatteringFog(medium=gr.Medium(**MEDIUM), fov_x_deg=FOG["fov_x_deg"], **fields)


def _frame(rng, dtype=np.float64):
    depth = np.full((HEIGHT, WIDTH), np.inf)
    depth[3:] = rng.uniform(5.0, 50.0, (HEIGHT - 3, WIDTH))  # ground nearer and farther than max_distance
    depth[:, 5] = 12.0  # a pillar
    coverage = np.isfinite(depth).astype(float)
    color = rng.uniform(0.0, 2.0, (HEIGHT, WIDTH, 4))
    return gr.Buffers(color=jnp.asarray(color, dtype), depth=jnp.asarray(depth, dtype), coverage=jnp.asarray(coverage, dtype))


def reference_fog(color, depth, light, *, fov_x_deg, extinction, max_distance, ambient_color, light_color, anisotropy, lit=None, in_front=True):
    """One pixel at a time: direction through the pixel, HG phase, Beer-Lambert, single scattering."""
    height, width = depth.shape
    focal = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
    sun = np.array([(light[0] - width / 2) / focal, (height / 2 - light[1]) / focal, 1.0 if in_front else -1.0])
    sun /= np.linalg.norm(sun)
    out = np.array(color, np.float64)
    for row in range(height):
        for col in range(width):
            view = np.array([(col + 0.5 - width / 2) / focal, (height / 2 - row - 0.5) / focal, 1.0])
            cosine = view @ sun / np.linalg.norm(view)
            g = anisotropy
            phase = (1 - g * g) / (4 * math.pi * (1 + g * g - 2 * g * cosine) ** 1.5)
            distance = min(depth[row, col], max_distance)
            t = math.exp(-extinction * distance)
            sun_share = 1.0 if lit is None else lit[row, col]
            scattered = (1 - t) * (np.asarray(ambient_color) + np.asarray(light_color) * phase * sun_share)
            out[row, col, :3] = color[row, col, :3] * t + scattered
    return out


def test_henyey_greenstein_integrates_to_one_and_is_isotropic_at_zero():
    cosines = np.linspace(-1.0, 1.0, 200001)
    for g in (-0.5, 0.0, 0.8):
        values = np.asarray(henyey_greenstein(jnp.asarray(cosines), anisotropy=g))
        # The sphere's measure is 2 pi d(cos theta).
        assert 2 * math.pi * np.trapezoid(values, cosines) == pytest.approx(1.0, rel=1e-4)
    np.testing.assert_allclose(henyey_greenstein(jnp.asarray([-1.0, 0.3, 1.0]), anisotropy=0.0), 1 / (4 * math.pi), rtol=1e-6)


def test_apply_fog_matches_loop_eager_jit_vmap(x64, rng):
    frame = _frame(rng)
    lit = rng.uniform(0.0, 1.0, (HEIGHT, WIDTH))
    expected = reference_fog(np.asarray(frame.color), np.asarray(frame.depth), LIGHT, lit=lit, **FOG)
    fog = lambda color, depth, light: apply_fog(color, depth, light, lit=jnp.asarray(lit), **FOG)  # noqa: E731
    np.testing.assert_allclose(fog(frame.color, frame.depth, jnp.asarray(LIGHT)), expected, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(jax.jit(fog)(frame.color, frame.depth, jnp.asarray(LIGHT)), expected, rtol=1e-10, atol=1e-12)
    lights = jnp.asarray([LIGHT, (-20.0, 40.0)])
    batched = jax.vmap(fog, in_axes=(None, None, 0))(frame.color, frame.depth, lights)
    second = reference_fog(np.asarray(frame.color), np.asarray(frame.depth), (-20.0, 40.0), lit=lit, **FOG)
    np.testing.assert_allclose(batched, np.stack([expected, second]), rtol=1e-10, atol=1e-12)
    assert np.array_equal(batched[..., 3], np.broadcast_to(frame.color[..., 3], (2, HEIGHT, WIDTH)))  # alpha kept


def test_transmittance_sky_sees_max_distance_and_layer_completes_the_frame(rng):
    frame = _frame(rng, np.float32)
    t = transmittance(frame.depth, extinction=0.05, max_distance=30.0)
    np.testing.assert_allclose(t[0, :5], math.exp(-1.5), rtol=1e-6)  # sky
    np.testing.assert_allclose(t[:, 5], math.exp(-0.6), rtol=1e-6)  # pillar at 12 units
    fog = gr.ScatteringFog(num_samples=3.0, max_samples=3)
    t_fog = transmittance(frame.depth, extinction=fog.medium.extinction, max_distance=fog.medium.max_distance)
    np.testing.assert_allclose(
        fog(frame, jnp.asarray(LIGHT))[..., :3], frame.color[..., :3] * t_fog[..., None] + fog.layer(frame, jnp.asarray(LIGHT)),
        rtol=1e-5, atol=1e-6,
    )  # fmt: skip


def _expected_effect(effect, frame, light, in_front=True):
    """The effect by hand: lit from the NumPy radial-rays loop, then the per-pixel fog loop."""
    sky = 1.0 - np.asarray(frame.coverage)[..., None]
    n = int(effect.num_samples)
    options = dict(num_samples=n, density=float(effect.density), decay=float(effect.decay), weight=1.0, exposure=1.0)
    rays = reference_rays(sky, light, **options)[..., 0]
    normaliser = 1.0 + sum(float(effect.decay) ** i for i in range(n))
    lit = 1.0 - float(effect.shadow_strength) * (1.0 - rays / normaliser) * (1.0 if in_front else 0.0)
    fog = {name: np.asarray(getattr(effect.medium, name)).tolist() for name in MEDIUM} | {"fov_x_deg": float(effect.fov_x_deg)}
    return reference_fog(np.asarray(frame.color), np.asarray(frame.depth), light, lit=lit, in_front=in_front, **fog)


def test_scattering_fog_effect_matches_loop_with_shafts_and_behind_camera(x64, rng):
    frame = _frame(rng)
    effect = _fog(shadow_strength=0.8, density=0.9, decay=0.9, num_samples=5.0, max_samples=6)
    call = eqx.filter_jit(lambda e, f, light, front: e(f, light, light_in_front=front))
    np.testing.assert_allclose(call(effect, frame, jnp.asarray(LIGHT), True), _expected_effect(effect, frame, LIGHT), rtol=1e-9, atol=1e-12)
    behind = call(effect, frame, jnp.asarray(LIGHT), False)
    assert np.all(np.isfinite(behind))
    # Behind the camera: no screen-space shafts (lit = 1) and the backward lobe.
    np.testing.assert_allclose(behind, _expected_effect(effect, frame, LIGHT, in_front=False), rtol=1e-9, atol=1e-12)
    # Shadowed shafts only ever remove sun light: the shaded frame is never brighter.
    unshadowed = eqx.tree_at(lambda e: e.shadow_strength, effect, jnp.asarray(0.0))
    assert np.all(np.asarray(effect(frame, jnp.asarray(LIGHT))) <= np.asarray(unshadowed(frame, jnp.asarray(LIGHT))) + 1e-12)


FITTED = ("medium.extinction", "medium.max_distance", "medium.anisotropy", "medium.light_color", "medium.ambient_color",
          "fov_x_deg", "shadow_strength", "density", "decay", "num_samples", "offscreen_fade")  # fmt: skip


def test_scattering_fog_gradients_float64(x64, rng):
    frame = _frame(rng)
    effect = _fog(shadow_strength=0.8, density=0.9, decay=0.9, num_samples=4.6, max_samples=6)
    values = tuple(field_value(effect, name) for name in FITTED)

    def render(*values):
        return jnp.sum(eqx.tree_at(lambda e: [field_value(e, n) for n in FITTED], effect, list(values))(frame, jnp.asarray(LIGHT)) ** 2)

    check_grads(jax.jit(render), values, order=1, modes=("fwd", "rev"), eps=1e-6)


def test_degenerate_inputs_give_finite_values_and_gradients():
    # All sky; the light on a pixel centre, far off screen or behind the camera; no medium or an empty one.
    frame = gr.Buffers(color=jnp.ones((4, 5, 3)), depth=jnp.full((4, 5), jnp.inf), coverage=jnp.zeros((4, 5)))
    small = dict(num_samples=3.0, max_samples=3)
    effects = [gr.ScatteringFog(medium=gr.Medium(**{name: value}), **small)
               for name, value in (("extinction", 0.0), ("max_distance", 0.0), ("anisotropy", 0.95))]  # fmt: skip
    value_and_grad = eqx.filter_jit(eqx.filter_value_and_grad(lambda e, light, front: jnp.sum(e(frame, light, light_in_front=front))))
    for effect in effects:
        for light, front in (((2.5, 1.5), True), ((-400.0, 90.0), True), ((2.5, 1.5), False)):
            value, grads = value_and_grad(effect, jnp.asarray(light), jnp.asarray(front))
            assert np.isfinite(value)
            assert all(np.all(np.isfinite(g)) for g in jax.tree_util.tree_leaves(grads))
    np.testing.assert_allclose(effects[0](frame, jnp.asarray([2.5, 1.5])), frame.color, rtol=1e-6)


def test_preset_round_trips_and_errors_name_the_argument(tmp_path):
    effect = gr.preset("participating_media")
    assert isinstance(effect, gr.ScatteringFog) and effect.max_samples == 128
    gr.save_effect(tmp_path / "fog.json", effect)
    loaded = gr.load_effect(tmp_path / "fog.json")
    assert gr.effect_to_dict(loaded) == gr.effect_to_dict(effect)
    assert set(gr.parameter_bounds(effect)) == set(FITTED)
    depth = jnp.ones((3, 4))
    with pytest.raises(ValueError, match="ambient_color"):
        in_scattering(depth, (1.0, 1.0), **{**FOG, "ambient_color": (0.1, 0.2)})
    with pytest.raises(ValueError, match="lit"):
        in_scattering(depth, (1.0, 1.0), **FOG, lit=jnp.ones((2, 2)))
    with pytest.raises(ValueError, match="depth"):
        apply_fog(jnp.ones((3, 4, 3)), jnp.ones((3, 5)), (1.0, 1.0), **FOG)
    with pytest.raises(ValueError, match="anisotropy"):
        henyey_greenstein(jnp.zeros(3), anisotropy=jnp.zeros(2))
