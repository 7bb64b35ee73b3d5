"""Levenberg-Marquardt with Marquardt's scaling: each unknown damped in proportion to how much it moves the frame.

optimistix's `LevenbergMarquardt` damps every unknown alike, solving
`(J^T J + lambda I) step = -J^T r`. The fit's unknowns share one unit scale
over their fitting ranges (`problem.from_unit`), but not one sensitivity: a
unit of `max_distance` spans 10^4 scene units, a unit of `anisotropy` the
whole phase function. With one damping for all, the trust region's steps
favour the unknowns the frame is most sensitive to and crawl along the
others, and a fit stops on a slow slope where its loss falls by less than the
plateau stop's share per step (`benchmarks/README.md`, "Marquardt's scaling").
Marquardt damps each unknown by the diagonal of `J^T J` instead,
`(J^T J + lambda D) step = -J^T r` with `D = diag(J^T J)`, which makes the
steps independent of how each unknown is scaled.
"""

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from jaxtyping import Array, Float

# An unknown that does not move the frame (a field on a bound it cannot leave, a layer top above every ray) has a
# zero column in J: it is damped as a column this much smaller than the largest, so the damped system stays
# positive definite and such an unknown takes no step (its gradient is zero as well).
_SMALLEST_DAMPING_SHARE = 1e-6


class _ScaledDamping(eqx.Module):
    """The stacked operator `[J; sqrt(lambda D)]`, whose least-squares solution is the damped step."""

    jacobian: lx.AbstractLinearOperator
    damping: Float[Array, ""]
    scale: Float[Array, " n"]  # sqrt(D)

    def __call__(self, step):
        return self.jacobian.mv(step), jnp.sqrt(self.damping) * self.scale * step


class ScaledDampedNewtonDescent(optx.DampedNewtonDescent):
    """`optx.DampedNewtonDescent` for least squares over a flat vector of unknowns, damped by `lambda diag(J^T J)`.

    The trust region's step size is `1 / lambda`, as in optimistix.
    """

    def step(self, step_size, state):
        f_info = state.f_info
        if not isinstance(f_info, optx.FunctionInfo.ResidualJac):
            raise ValueError("ScaledDampedNewtonDescent needs a least-squares problem's residuals and Jacobian")
        dtype = step_size.dtype
        positive = step_size > jnp.finfo(dtype).eps
        damping = jnp.where(positive, 1.0 / jnp.where(positive, step_size, 1.0), jnp.finfo(dtype).max)
        column_squares = jnp.sum(f_info.jac.as_matrix() ** 2, axis=0)
        floor = _SMALLEST_DAMPING_SHARE * jnp.max(column_squares) + jnp.finfo(column_squares.dtype).tiny
        scale = jnp.sqrt(jnp.maximum(column_squares, floor))
        structure = f_info.jac.in_structure()
        operator = lx.FunctionLinearOperator(_ScaledDamping(f_info.jac, damping, scale), structure)
        zeros = jax.tree.map(lambda leaf: jnp.zeros(leaf.shape, leaf.dtype), structure)
        solution = lx.linear_solve(operator, (f_info.residual, zeros), self.linear_solver, throw=False)
        return -solution.value, optx.RESULTS.promote(solution.result)


def _quiet(**_) -> None:
    """The solver's progress report: nothing (`fit` reports its own)."""


class ScaledLevenbergMarquardt(optx.AbstractGaussNewton):
    """Levenberg-Marquardt whose damping is Marquardt's `lambda diag(J^T J)` (see the module's docstring).

    Otherwise optimistix's `LevenbergMarquardt`: the classical trust region, the
    same termination on `rtol` and `atol`. The damped steps are solved by the
    normal equations (`lx.Normal(lx.Cholesky())`: the matrix is parameters x
    parameters and positive definite for any damping > 0).
    """

    rtol: float
    atol: float
    norm: Callable
    descent: ScaledDampedNewtonDescent
    search: optx.ClassicalTrustRegion
    verbose: Callable

    def __init__(self, rtol: float, atol: float):
        self.rtol = rtol
        self.atol = atol
        self.norm = optx.max_norm
        self.descent = ScaledDampedNewtonDescent(linear_solver=lx.Normal(lx.Cholesky()))
        self.search = optx.ClassicalTrustRegion()
        self.verbose = _quiet
