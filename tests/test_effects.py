"""Whole effects: every preset runs eagerly, jitted and vmapped; parameters round-trip through JSON;
gradients are finite; degenerate frames (all sky, no sky, light behind the camera) stay finite."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import godrays_jax as gr
from godrays_jax.effects.fields import field_value, parameter_bounds
from frames import HEIGHT, LIGHT, WIDTH, make_frame, slow_where, small

LIGHT_DEPTH = 1000.0
"""The sun's distance in the XNA article's author's sample: the XNA preset's flare is `SunSize / z` of it (1.5 UV)."""

@pytest.mark.parametrize("name", slow_where(sorted(gr.PRESETS)))
def test_preset_runs_jit_vmap_and_adds_light(name):
    # Eager execution of every kernel is covered in test_kernels.py; here one
    # compilation per preset keeps the suite fast.
    effect = small(gr.preset(name))
    frame = make_frame()

    @eqx.filter_jit
    def both(effect, lights):
        single = effect(frame, lights[0], light_depth=LIGHT_DEPTH)
        batched = jax.vmap(lambda light: effect(frame, light, light_depth=LIGHT_DEPTH))(lights)
        return single, batched, effect.layer(frame, lights[0], light_depth=LIGHT_DEPTH)

    single, batched, layer = both(effect, jnp.stack([LIGHT, LIGHT + 1.0]))
    assert single.shape == frame.color.shape and bool(jnp.all(jnp.isfinite(single)))
    # VolumetricFog's shadow test amplifies float32 rounding at its slabs' soft faces (1.4e-5 here, on the occluder's
    # top, under the suite's XLA flags; 0 under XLA's defaults), which programs compiled apart round apart.
    np.testing.assert_allclose(batched[0], single, rtol=5e-4 if isinstance(effect, gr.VolumetricFog) else 1e-5, atol=1e-6)
    assert float(jnp.max(layer)) > 0.0, "the effect must add something to a frame with a visible sun"
    if type(effect).__call__ is gr.Effect.__call__:  # effects that blend a layer (ScatteringFog attenuates)
        np.testing.assert_allclose(single, gr.blend(frame.color, layer, mode=effect.blend_mode), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("name", sorted(gr.PRESETS))
def test_preset_parameters_round_trip_through_json(tmp_path, name):
    effect = gr.preset(name)
    path = tmp_path / "params.json"
    gr.save_effect(path, effect)
    loaded = gr.load_effect(path)
    assert type(loaded) is type(effect)
    for field in dataclasses.fields(effect):
        np.testing.assert_array_equal(np.asarray(getattr(loaded, field.name)), np.asarray(getattr(effect, field.name)))


@pytest.mark.parametrize("name", ["xna_crepuscular", "galaxy_vls", "kbengine_flares", "sun_overcast"])
def test_seed_effect_gradients_are_finite_and_nonzero(name):
    effect = small(gr.preset(name))
    frame = make_frame()
    params, static = eqx.partition(effect, eqx.is_inexact_array)

    def total(params):
        return jnp.sum(eqx.combine(params, static)(frame, LIGHT, light_depth=LIGHT_DEPTH))

    grads = jax.jit(jax.grad(total))(params)
    leaves = jax.tree_util.tree_leaves(grads)
    assert all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in leaves)
    assert any(float(jnp.max(jnp.abs(leaf))) > 0 for leaf in leaves)


@pytest.mark.parametrize("sky_rows", [0, HEIGHT], ids=["no_sky", "all_sky"])
def test_degenerate_frames_give_finite_values_and_gradients(sky_rows):
    frame = make_frame(sky_rows=sky_rows, occluder_cols=(0, 0))
    if sky_rows == 0:
        frame = eqx.tree_at(lambda b: b.depth, frame, jnp.full((HEIGHT, WIDTH), 3.0))
        frame = eqx.tree_at(lambda b: b.coverage, frame, jnp.ones((HEIGHT, WIDTH)))
    effect = small(gr.preset("xna_crepuscular"))
    value, grad = eqx.filter_jit(eqx.filter_value_and_grad(lambda e, light: jnp.sum(e(frame, light))))(
        effect, jnp.asarray([12.5, 5.5])  # the light exactly on a pixel centre
    )
    assert np.isfinite(float(value))
    assert all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree_util.tree_leaves(grad))


def test_light_behind_the_camera_leaves_the_frame_unchanged():
    frame = make_frame()
    for name in ("xna_crepuscular", "kbengine_flares", "sun_overcast"):
        effect = small(gr.preset(name))
        behind = eqx.filter_jit(lambda e: e(frame, LIGHT, light_in_front=False))(effect)
        np.testing.assert_array_equal(behind, frame.color)


def test_relaxed_sample_count_equals_integer_count_in_the_effect():
    frame = make_frame()
    effect = gr.GodRays(num_samples=6.0, max_samples=10, source="disc", flare_size=5.0, units="px")
    flare = gr.procedural_flare()[::-1, ::-1]  # the XNA article samples its flare at .5 - offset
    exact = gr.radial_rays(
        gr.light_source_mask(HEIGHT, WIDTH, LIGHT, flare_size=5.0, texture=flare) * gr.coverage_mask(frame.coverage)[..., None],
        LIGHT, num_samples=6, density=0.5, decay=0.95, weight=1.0, exposure=0.15,
    )  # fmt: skip
    np.testing.assert_allclose(effect.layer(frame, LIGHT)[..., :1], exact, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("name", sorted(gr.PRESETS))
def test_with_camera_sets_the_camera_fields_an_effect_reads_and_nothing_else(name):
    """`Effect.with_camera` gives an effect a frame's field of view and clip planes in the fields it names
    (`CAMERA_FIELDS`), each a field of the effect; every other field, and an effect that reads no camera, unchanged."""
    effect = gr.preset(name)
    names = {field.name for field in dataclasses.fields(effect)}
    assert set(type(effect).CAMERA_FIELDS) <= names
    assert ("near_plane" in type(effect).CAMERA_FIELDS) == ("far_plane" in type(effect).CAMERA_FIELDS)
    assert effect.with_camera() is effect
    seen = effect.with_camera(fov_x_deg=33.0, clip_planes=(0.5, 500.0))
    expected = {"fov_x_deg": 33.0, "near_plane": 0.5, "far_plane": 500.0}
    for field in names:
        value, before = getattr(seen, field), getattr(effect, field)
        if field in type(effect).CAMERA_FIELDS:
            assert float(value) == pytest.approx(expected[field])
        elif eqx.is_array(before):
            assert value is before
        else:
            assert value == before
    if not type(effect).CAMERA_FIELDS:
        assert seen is effect


def test_bounds_cover_every_fittable_field_and_contain_the_presets():
    for name in gr.PRESETS:
        effect = gr.preset(name)
        bounds = parameter_bounds(effect)
        params = {name for name in gr.field_metadata(effect) if isinstance(field_value(effect, name), jax.Array)}
        params -= {"flare_texture"}  # a texture, not a bounded scalar
        assert params <= set(bounds), params - set(bounds)
        for field_name, (low, high) in bounds.items():
            value = np.asarray(field_value(effect, field_name))
            assert np.all(value >= low) and np.all(value <= high), (name, field_name, value)


def test_bad_options_raise_value_errors_naming_them():
    with pytest.raises(ValueError, match="blend_mode"):
        gr.GodRays(blend_mode="overlay")
    with pytest.raises(ValueError, match="source"):
        gr.GodRays(source="moon")
    with pytest.raises(ValueError, match="unknown preset"):
        gr.preset("unreal")
    with pytest.raises(ValueError, match="light_pass"):
        gr.GodRays(source="light_pass", num_samples=4.0, max_samples=4)(
            eqx.tree_at(lambda b: b.light_pass, make_frame(), None, is_leaf=lambda x: x is None), LIGHT
        )
    with pytest.raises(ValueError, match="unknown parameter"):
        gr.effect_from_dict({"effect": "GodRays", "densty": 0.5})
    with pytest.raises(ValueError, match="unknown effect"):
        gr.effect_from_dict({"effect": "Nope"})


def test_godrays_disc_runs_near_the_light_with_the_same_result():
    rng = np.random.default_rng(3)
    height, width = 120, 200
    buffers = gr.Buffers(color=jnp.asarray(rng.random((height, width, 3)), jnp.float32),
                         depth=jnp.where(jnp.asarray(rng.random((height, width))) < 0.7, jnp.inf, 5.0),
                         coverage=jnp.asarray(rng.random((height, width)) < 0.3, jnp.float32))  # fmt: skip
    effect = eqx.tree_at(lambda e: e.flare_size, gr.preset("xna_crepuscular"), jnp.float32(8.0 / width))
    for light in ([120.3, 40.6], [-3.0, 60.0]):
        light = jnp.asarray(light, jnp.float32)
        near_light = jax.jit(lambda b, xy: effect(b, xy))(buffers, light)  # fields concrete: the windowed loop
        whole = jax.jit(lambda e, b, xy: e(b, xy))(effect, buffers, light)  # fields traced: the whole frame
        np.testing.assert_allclose(near_light, whole, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("effect_type", [gr.GodRays, gr.FlareOuts])
def test_emitter_inputs_gradients_match_finite_differences(x64, effect_type):
    """The disc's radius, the light (drawing the disc and centring the copies) and the fade:
    derivative images sampled in the loop (forward mode) give the true derivative, both modes."""
    frame = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64), make_frame())
    counts = dict(num_samples=6.4, max_samples=8) if effect_type is gr.GodRays else dict(num_iters=4.6, max_iters=5)
    base = effect_type(source="disc", units="px", **counts)

    def layer(radius, light, fade, density_or_step):
        field = "density" if effect_type is gr.GodRays else "scale_step"
        effect = eqx.tree_at(lambda e: (e.flare_size, e.offscreen_fade, getattr(e, field)), base,
                             (radius, fade, density_or_step))  # fmt: skip
        return effect.layer(frame, light)

    # A light off the right edge, so the fade acts too; positions chosen off texel boundaries.
    density_or_step = 0.83 if effect_type is gr.GodRays else 1.07
    args = (jnp.float64(5.3), jnp.asarray([24.7, 5.35]), jnp.float64(0.4), jnp.float64(density_or_step))
    check_grads(jax.jit(layer), args, order=1, modes=("fwd", "rev"), eps=1e-6, atol=1e-4, rtol=1e-4)
    # Reverse mode equals a plain forward-mode Jacobian (the same loop, other transposition).
    reverse = jax.jit(jax.jacrev(lambda r: jnp.sum(layer(r, *args[1:]) ** 2)))(args[0])
    forward = jax.jit(jax.jacfwd(lambda r: jnp.sum(layer(r, *args[1:]) ** 2)))(args[0])
    np.testing.assert_allclose(reverse, forward, rtol=1e-10)
    assert float(jnp.abs(reverse)) > 0
