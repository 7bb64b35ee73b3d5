"""A small synthetic frame and short-loop presets shared by the effect tests (a helper module, not a test file)."""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

import godrays_jax as gr

HEIGHT, WIDTH = 18, 24


def make_frame(sky_rows=10, occluder_cols=(11, 13)):
    depth = np.full((HEIGHT, WIDTH), np.inf, np.float32)
    depth[sky_rows:, :] = 8.0
    depth[:, occluder_cols[0] : occluder_cols[1]] = 4.0
    coverage = np.isfinite(depth).astype(np.float32)
    color = np.where(coverage[..., None] > 0, 0.05, 0.3).astype(np.float32) * np.ones(3, np.float32)
    color[3:7, 8:16] = 20.0  # a sun on the sky behind the occluder
    light_pass = np.zeros((HEIGHT, WIDTH), np.float32)
    light_pass[3:7, 8:16] = 1.0
    light_pass[:, occluder_cols[0] : occluder_cols[1]] = 0.0
    return gr.Buffers(
        color=jnp.asarray(color), depth=jnp.asarray(depth), coverage=jnp.asarray(coverage),
        light_pass=jnp.asarray(light_pass),
    )  # fmt: skip


LIGHT = jnp.asarray([12.3, 5.1], jnp.float32)


def at_fit_counts(effect):
    """The effect, a `VolumetricFog` with the loop counts of `fit`'s default model (`volumetric_haze`).

    Its presets then share one compiled program per test, as they share their structure: the counts are loop
    lengths, which the kernels' checklist and NumPy loops cover, and the suite's time on CI has no room for a
    preset's larger counts (benchmarks/README.md, "The test suite on CI").
    """
    if not isinstance(effect, gr.VolumetricFog):
        return effect
    model = gr.preset("volumetric_haze")
    return dataclasses.replace(effect, num_view_steps=model.num_view_steps, num_shadow_samples=model.num_shadow_samples)


def small(effect):
    """The preset with its loops shortened, so the tests compile quickly (a `VolumetricFog` `at_fit_counts`)."""
    replacements = {"max_samples": 8, "num_samples": 8.0, "max_iters": 5, "num_iters": 5.0}
    fields = {f.name: getattr(effect, f.name) for f in dataclasses.fields(effect)}
    return at_fit_counts(type(effect)(**{**fields, **{k: v for k, v in replacements.items() if k in fields}}))


SLOW_PRESETS = frozenset({"volumetric_haze", "physically_based"})
"""The presets whose tests compile their fog's lines at fit counts, about ten seconds or more each from an empty
cache."""


def slow_where(values, slow=SLOW_PRESETS) -> list:
    """`values` as `pytest.mark.parametrize` takes them, those in `slow` marked `slow` (run apart, README), under their
    own ids."""
    return [pytest.param(value, marks=pytest.mark.slow) if value in slow else value for value in values]
