"""Every preset's effect through what a training loop does with it: jit, vmap, grad of vmap, vmap of grad.

The effects' counterpart of `test_kernel_checklist.py`: a batch of frames (stacked `Buffers`, every optional pass
rendered) under a light per frame. The gradient of a batched loss in the effect's fittable values is the sum of the
per-frame gradients, and in each frame's colour that frame's own gradient, under `jit`; `vmap` of the
per-frame gradient equals a loop. New presets join the table by themselves.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from closeness import assert_trees_close
from frames import SLOW_PRESETS, at_fit_counts, slow_where

import godrays_jax as gr

HEIGHT, WIDTH = 24, 36
BATCH = 2


def _frame(seed: int) -> gr.Buffers:
    """A frame with open sky above a ragged horizon, an occluder near the light and every optional pass."""
    rng = np.random.default_rng(seed)
    rows = np.arange(HEIGHT)[:, None] + 0.5
    horizon = HEIGHT * (0.55 + 0.1 * np.sin(np.arange(WIDTH) / 3.0 + seed))[None, :]
    covered = (rows > horizon) | ((np.abs(np.arange(WIDTH) - 15 - 3 * seed) < 3)[None, :] & (rows > 8))
    depth = np.where(covered, rng.uniform(5.0, 40.0, (HEIGHT, WIDTH)), np.inf).astype(np.float32)
    coverage = covered.astype(np.float32)
    color = rng.uniform(0.0, 1.5, (HEIGHT, WIDTH, 3)).astype(np.float32)
    glow = np.concatenate([color * 0.3, coverage[..., None] * 0.5], axis=-1)
    return gr.Buffers(
        color=jnp.asarray(color),
        depth=jnp.asarray(depth),
        coverage=jnp.asarray(coverage),
        light_pass=jnp.asarray(1.0 - coverage),
        glow_pass=jnp.asarray(glow),
        glow_target=jnp.asarray(color * (1.0 - coverage[..., None])),
    )


FRAMES = [_frame(seed) for seed in range(BATCH)]
LIGHTS = jnp.asarray([[13.3, 7.6], [24.8, 5.2]], jnp.float32)
STACKED = jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *FRAMES)
COTANGENTS = jnp.asarray(np.random.default_rng(7).normal(size=(BATCH, HEIGHT, WIDTH, 3)), jnp.float32)


def _split(name):
    return eqx.partition(at_fit_counts(gr.preset(name)), eqx.is_inexact_array)


def _frame_loss(values, static, frame, color, light, cotangent):
    effect = eqx.combine(values, static)
    frame = eqx.tree_at(lambda f: f.color, frame, color)
    return jnp.sum(cotangent * effect(frame, light, light_depth=math.inf)[..., :3])


def _assert_close(actual, expected, rtol=1e-3):
    """Within float32 accumulation: an effect's gradient sums over whole frames and pyramids, in another order."""
    assert_trees_close(actual, expected, rtol=rtol)


@pytest.mark.parametrize("name", slow_where(sorted(gr.PRESETS), {*SLOW_PRESETS, "vbex_bloom", "vbex_sun_spot"}))
def test_jit_and_vmap_equal_eager_frames(name):
    effect = at_fit_counts(gr.preset(name))
    compiled = eqx.filter_jit(effect)
    looped = jnp.stack([compiled(frame, light) for frame, light in zip(FRAMES, LIGHTS)])
    _assert_close(effect(FRAMES[1], LIGHTS[1]), looped[1])  # one frame eager: op by op is the slow path
    _assert_close(eqx.filter_vmap(effect)(STACKED, LIGHTS), looped)


@pytest.mark.parametrize("name", slow_where(sorted(gr.PRESETS), {*SLOW_PRESETS, "vbex_sun_spot"}))
def test_grad_of_vmap_and_vmap_of_grad_equal_per_frame_gradients(name):
    """Under `jit`, as a training step runs them (the kernels' checklist also takes the eager path): the gradient of
    a batched loss, and the per-frame gradient mapped over the batch. One test for both, so that the per-frame
    gradient is traced and compiled once."""
    values, static = _split(name)
    gradient = jax.grad(_frame_loss, argnums=(0, 3))

    def batch_loss(values, colors):
        per_frame = jax.vmap(_frame_loss, in_axes=(None, None, 0, 0, 0, 0))
        return jnp.sum(per_frame(values, static, STACKED, colors, LIGHTS, COTANGENTS))

    value_gradient, color_gradients = jax.jit(jax.grad(batch_loss, argnums=(0, 1)))(values, STACKED.color)
    mapped = jax.jit(jax.vmap(gradient, in_axes=(None, None, 0, 0, 0, 0)), static_argnums=1)
    value_gradients, mapped_color_gradients = mapped(values, static, STACKED, STACKED.color, LIGHTS, COTANGENTS)
    per_frame = jax.jit(gradient, static_argnums=1)
    expected = [per_frame(values, static, frame, frame.color, light, cotangent)
                for frame, light, cotangent in zip(FRAMES, LIGHTS, COTANGENTS)]  # fmt: skip
    # A sum over frames of gradients of either sign: float32 cancellation allows a looser match.
    _assert_close(value_gradient, jax.tree_util.tree_map(lambda *g: sum(g), *[e[0] for e in expected]), rtol=3e-3)
    for i, (expected_values, expected_color) in enumerate(expected):
        _assert_close(color_gradients[i], expected_color)
        _assert_close(jax.tree_util.tree_map(lambda g: g[i], value_gradients), expected_values)
        _assert_close(mapped_color_gradients[i], expected_color)
