"""`VolumetricFog`: the kernel's terms composited, params files, presets and a fit that recovers the medium."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import godrays_jax as gr
from godrays_jax.effects.serialization import load_effect, save_effect
from godrays_jax.effects.volumetric import march_factor, silhouette_coverage
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
        thickness=0.15, edge_softness=0.05, coverage=silhouette_coverage(buffers.coverage, buffers.depth, buffers.color), **MEDIUM,
        **EFFECT,
    )  # fmt: skip
    np.testing.assert_allclose(effect(buffers, jnp.asarray(LIGHT), light_depth=20.0), expected, rtol=1e-6)
    layer = effect.layer(buffers, jnp.asarray(LIGHT), light_depth=20.0)
    surface, _, _ = effect.terms(buffers, jnp.asarray(LIGHT), light_depth=20.0)
    np.testing.assert_allclose(buffers.color * surface[..., None] + layer, expected, rtol=1e-5, atol=1e-6)


def test_coverage_from_depth_alone_is_spread_like_a_pixel_filter(rng):
    buffers = _frame(rng)
    grey = jnp.full_like(buffers.color, 0.3)  # surface and sky alike: the colour cannot tell, the filter's spread stands in
    spread = np.asarray(silhouette_coverage(buffers.coverage, buffers.depth, grey))
    assert spread[6, 3] == pytest.approx(0.15) and spread[7, 3] == pytest.approx(0.85)  # the ground's edge
    assert spread[12 - 1, 0] == 1.0 and spread[0, 0] == 0.0
    measured = buffers.coverage.at[6, 3].set(0.4)  # a coverage pass: kept as it is
    np.testing.assert_array_equal(silhouette_coverage(measured, buffers.depth, buffers.color), measured)


def test_coverage_of_a_filtered_silhouette_is_read_from_its_colour():
    # A dark wall (columns 0-4) over a bright sky, column 4 blended by a pixel filter with known coverage; its depth is
    # one sample's (Cycles' Z): the wall's where it covers half or more. A bright emitter sits among the sky's pixels.
    surface, sky = np.array([0.05, 0.04, 0.03]), np.array([0.8, 0.85, 0.9])
    covered = np.array([0.3, 0.6, 0.2, 0.7, 0.45, 0.55, 0.35, 0.65])
    depth = np.full((8, 8), np.inf)
    depth[:, :4] = 5.0
    depth[:, 4] = np.where(covered >= 0.5, 5.0, np.inf)
    share = np.zeros((8, 8))
    share[:, :4], share[:, 4] = 1.0, covered
    color = share[..., None] * surface + (1 - share[..., None]) * sky
    color[3, 5] = 50.0
    estimate = np.asarray(silhouette_coverage(jnp.asarray(np.isfinite(depth), jnp.float32), jnp.asarray(depth, jnp.float32),
                                              jnp.asarray(color, jnp.float32)))  # fmt: skip
    np.testing.assert_allclose(estimate[:, 4], covered, atol=1e-5)
    np.testing.assert_allclose(estimate[:, :4], 1.0, atol=1e-5)
    np.testing.assert_allclose(estimate[:, 6:], 0.0, atol=1e-5)


def _silhouette_coverage_loop(coverage, depth, color):
    """`silhouette_coverage` pixel by pixel: the filter's spread, or at a silhouette the colour's unmixed share."""
    if not np.all(coverage == np.isfinite(depth)):
        return coverage
    height, width = depth.shape
    display = lambda c: c / (1 + np.abs(c))  # noqa: E731
    out = np.zeros((height, width))
    for y in range(height):
        for x in range(width):
            around = [(min(max(y + dy, 0), height - 1), min(max(x + dx, 0), width - 1))
                      for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dy, dx) != (0, 0)]  # fmt: skip
            spread = sum(
                (0.7 if dy == 0 else 0.15) * (0.7 if dx == 0 else 0.15)
                * coverage[min(max(y + dy, 0), height - 1), min(max(x + dx, 0), width - 1)]
                for dy in (-1, 0, 1) for dx in (-1, 0, 1)
            )  # fmt: skip
            own = depth[y, x]
            finite = [depth[p] for p in around if np.isfinite(depth[p])]
            at = own if np.isfinite(own) else min(finite, default=np.inf)
            if not np.isfinite(at) or (np.isfinite(own) and len(finite) == 8):
                out[y, x] = spread
                continue
            same = [color[p] for p in around if np.isfinite(depth[p]) and abs(depth[p] - at) <= 0.05 * at]
            skies = [color[p] for p in around if not np.isfinite(depth[p])]
            if not same and np.isfinite(own):
                same = [color[y, x]]
            if not skies and not np.isfinite(own):
                skies = [color[y, x]]
            if not same or not skies:
                out[y, x] = spread
                continue
            surface, sky = np.median(same, axis=0), np.median(skies, axis=0)
            share = np.clip(np.dot(color[y, x] - sky, surface - sky) / max(np.dot(surface - sky, surface - sky), 1e-20), 0, 1)
            trust = np.clip((np.mean(np.abs(display(surface) - display(sky))) - 0.02) / 0.03, 0, 1)
            out[y, x] = trust * share + (1 - trust) * spread
    return out


def test_silhouette_coverage_matches_a_loop(rng):
    buffers = _frame(rng)
    color = np.asarray(buffers.color, np.float64) * rng.choice([0.02, 1.0], (HEIGHT, WIDTH, 1))  # some contrasts too low
    depth, coverage = np.asarray(buffers.depth, np.float64), np.asarray(buffers.coverage, np.float64)
    expected = _silhouette_coverage_loop(coverage, depth, color)
    got = silhouette_coverage(jnp.asarray(coverage, jnp.float32), jnp.asarray(depth, jnp.float32), jnp.asarray(color, jnp.float32))
    np.testing.assert_allclose(got, expected, atol=2e-5)
    vmapped = jax.jit(jax.vmap(silhouette_coverage))(*(jnp.asarray(a, jnp.float32)[None] for a in (coverage, depth, color)))
    np.testing.assert_allclose(vmapped[0], expected, atol=2e-5)


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
