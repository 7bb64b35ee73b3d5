"""Several lights in one frame (`effects.lights`): one light is the effect itself, several add as the physics does,
against sums of the single-light layers and terms taken apart in NumPy."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import godrays_jax as gr
from godrays_jax.pipeline.batch import frames_function

from frames import LIGHT, make_frame, small

SECOND = jnp.asarray([3.2, 14.7], jnp.float32)  # on the ground, left of the occluder
RED = (1.5, 0.4, 0.2)


def cheap_volumetric():
    """A `VolumetricFog` with shadows from a few samples: the lights' sums, not the shadows, are under test."""
    effect = gr.preset("physically_based")
    return dataclasses.replace(effect, num_view_steps=4, num_shadow_samples=4, resolution_factor=2)


ADDITIVE = ["xna_crepuscular", "kbengine_flares", "sun_overcast", "vbex_lens_dirt", "vbex_sun_spot"]


@pytest.mark.parametrize("name", ADDITIVE)
def test_an_additive_effect_under_two_lights_adds_their_tinted_layers(name):
    effect, frame = small(gr.preset(name)), make_frame()
    both = gr.lit_by(effect, frame, [gr.Light(LIGHT), gr.Light(SECOND, tint=RED)])
    layers = [np.asarray(effect.layer(frame, xy), np.float64) for xy in (LIGHT, SECOND)]
    colour = np.asarray(frame.color, np.float64)
    expected = colour + layers[0][..., :3] + layers[1][..., :3] * np.asarray(RED)
    np.testing.assert_allclose(np.asarray(both), expected, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("name", [*ADDITIVE, "vbex_bloom", "participating_media"])
def test_one_light_of_tint_one_is_the_effect_itself(name):
    effect, frame = small(gr.preset(name)), make_frame()
    for in_front in (True, False):
        alone = gr.lit_by(effect, frame, [gr.Light(LIGHT, in_front=in_front)])
        np.testing.assert_allclose(np.asarray(alone), np.asarray(effect(frame, LIGHT, light_in_front=in_front)),
                                   rtol=1e-5, atol=1e-6)  # fmt: skip


def test_one_light_of_tint_one_is_the_volumetric_fog_itself():
    effect, frame = cheap_volumetric(), make_frame()
    alone = gr.lit_by(effect, frame, [gr.Light(LIGHT, depth=30.0)])
    expected = effect(frame, LIGHT, light_depth=30.0)
    np.testing.assert_allclose(np.asarray(alone), np.asarray(expected), rtol=1e-5, atol=1e-6)


def fog_from_terms(effect, frame, terms, tints):
    """The fogged frame in float64 from each light's `(surface, scattered, ambient)` and tint, as `effects.lights`
    says: each light's in-scattering times its tint, the ambient once, the surfaces dimmed toward each light by its
    share of the tints' means."""
    terms = [[np.asarray(term, np.float64) for term in each] for each in terms]
    means = np.asarray([np.mean(tint) for tint in tints])
    surface = sum(share * each[0] for share, each in zip(means / means.sum(), terms))
    light_color = np.asarray(effect.medium.light_color, np.float64)
    added = sum(each[1][..., None] * light_color * np.asarray(tint) for each, tint in zip(terms, tints))
    added = added + terms[0][2][..., None] * np.asarray(effect.medium.ambient_color, np.float64)
    return np.asarray(frame.color, np.float64) * surface[..., None] + added


def test_the_volumetric_fog_under_two_lights_from_its_terms():
    """Each light's in-scattering times its tint, the ambient once, the surfaces dimmed toward each light by its
    share of the tints' means."""
    effect, frame = cheap_volumetric(), make_frame()
    lights = [gr.Light(LIGHT), gr.Light(SECOND, depth=20.0, tint=RED)]
    both = np.asarray(gr.lit_by(effect, frame, lights), np.float64)
    terms = [[np.asarray(term, np.float64) for term in effect.terms(frame, light.xy, light_depth=light.depth)]
             for light in lights]  # fmt: skip
    np.testing.assert_allclose(terms[0][2], terms[1][2], rtol=1e-6)  # the ambient does not depend on the light
    np.testing.assert_allclose(both, fog_from_terms(effect, frame, terms, [(1.0, 1.0, 1.0), RED]), rtol=1e-5, atol=1e-6)
    # The order of the lights changes nothing.
    swapped = np.asarray(gr.lit_by(effect, frame, lights[::-1]), np.float64)
    np.testing.assert_allclose(swapped, both, rtol=1e-5, atol=1e-6)
    # Compiled, the same frame (the jit, vmap and gradient test below starts from a compiled one).
    np.testing.assert_allclose(eqx.filter_jit(gr.lit_by)(effect, frame, lights), both, rtol=1e-5, atol=1e-6)


def test_lights_of_one_kind_are_traced_once_with_each_lights_own_terms(monkeypatch):
    """Two lamps (both point lights, both in front as Python bools) go through one loop: the terms are traced once,
    and each light's are the terms `effect.terms` gives it alone. A sun beside a lamp is traced apart."""
    effect, frame = cheap_volumetric(), make_frame()
    lamps = [gr.Light(LIGHT, depth=30.0), gr.Light(SECOND, depth=20.0, tint=RED)]
    alone = [[np.asarray(term) for term in effect.terms(frame, light.xy, light_depth=light.depth)] for light in lamps]
    traced = []
    terms = type(effect).terms

    def counted(self, *args, **kwargs):
        traced.append(kwargs["light_depth"])
        return terms(self, *args, **kwargs)

    monkeypatch.setattr(type(effect), "terms", counted)
    both = np.asarray(gr.lit_by(effect, frame, lamps), np.float64)
    assert len(traced) == 1 and isinstance(traced[0], jax.core.Tracer)
    np.testing.assert_allclose(both, fog_from_terms(effect, frame, alone, [(1.0, 1.0, 1.0), RED]), rtol=1e-5, atol=1e-6)
    traced.clear()
    gr.lit_by(effect, frame, [gr.Light(LIGHT), lamps[1]])
    assert len(traced) == 2  # the sun as a Python number drops the point light's branches: a program of its own


def test_the_scattering_fog_counts_its_ambient_light_once():
    effect, frame = small(gr.preset("participating_media")), make_frame()
    both = np.asarray(gr.lit_by(effect, frame, [gr.Light(LIGHT), gr.Light(SECOND, tint=RED)]), np.float64)
    first = np.asarray(effect(frame, LIGHT), np.float64)
    medium = dataclasses.replace(effect.medium, ambient_color=jnp.zeros(3))
    second = np.asarray(dataclasses.replace(effect, medium=medium).layer(frame, SECOND), np.float64)
    np.testing.assert_allclose(both, first + second * np.asarray(RED), rtol=1e-5, atol=1e-6)


def test_a_light_behind_the_camera_adds_nothing_to_an_effect_that_hides_it():
    effect, frame = small(gr.preset("xna_crepuscular")), make_frame()
    one = gr.lit_by(effect, frame, [gr.Light(LIGHT)])
    with_hidden = gr.lit_by(effect, frame, [gr.Light(LIGHT), gr.Light(SECOND, in_front=False)])
    np.testing.assert_allclose(np.asarray(with_hidden), np.asarray(one), rtol=1e-6, atol=1e-7)


def test_lights_are_refused_where_they_do_not_add():
    frame = make_frame()
    with pytest.raises(ValueError, match="lights"):
        gr.lit_by(small(gr.preset("xna_crepuscular")), frame, [])
    with pytest.raises(ValueError, match="lights"):
        gr.lit_by(small(gr.preset("xna_crepuscular")), frame, [LIGHT])
    with pytest.raises(ValueError, match=r"lights\[1\]\.tint must be finite and >= 0"):
        negative = gr.Light(SECOND, tint=(1.0, -0.5, 1.0))
        gr.lit_by(small(gr.preset("xna_crepuscular")), frame, [gr.Light(LIGHT), negative])
    multiply = dataclasses.replace(small(gr.preset("xna_crepuscular")), blend_mode="multiply")
    with pytest.raises(ValueError, match="lights: GodRays blends 'multiply'"):
        gr.lit_by(multiply, frame, [gr.Light(LIGHT), gr.Light(SECOND)])
    with pytest.raises(ValueError, match="lights: GodRays blends 'multiply'"):  # a batch's, before any frame
        frames_function(multiply, beside=[gr.Light(SECOND)])
    with pytest.raises(ValueError, match="lights: GodRays blends 'multiply'"):
        frames_function(multiply, light_tint=(1.0, 0.5, 0.5))
    frames_function(multiply)  # one light of its own: the effect as it is


@pytest.mark.slow
def test_lights_under_jit_and_vmap_with_finite_gradients_in_their_positions_and_tints():
    effect, frame = cheap_volumetric(), make_frame()

    def loss(first, second, tint):  # two lamps: one loop over both (the sun beside a lamp is compiled above)
        lights = [gr.Light(first, depth=30.0), gr.Light(second, depth=20.0, tint=tint)]
        return jnp.mean(gr.lit_by(effect, frame, lights) ** 2)

    # These lights' eager frame is checked in `test_lights_of_one_kind_are_traced_once_with_each_lights_own_terms`.
    jitted = jax.jit(loss)(LIGHT, SECOND, jnp.asarray(RED))
    seconds = jnp.stack([SECOND, SECOND + 1.0])
    batched = jax.jit(jax.vmap(loss, in_axes=(None, 0, None)))(LIGHT, seconds, jnp.asarray(RED))
    np.testing.assert_allclose(batched[0], jitted, rtol=1e-5)
    assert batched[1] != batched[0]  # each frame of the batch its own second light
    gradients = jax.jit(jax.grad(loss, argnums=(0, 1, 2)))(LIGHT, SECOND, jnp.asarray(RED))
    assert all(np.isfinite(np.asarray(g)).all() for g in gradients)
    assert np.abs(np.asarray(gradients[2])).sum() > 0  # the second light's tint reaches the frame
