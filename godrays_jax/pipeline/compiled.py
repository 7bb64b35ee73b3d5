"""`render_compiled`: an effect's frame compiled once and stored (`exported`), its fields checked beforehand."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from godrays_jax.effects.base import Effect
from godrays_jax.pipeline import exported
from godrays_jax.pipeline.problem import check_inside_bounds, strongly_typed
from godrays_jax.primitives.buffers import Buffers
from godrays_jax.primitives.checks import ranges_guaranteed
from godrays_jax.primitives.derivatives import values_only


def render_compiled(
    effect: Effect,
    buffers: Buffers,
    light_xy: Float[ArrayLike, "2"],
    light_in_front: bool,
    light_depth: Float[ArrayLike, ""] = math.inf,
) -> Float[Array, "H W C"]:
    """`effect(buffers, light_xy, ...)`, compiled (run op by op, each operation would compile on its own).

    Known fields are checked against their bounds here, so that the compiled
    render carries no run-time range check and can be stored (`exported`):
    `ValueError` naming a field outside them; that render takes no derivatives
    (`derivatives.values_only`). Traced arguments (a call inside `jit` or a
    derivative) are checked by the kernels when the program runs.
    """
    if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves((effect, buffers, light_xy, light_depth))):
        return _render(effect, buffers, light_xy, light_in_front, light_depth, True)  # traced: checked when run
    check_inside_bounds(effect)
    # Every field an argument of the program: a NumPy value or a weakly typed one would make another program.
    effect = jax.tree.map(strongly_typed, effect)
    # The sun as a Python number: its program drops the point light's branches (`bounded_medium.light_geometry`).
    at_infinity = float(np.asarray(light_depth)) == math.inf
    light_depth = math.inf if at_infinity else jnp.asarray(np.asarray(light_depth, buffers.color.dtype))
    # Checked here, so the program is the same whether or not the caller guarantees ranges, and at the default
    # matmul precision whatever the caller's (a fit sets both for its solver): one stored program for every caller.
    with ranges_guaranteed(), jax.default_matmul_precision(None):
        return exported.call("render", _render, effect, buffers, light_xy, light_in_front, light_depth, False)


@eqx.filter_jit
def _render(effect, buffers, light_xy, light_in_front, light_depth, checked):
    """`checked` is static: a render traced without range checks (nor derivatives) is never reused for one that
    needs them."""
    if checked:
        return effect(buffers, light_xy, light_in_front=light_in_front, light_depth=light_depth)
    with ranges_guaranteed(), values_only():
        return effect(buffers, light_xy, light_in_front=light_in_front, light_depth=light_depth)
