"""`render_compiled`: an effect's frame compiled once and stored (`exported`), its fields checked beforehand."""

import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from godrays_jax.effects.base import Effect
from godrays_jax.effects.lights import Light
from godrays_jax.pipeline import exported
from godrays_jax.pipeline.problem import check_inside_bounds, drawn, strongly_typed
from godrays_jax.primitives.buffers import Buffers
from godrays_jax.primitives.checks import ranges_guaranteed
from godrays_jax.primitives.derivatives import values_only


def render_compiled(
    effect: Effect,
    buffers: Buffers,
    light_xy: Float[ArrayLike, "2"],
    light_in_front: bool,
    light_depth: Float[ArrayLike, ""] = math.inf,
    *,
    other_lights: Sequence[Light] = (),
) -> Float[Array, "H W C"]:
    """`effect(buffers, light_xy, ...)`, compiled (run op by op, each operation would compile on its own); with
    `other_lights`, the frame under that light and them, their light added (`effects.lights.lit_by`).

    Known fields are checked against their bounds here, so that the compiled
    render carries no run-time range check and can be stored (`exported`):
    `ValueError` naming a field outside them; that render takes no derivatives
    (`derivatives.values_only`). Traced arguments (a call inside `jit` or a
    derivative) are checked by the kernels when the program runs.
    """
    other_lights = tuple(other_lights)
    traced = jax.tree.leaves((effect, buffers, light_xy, light_depth, other_lights))
    if any(isinstance(leaf, jax.core.Tracer) for leaf in traced):  # traced: checked when run
        return _render(effect, buffers, light_xy, light_in_front, light_depth, other_lights, True)
    check_inside_bounds(effect)
    # Every field an argument of the program: a NumPy value or a weakly typed one would make another program.
    effect = jax.tree.map(strongly_typed, effect)
    # The sun as a Python number: its program drops the point light's branches (`bounded_medium.light_geometry`).
    at_infinity = float(np.asarray(light_depth)) == math.inf
    light_depth = math.inf if at_infinity else jnp.asarray(np.asarray(light_depth, buffers.color.dtype))
    # Checked here, so the program is the same whether or not the caller guarantees ranges, and at the default
    # matmul precision whatever the caller's (a fit sets both for its solver): one stored program for every caller.
    with ranges_guaranteed(), jax.default_matmul_precision(None):
        return exported.call(
            "render", _render, effect, buffers, light_xy, light_in_front, light_depth, other_lights, False
        )  # fmt: skip


@eqx.filter_jit
def _render(effect, buffers, light_xy, light_in_front, light_depth, other_lights, checked):
    """`checked` is static: a render traced without range checks (nor derivatives) is never reused for one that
    needs them."""
    if checked:
        return drawn(effect, buffers, light_xy, light_in_front, light_depth, other_lights)
    with ranges_guaranteed(), values_only():
        return drawn(effect, buffers, light_xy, light_in_front, light_depth, other_lights)
