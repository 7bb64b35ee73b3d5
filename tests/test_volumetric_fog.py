"""`VolumetricFog`: the kernel's terms composited, params files, presets and a fit that recovers the medium."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import godrays_jax as gr
from godrays_jax.effects.serialization import load_effect, save_effect
from godrays_jax.effects.volumetric import filtered_coverage, march_factor
from godrays_jax.pipeline.compiled import render_compiled
from godrays_jax.pipeline.fit import fit

HEIGHT, WIDTH = 12, 16


def _frame(rng):
    depth = np.full((HEIGHT, WIDTH), np.inf, np.float32)
    depth[7:] = np.linspace(8.0, 30.0, 5)[:, None]  # ground
    depth[2:, 6:8] = 12.0  # a post below the sun
    color = rng.uniform(0.0, 1.0, (HEIGHT, WIDTH, 3)).astype(np.float32)
    return gr.Buffers(color=jnp.asarray(color), depth=jnp.asarray(depth), coverage=jnp.asarray(np.isfinite(depth), jnp.float32))


MEDIUM = dict(extinction=0.04, max_distance=40.0, anisotropy=0.7, light_color=(2.0, 1.6, 1.2),
              ambient_color=(0.1, 0.12, 0.15))  # fmt: skip
EFFECT = dict(direct_fraction=0.6, fov_x_deg=60.0, num_view_steps=8, num_shadow_samples=12, resolution_factor=2)
LIGHT = (7.3, 1.6)


def _fog(**medium):
    return gr.VolumetricFog(medium=gr.Medium(**{**MEDIUM, **medium}), **EFFECT)


def test_effect_is_the_kernel_composited(rng):
    buffers = _frame(rng)
    effect = _fog()
    expected = gr.apply_volumetric_fog(
        buffers.color, buffers.depth, jnp.asarray(LIGHT), light_depth=20.0, height_falloff=0.0, layer_top=1e4,
        thickness=0.15, edge_softness=0.05, coverage=filtered_coverage(buffers.coverage, buffers.depth), **MEDIUM,
        **EFFECT,
    )  # fmt: skip
    np.testing.assert_allclose(effect(buffers, jnp.asarray(LIGHT), light_depth=20.0), expected, rtol=1e-6)
    layer = effect.layer(buffers, jnp.asarray(LIGHT), light_depth=20.0)
    surface, _, _ = effect.terms(buffers, jnp.asarray(LIGHT), light_depth=20.0)
    np.testing.assert_allclose(buffers.color * surface[..., None] + layer, expected, rtol=1e-5, atol=1e-6)


def test_coverage_from_depth_alone_is_spread_like_a_pixel_filter(rng):
    buffers = _frame(rng)
    spread = np.asarray(filtered_coverage(buffers.coverage, buffers.depth))
    assert spread[6, 3] == pytest.approx(0.15) and spread[7, 3] == pytest.approx(0.85)  # the ground's edge
    assert spread[12 - 1, 0] == 1.0 and spread[0, 0] == 0.0
    measured = buffers.coverage.at[6, 3].set(0.4)  # a coverage pass: kept as it is
    np.testing.assert_array_equal(filtered_coverage(measured, buffers.depth), measured)


def test_march_factor_divides_both_sides():
    assert march_factor(180, 320, 4) == 4
    assert march_factor(180, 320, 8) == 5
    assert march_factor(181, 320, 4) == 1


def test_params_file_round_trip(tmp_path):
    effect = gr.preset("volumetric_haze")
    save_effect(tmp_path / "fog.json", effect)
    loaded = load_effect(tmp_path / "fog.json")
    assert type(loaded) is gr.VolumetricFog
    assert jax.tree.all(jax.tree.map(lambda a, b: bool(np.all(np.asarray(a) == np.asarray(b))), loaded, effect))


def test_static_counts_are_checked():
    with pytest.raises(ValueError, match="num_view_steps"):
        gr.VolumetricFog(num_view_steps=0)
    with pytest.raises(ValueError, match="thickness"):
        gr.VolumetricFog(thickness=-1.0)


def test_fit_recovers_the_medium(rng):
    buffers = _frame(rng)
    truth = _fog()
    target = render_compiled(truth, buffers, jnp.asarray(LIGHT), True, 20.0)
    start = _fog(extinction=0.02, anisotropy=0.5, light_color=(1.0, 1.0, 1.0))
    fixed = ("fov_x_deg", "medium.max_distance", "height_falloff", "layer_top", "thickness", "edge_softness",
             "direct_fraction", "medium.ambient_color")  # fmt: skip
    result = fit(start, buffers, jnp.asarray(LIGHT), target, fixed=fixed, light_depth=20.0, max_steps=30)
    assert result.loss_after < 1e-3 * result.loss_before
    assert float(result.effect.medium.extinction) == pytest.approx(0.04, rel=0.02)
    assert float(result.effect.medium.anisotropy) == pytest.approx(0.7, rel=0.02)


def test_light_depth_reaches_the_effect_through_fit(rng):
    buffers = _frame(rng)
    effect = _fog()
    near = render_compiled(effect, buffers, jnp.asarray(LIGHT), True, 15.0)
    sun = render_compiled(effect, buffers, jnp.asarray(LIGHT), True, math.inf)
    assert not np.allclose(near, sun)
    with pytest.raises(ValueError, match="light_depth"):
        fit(effect, buffers, jnp.asarray(LIGHT), sun, light_depth=-1.0, max_steps=1)
