"""How a fit runs: its solver (`SOLVERS`), whether a polish follows (`polishes`), the settings of its phases
(`Phases`), from `fit`'s keyword arguments, checked, when a phase stops (`plateaued`, `stalled`), how its steps are
counted (`StepCounter`) and how the race advances its starts (`advance_two_at_a_time`)."""

import collections
import dataclasses
import threading
from collections.abc import Callable, Sequence

import optimistix as optx

from godrays_jax.kernels.losses import LOSSES, check_space
from godrays_jax.pipeline import exported
from godrays_jax.pipeline.marquardt import LevenbergMarquardt, MarquardtState

SOLVERS: tuple[str, ...] = ("auto", "levenberg_marquardt", "gauss_newton", "bfgs")


def _solver(solver, loss, rtol, atol):
    """The optimiser `solver` names (or is), checked against `loss`."""
    if not isinstance(solver, str):
        if not isinstance(solver, (optx.AbstractLeastSquaresSolver, optx.AbstractMinimiser)):
            raise ValueError("solver must be a name or an optimistix least-squares solver or minimiser")
        if isinstance(solver, optx.AbstractLeastSquaresSolver) and loss != "mse":
            raise ValueError(f"a least-squares solver fits loss='mse' only, got loss={loss!r}: use a minimiser")
        return solver
    if solver not in SOLVERS:
        raise ValueError(f"solver must be one of {', '.join(SOLVERS)}; got {solver!r}")
    if solver == "auto":
        solver = "levenberg_marquardt" if loss == "mse" else "bfgs"
    if solver in ("levenberg_marquardt", "gauss_newton") and loss != "mse":
        raise ValueError(f"solver={solver!r} fits least squares (loss='mse') only; use solver='bfgs' for loss={loss!r}")
    if solver == "levenberg_marquardt":  # on the host (`marquardt`): no phase compiles a solver step of its own
        return LevenbergMarquardt(rtol=rtol, atol=atol)
    if solver == "gauss_newton":
        return optx.GaussNewton(rtol=rtol, atol=atol)
    return optx.BFGS(rtol=rtol, atol=atol)


def polishes(solver, loss: str) -> bool:
    """Whether `fit(solver=solver, loss=loss)` follows its descent with the polish phase (Marquardt's scaling):
    after the Levenberg-Marquardt that `solver` names ("auto" for MSE); a solver the caller built runs as it is."""
    return isinstance(solver, str) and loss == "mse" and solver in ("auto", "levenberg_marquardt")


@dataclasses.dataclass(frozen=True)
class Phases:
    """How a fit runs, from `fit`'s keyword arguments (checked): its solver and the polish's, and the settings of
    its descents (`fit._descend`'s keywords), at full and at the coarse resolution."""

    optimiser: object
    polisher: LevenbergMarquardt | None
    descend: dict
    coarse_factor: int
    coarse_plateau_rtol: float
    coarse_jacobian: bool
    coarse_plateau_steps: int

    @classmethod
    def of(cls, *, loss, space, solver, max_steps, rtol, atol, probe_steps, coarse_factor, plateau_steps,
           plateau_rtol, coarse_plateau_rtol, coarse_jacobian, coarse_plateau_steps, tint_high=None) -> "Phases":  # fmt: skip
        """`tint_high`: the fitted tints' upper bound (`problem.tint_range`), None where no tint is fitted."""
        if loss not in LOSSES:
            raise ValueError(f"loss must be one of {', '.join(LOSSES)}; got {loss!r}")
        for name, value, least in (("max_steps", max_steps, 0), ("probe_steps", probe_steps, 1),
                                   ("coarse_factor", coarse_factor, 1), ("plateau_steps", plateau_steps, 0),
                                   ("coarse_plateau_steps", coarse_plateau_steps, 0)):  # fmt: skip
            if not (isinstance(value, int) and value >= least):
                raise ValueError(f"{name} must be an int >= {least}, got {value!r}")
        if not (plateau_rtol >= 0 and coarse_plateau_rtol >= 0):
            raise ValueError(f"plateau_rtol and coarse_plateau_rtol must be >= 0, got {plateau_rtol!r}, {coarse_plateau_rtol!r}")
        check_space(space)
        optimiser = _solver(solver, loss, rtol, atol)
        descend = dict(
            optimiser=optimiser, least_squares=isinstance(optimiser, (LevenbergMarquardt, optx.AbstractLeastSquaresSolver)),
            loss=loss, space=space, max_steps=max_steps, probe_steps=probe_steps, plateau_steps=plateau_steps,
            plateau_rtol=plateau_rtol, tint_high=tint_high,
        )  # fmt: skip
        polisher = LevenbergMarquardt(rtol=rtol, atol=atol, scaled=True) if polishes(solver, loss) else None
        return cls(
            optimiser, polisher, descend, coarse_factor, coarse_plateau_rtol, bool(coarse_jacobian), coarse_plateau_steps
        )


def stalled(state: MarquardtState, solver_losses: Sequence[float], plateau_steps: int, plateau_rtol: float) -> bool:
    """Whether Levenberg-Marquardt has stopped before the plateau's window shows it: its last step was rejected,
    and its linear model promises the next one less than `plateau_rtol / plateau_steps` of the loss, a step's share
    of the fall the window asks for. A rejection shrinks the trust region fourfold, so the steps after it promise
    less still: a phase's last steps were mostly such rejections, each a render or a Jacobian (docs/findings.md, "A
    phase that stalls"). As `plateaued`, only once the loss has first fallen."""
    if not state.rejected or not any(value < solver_losses[0] for value in solver_losses):
        return False
    return state.predicted_fall < plateau_rtol / plateau_steps


def plateaued(solver_losses: Sequence[float], plateau_steps: int, plateau_rtol: float) -> bool:
    """Whether the loss has stopped moving: it fell by less than `plateau_rtol` of itself over the last
    `plateau_steps` steps, all taken since it first fell.

    `solver_losses[i]` is the loss at the solver's last accepted point after step `i + 1`; the first is the
    start's, as the solver computes it (the loss evaluated before the fit may differ in its last bits). Steps
    before the first fall do not count: Levenberg-Marquardt may reject its first steps and BFGS backtrack
    its first, the loss unchanged, while the solver is still looking for a way down.
    """
    first_fall = next((i for i, value in enumerate(solver_losses) if value < solver_losses[0]), None)
    earlier = len(solver_losses) - 1 - plateau_steps
    if first_fall is None or earlier < first_fall - 1:
        return False
    return solver_losses[earlier] - solver_losses[-1] <= plateau_rtol * solver_losses[earlier]


class StepCounter:
    """Counts solver steps over every start and phase and reports each to `progress` (or None), one at a time: the
    race's starts step on two threads (`advance_two_at_a_time`)."""

    def __init__(self, progress):
        self.progress, self.steps = progress, 0
        self._lock = threading.Lock()

    def __call__(self, value):
        with self._lock:
            self.steps += 1
            if self.progress is not None:
                self.progress(self.steps, value)


def advance_two_at_a_time(runs: Sequence, until: int, advance: Callable) -> None:
    """Each of `runs` advanced to `until` steps (`advance(run, until, stop)`), two at a time: this thread and a
    helper take the runs in turn, each running one to its end before taking the next.

    The runs share their compiled programs and nothing else, so each ends as it would alone. Two at once keep both
    cores of a small machine busy where one run's steps leave part of them idle (XLA on the CPU runs a loop's body
    on one core, and each step's linear algebra is on the host; benchmarks/README.md, "The fit as users run it").
    The helper runs in this thread's JAX settings (`exported.carried`). An error on either thread stops the other
    after its step and is raised here, this thread's first."""
    waiting = collections.deque(runs)
    stop = threading.Event()
    failures = []

    def work():
        while not stop.is_set():
            try:
                run = waiting.popleft()
            except IndexError:
                return
            advance(run, until, stop)

    def helper():
        try:
            work()
        except BaseException as error:  # raised on the caller's thread once it has stopped too
            failures.append(error)
            stop.set()

    thread = threading.Thread(target=exported.carried(helper), name="godrays-jax-race", daemon=True)
    thread.start()
    try:
        work()
        thread.join()
    except BaseException:  # an interrupt too: the helper stops after its step
        stop.set()
        thread.join()
        raise
    if failures:
        raise failures[0]
