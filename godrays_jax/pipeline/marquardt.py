"""Levenberg-Marquardt on the host, around one compiled program: the residuals and their Jacobian at a point.

A fit's unknowns are a handful of scalars and its residuals millions of
pixels, so everything but the residuals and their Jacobian is small: the
damped normal equations are parameters x parameters. Here that small part
runs in NumPy (float64) and the one compiled program (`fit`'s
`residuals_and_jacobian`) is called once per step. So every phase of a fit
(the starts' race, the descent, the polish below, and `determination` after
it) runs the same compiled program, where a solver step compiled whole would
be compiled once per solver and phase, each copy holding the effect's
Jacobian.

The algorithm is optimistix's `LevenbergMarquardt`, step for step: the
classical trust region (a step is accepted when the loss falls by at least
0.01 of the fall its linear model predicts; the region grows 3.5 times when
the fall is within 0.99 of it and shrinks 4 times on a rejection), damping
`lambda = 1 / step size`, its first step the start's own evaluation, and the
Cauchy termination on `rtol` and `atol` in the max norm.

`held` unknowns take no step (`fit` holds the fields an effect fits in its
polish alone, `Effect.POLISH_FIELDS`, while its starts race and descend).

`scaled=True` damps each unknown by its own sensitivity, Marquardt's scaling:
`(J^T J + lambda D) step = -J^T r` with `D = diag(J^T J)` instead of the
identity, which makes the steps independent of how each unknown is scaled.
The fit's unknowns share one unit scale over their fitting ranges
(`problem.from_unit`), but not one sensitivity (a unit of `max_distance`
spans 10^4 scene units, a unit of `anisotropy` the whole phase function);
with one damping for all, the trust region's steps favour the unknowns the
frame is most sensitive to and crawl along the others.
"""

import dataclasses
from collections.abc import Callable

import numpy as np

# The classical trust region's constants (optimistix.ClassicalTrustRegion, after Gould et al.).
_LOW_CUTOFF, _HIGH_CUTOFF = 0.01, 0.99
_SHRINK, _GROW = 0.25, 3.5

# An unknown that does not move the frame (a field on a bound it cannot leave, a layer top above every ray) has a
# zero column in J: with Marquardt's scaling it is damped as a column this much smaller than the largest, so the
# damped system stays positive definite and such an unknown takes no step (its gradient is zero as well).
_SMALLEST_DAMPING_SHARE = 1e-6

Linearise = Callable[[], tuple[np.ndarray, np.ndarray]]
"""`linearise()`: the normal equations `J^T J` `(n, n)` and `J^T r` `(n,)` of the residuals' Jacobian `J` at the
point evaluated (`normal_equations`)."""

Evaluate = Callable[[np.ndarray], tuple[np.ndarray, Linearise]]
"""`evaluate(y)`: at the unknowns `y` `(n,)`, the residuals `(N,)` and how to linearise them there. A step calls
`linearise` only when it accepts the point: where the residuals cost less than their Jacobian (a fit's polish,
`fit_programs.host_evaluator`), a rejected step costs only its residuals."""


def normal_equations(jacobian: np.ndarray, residuals: np.ndarray, rows: int = 1 << 19) -> tuple[np.ndarray, np.ndarray]:
    """`(J^T J, J^T r)` in float64, `rows` rows at a time (a float64 copy of a large frame's Jacobian is not kept)."""
    count = jacobian.shape[1]
    normal, gradient = np.zeros((count, count)), np.zeros(count)
    for start in range(0, jacobian.shape[0], rows):
        block = np.asarray(jacobian[start : start + rows], np.float64)
        normal += block.T @ block
        gradient += block.T @ np.asarray(residuals[start : start + rows], np.float64)
    return normal, gradient


@dataclasses.dataclass
class MarquardtState:
    """Where a descent stands: its last accepted unknowns and residuals, the normal equations there (`J^T J`,
    `J^T r`), and the point it evaluates next."""

    y: np.ndarray
    residuals: np.ndarray | None
    normal: np.ndarray | None
    gradient: np.ndarray | None
    proposal: np.ndarray
    step_size: float = 1.0
    first_step: bool = True
    done: bool = False
    evaluated: tuple | None = None  # the proposal's `Evaluate`, when made already
    rejected: bool = False  # whether the last step rejected its point

    @property
    def loss(self) -> float:
        """The sum of squared residuals at the last accepted point (the fit's loss)."""
        return float(np.sum(np.square(self.residuals, dtype=np.float64)))

    @property
    def predicted_half_change(self) -> float:
        """The change of half the loss that the linear model at the last accepted point predicts for the proposal:
        `0.5 (|J d + r|^2 - |r|^2)`, `d` the proposal's step."""
        difference = self.proposal - self.y
        return difference @ self.gradient + 0.5 * difference @ self.normal @ difference

    @property
    def predicted_fall(self) -> float:
        """The fall of the loss that the linear model predicts for the proposal, as a fraction of the loss at the
        last accepted point (0 before the first step)."""
        if self.normal is None:
            return 0.0
        return float(-2.0 * self.predicted_half_change / max(self.loss, np.finfo(np.float64).tiny))


@dataclasses.dataclass(frozen=True)
class LevenbergMarquardt:
    """Levenberg-Marquardt (the module's docstring); `scaled`: Marquardt's scaling of the damping."""

    rtol: float
    atol: float
    scaled: bool = False
    held: tuple[int, ...] = ()
    """Unknowns (indices) its steps leave where they start: the others descend as in the problem with those fixed
    (the damped normal equations of the others' columns alone)."""

    def init(self, y: np.ndarray, evaluation: tuple | None = None) -> MarquardtState:
        """The state at the start `y`; `evaluation`, the start's `Evaluate` if made already (the first step then
        uses it instead of evaluating again)."""
        y = np.asarray(y, np.float64)
        return MarquardtState(y=y, residuals=None, normal=None, gradient=None, proposal=y, evaluated=evaluation)

    def step(self, state: MarquardtState, evaluate: Evaluate) -> MarquardtState:
        """One step: evaluate the proposal, accept or reject it, test for convergence, propose the next point."""
        residuals, linearise = state.evaluated if state.evaluated is not None else evaluate(state.proposal)
        loss = float(np.sum(np.square(residuals, dtype=np.float64)))
        if state.first_step:
            accept, good = True, False
        else:
            predicted = state.predicted_half_change
            fall = 0.5 * (loss - state.loss)
            accept = bool(fall <= _LOW_CUTOFF * predicted)
            good = bool(fall < _HIGH_CUTOFF * predicted and predicted < 0)
        step_size = state.step_size * ((_GROW if good else 1.0) if accept else _SHRINK)
        if accept:
            previous = np.zeros_like(residuals) if state.residuals is None else state.residuals
            done = _converged(self.rtol, self.atol, state.proposal, state.proposal - state.y, residuals, previous)
            normal, gradient = linearise()
            state = dataclasses.replace(state, y=state.proposal, residuals=residuals, normal=normal, gradient=gradient)
        else:
            done = False
        proposal = state.y + self._damped_step(state.normal, state.gradient, step_size)
        return dataclasses.replace(
            state, proposal=proposal, step_size=step_size, first_step=False, evaluated=None, rejected=not accept,
            done=done or not np.all(np.isfinite(proposal)),
        )  # fmt: skip

    def _damped_step(self, normal: np.ndarray, gradient: np.ndarray, step_size: float) -> np.ndarray:
        """`-(J^T J + lambda D)^-1 J^T r`, `lambda = 1 / step_size`, `D` the identity or Marquardt's `diag(J^T J)`."""
        damping = 1.0 / step_size if step_size > np.finfo(np.float64).eps else np.finfo(np.float64).max
        if self.scaled:
            columns = np.diag(normal)
            scale = np.maximum(columns, _SMALLEST_DAMPING_SHARE * np.max(columns) + np.finfo(np.float64).tiny)
        else:
            scale = np.ones(normal.shape[0])
        free = np.setdiff1d(np.arange(len(gradient)), np.asarray(self.held, int))
        step = np.zeros_like(gradient)
        try:
            step[free] = -np.linalg.solve((normal + damping * np.diag(scale))[np.ix_(free, free)], gradient[free])
        except np.linalg.LinAlgError:
            pass
        return step


def _converged(rtol, atol, y, y_difference, residuals, previous) -> bool:
    """optimistix's Cauchy termination in the max norm: both the step and the residuals' change small."""
    y_small = np.max(np.abs(y_difference) / (atol + rtol * np.abs(y)), initial=0.0) < 1
    f_scale = atol + rtol * np.abs(residuals)
    f_small = np.max(np.abs(np.asarray(residuals, np.float64) - previous) / f_scale, initial=0.0) < 1
    return bool(y_small and f_small)
