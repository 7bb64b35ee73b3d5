"""Fit an effect's parameters to reference frames with gradients (optimistix).

`fit(effect, buffers, light_xy, target)` finds the parameters that make the
cheap screen-space effect look like the target: a render with real
participating media, a photograph, another engine's frame. Several frames (a
sequence, several views of one scene) share one parameter set.

How the parameters are fitted:

- Every fittable field (`effects.parameter_bounds`) not named in `fixed` is
  fitted; static fields never are. Integer counts (`num_samples`, `num_iters`,
  `num_passes`) are fitted through the kernels' continuous relaxations and capped
  by their static loop lengths (`max_samples`, ...); the result also carries
  the effect with the counts rounded, re-evaluated.
- Ranges are kept by reparameterisation: a field with bounds `[low, high]` is
  `low + (high - low) * fold(z)` (`problem.from_unit`), `fold` of period 2:
  the identity on [0, 1] (stretched by 1 / (1 - `FOLD_ROUNDING`)), mirrored
  beyond, its corners rounded by parabolas. Unlike a sigmoid its slope
  vanishes only on the bounds themselves, and a start on a bound (presets put
  `decay` at 1.0) begins `START_INSET` inside it, so it still moves; unlike
  the triangle wave it has no corner where a field whose best value is its
  bound would jump from side to side every step; and the solver's unknowns
  all have the same unit scale. The race also runs each start with a field
  whose values span decades (`FieldInfo.decades`) moved by ratios.
- Levenberg-Marquardt's damping is the same for every unknown, but the frame
  is not equally sensitive to each (a unit of `max_distance` is 10^4 scene
  units), and where its descent stops the loss may still fall slowly along
  the unknowns it damps most. It is then polished: the same least squares
  goes on from there with each unknown damped by its own sensitivity
  (`marquardt`, Marquardt's scaling), after a coarse phase too (its result,
  from a frame that may lose thin surfaces, only starts the full resolution's
  descent). Not the race's own descent: with that
  scaling from the start, the race keeps worse starts on some frames
  (`docs/findings.md`, "Marquardt's scaling only as a polish"); as a polish it can only
  lower the loss.
- Derivatives are forward-mode: the Jacobian of the residuals (millions of
  them, a handful of parameters, which reverse mode would build one residual
  at a time) is one vectorised JVP per stage of the effect
  (`Effect.FIELD_STAGES`: fields that enter late are not carried through the
  march), memory O(image x parameters) whatever the loop lengths. The
  kernels' sample loops have custom JVPs that differentiate the parameters
  inside the loop that sums the copies, so the Jacobian costs about a
  reverse-mode gradient and stores no iteration (`benchmarks/bench_fit.py`).
- Levenberg-Marquardt (the default for MSE) runs on the host (`marquardt`) around compiled programs of the
  residuals and their Jacobian (`residuals_and_jacobian`), shared by the race, the descents, the polish and
  `determination`, kept by the persistent cache (`app.compile_cache`); with `coarse_jacobian` the full resolution
  linearises at the coarse one, its sharp fields by differences of its renders (`fit_programs.rendered_differences`).
- The race's starts step two at a time, on the caller's thread and a helper
  (`fit_phases.advance_two_at_a_time`), each as it would alone: they share compiled programs and nothing else.
- A fit never ends above its start: where the reduced frames and the stand-in lead it to a higher loss than the
  effect given (a start already at the frames' minimum), it returns the effect given (`FitResult.kept_start`).
"""

import dataclasses
import itertools
import math
from collections.abc import Callable, Sequence
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import ArrayLike, Bool, Float

from godrays_jax.effects.base import Effect
from godrays_jax.effects.fields import field_value, replace_fields, round_counts
from godrays_jax.effects.lights import Light
from godrays_jax.kernels.losses import Space
from godrays_jax.pipeline import exported
from godrays_jax.pipeline.fit_programs import (
    CoarseLinearisation,
    effect_loss,
    evaluate_loss,
    host_evaluator,
    objective_function,
    residual_function,
    solver_init,
    solver_step,
)
from godrays_jax.pipeline.fit_phases import Phases, StepCounter, advance_two_at_a_time, plateaued, stalled
from godrays_jax.pipeline.marquardt import LevenbergMarquardt, MarquardtState
from godrays_jax.pipeline.problem import (
    FitProblem,
    as_frames,
    check_inside_bounds,
    fitted_bounds,
    folded_positions,
    light_tints,
    start_point,
    strongly_typed,
    tint_range,
    warped_start,
    with_frames_read_once,
    with_light_tints,
)
from godrays_jax.pipeline.reduced import clip_to_bounds, downsample_frames, scale_pixel_fields
from godrays_jax.primitives.buffers import Buffers
from godrays_jax.primitives.checks import ranges_guaranteed

@dataclasses.dataclass(frozen=True)
class FitResult:
    """What `fit` returns.

    Attributes:
        effect: the fitted effect, same type and static fields as the start;
            counts may be fractional (the relaxation).
        rounded: `effect` with every fitted count rounded to the nearest integer.
        loss_history: the loss at the solver's last accepted parameters after
            each step; `loss_history[0]` is the starting loss. From another of
            `starts` or after a coarse phase, `loss_history[1]` is the loss the
            winning start's full-resolution descent starts from (every entry at
            the frames' own resolution) and the rest follow that descent.
        loss_before: the loss of the effect given as the start.
        loss_after: the loss of `effect`.
        loss_rounded: the loss of `rounded`.
        fitted: the names of the fields that were fitted.
        steps: solver steps taken at the frames' own resolution, every start's.
        converged: whether the solver met its tolerances within `max_steps`
            (in the last phase: the polish, where there is one).
        plateaued: whether the fit stopped because the loss had stopped moving
            (`plateau_steps`, `plateau_rtol`; in the last phase).
        coarse_steps: solver steps taken at the reduced resolution first (`coarse_factor`), every start's.
        start: which start the fit began from: 0 the effect given, `i` `starts[i - 1]`.
        kept_start: whether the fit ended above the loss of the effect given, which it then returns (`effect`,
            `rounded`, their losses, images and light tints are the start's; `loss_history` is the fit's path, then
            the start's loss).
        polish_steps: of `steps`, those of the polish phase (Marquardt's scaling, after Levenberg-Marquardt).
        images_before, images_after, images_rounded: each frame as the effect given, `effect` and `rounded`
            render it (`(H, W, C)` linear, as `apply` renders it), from which the losses were taken.
        light_tints: the fitted tints of the lights beside each frame's first, `(K, 3)` (`fit_light_tints`), the
            images' and losses' after the fit; None where none were fitted.
    """

    effect: Effect
    rounded: Effect
    loss_history: np.ndarray
    loss_before: float
    loss_after: float
    loss_rounded: float
    fitted: tuple[str, ...]
    steps: int
    converged: bool
    plateaued: bool = False
    coarse_steps: int = 0
    start: int = 0
    kept_start: bool = False
    polish_steps: int = 0
    light_tints: np.ndarray | None = None
    images_before: list = dataclasses.field(default_factory=list, repr=False)
    images_after: list = dataclasses.field(default_factory=list, repr=False)
    images_rounded: list = dataclasses.field(default_factory=list, repr=False)


def _start_like(effect: Effect, other: Effect, bounds: dict[str, tuple[float, float]]) -> Effect:
    """`effect` with the fitted fields (`bounds`) taken from `other`, a start of the same type, clipped to them."""
    if type(other) is not type(effect):
        raise ValueError(f"starts must be {type(effect).__name__}s like the effect, got a {type(other).__name__}")
    start = replace_fields(effect, {name: jnp.asarray(field_value(other, name)) for name in bounds})
    return jax.tree.map(strongly_typed, clip_to_bounds(start, bounds))


def _same_values(effect: Effect, other: Effect, names: Sequence[str]) -> bool:
    """Whether two effects hold equal values in the fields `names`."""
    return all(np.array_equal(np.asarray(field_value(effect, n)), np.asarray(field_value(other, n))) for n in names)


@eqx.filter_jit
def _fitted_effects(problem, positions):
    """The fitted effect at `positions` in its fields' ranges and its counts rounded, compiled (op by op each scalar
    operation compiles on its own)."""
    effect = problem.effect_at_positions(positions)
    return effect, round_counts(effect)


@dataclasses.dataclass
class _Run:
    """One start's descent: its problem and solver state, its losses so far, whether it stopped.

    `state` is a `marquardt.MarquardtState` for the host's Levenberg-Marquardt, else optimistix's state as
    `(y, leaves, done, succeeded)`.
    """

    problem: FitProblem
    state: object
    history: list[float]  # the start's loss, then the loss at the last accepted point after each step but the first
    solver_losses: list[float] = dataclasses.field(default_factory=list)
    steps: int = 0
    plateaued: bool = False
    warps: np.ndarray | None = None  # the host's map by ratios (`problem.folded_positions`), or None
    evaluate: Callable | None = None  # the host's `marquardt.Evaluate` of its unknowns

    @property
    def on_host(self) -> bool:
        return isinstance(self.state, MarquardtState)

    @property
    def done(self) -> bool:
        return self.state.done if self.on_host else bool(self.state[2])

    @property
    def converged(self) -> bool:
        return self.state.done and np.all(np.isfinite(self.state.y)) if self.on_host else self.done and bool(self.state[3])

    @property
    def stopped(self) -> bool:
        return self.done or self.plateaued

    def positions(self) -> np.ndarray:
        """The fitted fields' positions in their ranges at the last accepted point."""
        return folded_positions(np.asarray(self.state.y if self.on_host else self.state[0]), self.warps)[0]

    def positions_as(self, dtype) -> jax.Array:
        """`positions` as a JAX array of `dtype`, cast on the host and put on the device as it is (`jnp.asarray`
        compiles a program per size)."""
        return jax.device_put(np.asarray(self.positions(), dtype))


def _descend(
    candidates, bounds, frame_data, counter, *, optimiser, least_squares, loss, space, max_steps, probe_steps,
    plateau_steps, plateau_rtol, tint_high=None, hold=(), own=None, coarse=None, by_ratios=False,
) -> tuple[list[_Run], int]:
    """Fit from each of `candidates` by successive halving: every start takes `probe_steps` steps, the better
    half (by the loss at its last accepted point) goes on to twice as many, and so on until one is left, which
    goes on to `max_steps`. Returns the runs and the winner's index. `hold`: fields that Levenberg-Marquardt on the
    host leaves as they start (`Effect.POLISH_FIELDS` before the polish). `own`: as `host_evaluator`'s (Levenberg-
    Marquardt on the host only); `coarse`: a `CoarseLinearisation` of the residuals of `own` (or the problem's).
    `by_ratios` (Levenberg-Marquardt on the host, fields with `FieldInfo.decades`): each start races twice, the
    second time with those fields moved by ratios (`FitProblem.warps`); run `i + len(candidates)` is start `i`'s.

    The starts differ only in their fitted fields, so they share one problem and its compiled program; each
    keeps its own solver state, so a start that goes on is not started again.
    """
    frames, tints = frame_data[0], None if tint_high is None else light_tints(frame_data)
    problems = [
        FitProblem.of(candidate, bounds, frames, loss=loss, space=space, light_tints=tints, tint_high=tint_high)
        for candidate in candidates
    ]
    dtype = np.dtype(frames[0].color.dtype)
    data = (problems[0], frame_data)
    runs = []
    if isinstance(optimiser, LevenbergMarquardt):
        held = problems[0].unknowns_of(hold)
        optimiser = dataclasses.replace(optimiser, held=held)
        if coarse is not None and own is None:
            own = lambda positions: _fitted_effects(problems[0], positions)[0]  # noqa: E731
        maps = [None, problems[0].warps] if by_ratios and np.any(problems[0].warps) else [None]
        maps = [(warps, host_evaluator(problems[0], frame_data, dtype, own, coarse, warps)) for warps in maps]
        starts = {} if len(maps) > 1 else None  # each start's first point, which both maps take: taken once
        for (warps, evaluate), problem in itertools.product(maps, problems):
            y, given = (np.asarray(start_point(problem, dtype, inset=inset), np.float64) for inset in (True, False))
            if warps is not None:
                y, given = warped_start(y, warps), warped_start(given, warps, inset=False)
            y[list(held)] = given[list(held)]  # a held field stays as given, on a bound too (the polish insets it)
            # The first step's evaluation, the start's loss; linearised now (the first step accepts its point), so
            # that the starts waiting for their first step hold normal equations, not Jacobians.
            residuals, linearise = host_evaluator(problems[0], frame_data, dtype, own, coarse, warps, starts)(y)
            normal_equations = linearise()
            first = (residuals, lambda normal_equations=normal_equations: normal_equations)
            loss = float(np.sum(np.square(residuals, dtype=np.float64)))
            runs.append(_Run(problems[0], optimiser.init(y, first), [loss], warps=warps, evaluate=evaluate))

        def step(run):
            run.state = optimiser.step(run.state, run.evaluate)
            return run.state.loss

    else:
        function = residual_function if least_squares else objective_function
        for problem in problems:
            y = start_point(problem, dtype)
            state, done, succeeded = exported.call("fit_init", solver_init, optimiser, function, y, (problem, frame_data))
            start_loss = float(exported.call("fit_loss", evaluate_loss, problem.effect, (problem, frame_data)))
            runs.append(_Run(problems[0], (y, state, done, succeeded), [start_loss]))

        def step(run):
            y, leaves, done, succeeded, accepted_loss = exported.call(
                "fit_step", solver_step, optimiser, function, run.state[0], run.state[1], data, least_squares
            )  # fmt: skip
            run.state = (y, leaves, done, succeeded)
            return float(accepted_loss)

    def advance(run, until, stop=None):
        while run.steps < until and not run.stopped and not (stop is not None and stop.is_set()):
            run.solver_losses.append(step(run))
            run.steps += 1
            if run.steps > 1:  # after the first step the state holds the start's loss, already recorded
                run.history.append(run.solver_losses[-1])
            counter(run.history[-1])
            run.plateaued = bool(plateau_steps) and (
                plateaued(run.solver_losses, plateau_steps, plateau_rtol)
                or (run.on_host and stalled(run.state, run.solver_losses, plateau_steps, plateau_rtol))
            )

    # With several lights a Jacobian holds each light's temporaries, and two at once outgrow the fit's memory.
    together = not any(frame_data[5])
    alive, budget = list(range(len(runs))), probe_steps
    while len(alive) > 1:
        budget = min(budget, max_steps)
        if together:
            advance_two_at_a_time([runs[index] for index in alive], budget, advance)
        else:
            for index in alive:
                advance(runs[index], budget)
        keep = 1 if budget == max_steps else (len(alive) + 1) // 2
        alive = sorted(alive, key=lambda index: runs[index].history[-1])[:keep]
        budget *= 2
    advance(runs[alive[0]], max_steps)
    return runs, alive[0]


def _effect_of_run(run: _Run) -> Effect:
    """The effect at a run's last accepted point."""
    dtype = np.asarray(field_value(run.problem.effect, run.problem.names[0])).dtype
    return _fitted_effects(run.problem, run.positions_as(dtype))[0]


def _frames_of_run(run: _Run, frame_data) -> tuple:
    """`frame_data` with the lights' tints at a run's last accepted point (as they are where it fits none)."""
    return run.problem.frames_at_positions(run.positions_as(frame_data[0][0].color.dtype), frame_data)


def fit(
    effect: Effect,
    buffers: Buffers | Sequence[Buffers],
    light_xy: Float[ArrayLike, "2"] | Sequence[Float[ArrayLike, "2"]],
    target: Float[ArrayLike, "H W C"] | Sequence[Float[ArrayLike, "H W C"]],
    *,
    loss: Literal["mse", "l1", "charbonnier", "ssim"] = "mse",
    space: Space = "display",
    solver: str | optx.AbstractLeastSquaresSolver | optx.AbstractMinimiser = "auto",
    fixed: Sequence[str] = (),
    max_steps: int = 50,
    rtol: float = 1e-4,
    atol: float = 1e-7,
    light_in_front: Bool[ArrayLike, ""] | bool | Sequence[bool] = True,
    light_depth: float | Sequence[float] = math.inf,
    other_lights: Sequence[Light] | Sequence[Sequence[Light]] = (),
    fit_light_tints: bool = True,
    progress: Callable[[int, float], None] | None = None,
    starts: Sequence[Effect] = (),
    probe_steps: int = 3,
    coarse_factor: int = 1,
    plateau_steps: int = 5,
    plateau_rtol: float = 1e-3,
    coarse_plateau_rtol: float = 2e-2,
    coarse_plateau_steps: int = 10,
    coarse_jacobian: bool = False,
    stand_in: bool = True,
) -> FitResult:
    """Fit `effect`'s parameters so `effect(buffers, light_xy)` matches `target`.

    Args:
        effect: the starting effect; its type and static fields are kept (the fit draws the frames as
            `effect.same_on(buffers)`: the same frames, more cheaply where they allow). Its values must lie
            inside their bounds.
        buffers: one frame, or a sequence of frames sharing one parameter set.
        light_xy: the light in pixels, `(2,)`, or one per frame.
        target: the reference image(s), linear `(H, W, C)` of each frame's
            size; the first `min(C, 3)` channels are compared.
        loss: `"mse"`, `"l1"`, `"charbonnier"` or `"ssim"` (`losses.LOSSES`),
            averaged over frames weighted by pixel count.
        space: `"display"` (`x / (1 + |x|)`, the default: the sun does not
            drown every other difference) or `"linear"`.
        solver: `"auto"` (Levenberg-Marquardt for `"mse"`, BFGS otherwise),
            `"levenberg_marquardt"`, `"gauss_newton"`, `"bfgs"`, or an
            optimistix least-squares solver (MSE only) or minimiser.
            Levenberg-Marquardt runs on the host around one compiled
            program, the residuals and their Jacobian
            (`residuals_and_jacobian`; `marquardt`: optimistix's steps, the
            damped normal equations solved in NumPy), and is followed by a
            polish phase with Marquardt's scaling (up to `max_steps` more
            steps, with the plateau stop); the others are optimistix's
            with its default linear solvers. Gauss-Newton takes full,
            undamped steps: use it from a start near the solution.
        fixed: names of fittable fields to leave as they are.
        max_steps: solver steps at most (each evaluates the effect and its
            Jacobian once).
        rtol, atol: the solver's convergence tolerances (on the unit-scaled
            parameters and the loss).
        light_in_front: whether each frame's light is in front of the camera.
        light_depth: each frame's light distance along its camera ray, scene units
            (`inf`: the sun), one or one per frame; effects that measure depth read it.
        other_lights: the frame's lights beside its first (`effects.lights.Light`s: positions, sides, distances
            and tints), or one such sequence per frame: each frame is then drawn under all of them, their light
            added (`effects.lights.lit_by`), the fitted fields shared by every light.
        fit_light_tints: with `other_lights`, fit their tints too, jointly with the fields (the `k`-th light
            beside every frame's first sharing one tint, from the first frame's; up to `problem.TINT_RANGE` times
            the largest given): `FitResult.light_tints`. False: the tints stay as given.
        progress: called as `progress(step, loss)` after every step (steps
            counted over every start and both phases; the coarse phase's losses
            are at its resolution), one call at a time but not always from the
            caller's thread: the race's starts step two at a time, on this
            thread and a helper.
        starts: other starts, effects of `effect`'s type (a model's presets, a
            start read from the frame): their fitted fields clipped to their
            fitting ranges, the rest `effect`'s. `effect` and each of them race
            by successive halving (in the coarse phase when there is one): each
            takes `probe_steps` steps, the better half by loss goes on to twice
            as many steps, and so on until one is left, which goes on to
            `max_steps`; the result does not depend on which of them it was
            given, for a fraction of the cost of a fit from each.
        probe_steps: a Python int >= 1, the steps every start takes before the
            first halving.
        coarse_factor: a Python int >= 1; above 1 the fit first runs on every
            frame and target at `1 / coarse_factor` of its resolution
            (`reduced.downsample_buffers`: colour box-averaged, each block's
            nearest depth; the light and sizes in pixels scaled), up to
            `max_steps` steps, then goes on at full resolution from there, up
            to `max_steps` more. Each coarse step costs about `coarse_factor**2`
            times less, and the fine phase starts near its minimum.
        plateau_steps, plateau_rtol: stop (in each phase; in a coarse phase
            `coarse_plateau_rtol` replaces `plateau_rtol`) once the loss has
            fallen by less than `plateau_rtol` of itself over the last
            `plateau_steps` steps, every one of them taken since the loss first
            fell below the phase's start (steps the solver rejected before
            that do not count), or, for Levenberg-Marquardt on the host,
            once a step it rejected leaves its next step a predicted fall
            below `plateau_rtol / plateau_steps` of the loss (`stalled`);
            `plateau_steps=0` runs until the solver converges or `max_steps`.
        coarse_plateau_rtol, coarse_plateau_steps: `plateau_rtol` and
            `plateau_steps` of the coarse phase: its result only starts the
            full resolution, which then starts near its own minimum and ends
            on `plateau_rtol`. Over fewer steps a race stopped where the loss
            fell slowly on a long way to its minimum (a room's medium shrinking
            to its walls; docs/findings.md, "Where a room's fit ends").
        coarse_jacobian: with a coarse phase and Levenberg-Marquardt, the
            full resolution's descent before the polish takes its Jacobian
            from the coarse resolution (each pixel's derivatives its block's,
            `fit_programs.CoarseLinearisation`): its residuals, losses and
            the steps it accepts stay the full resolution's, each step a
            render and a coarse Jacobian. The polish takes the full
            resolution's derivatives of the fields that move sharp edges
            (`Effect.SHARP_STAGES`, taken where it starts and kept; every
            field's, at every step, where the effect names none) and the
            coarse ones of the rest. Ignored when a fitted field is in
            pixels (`reduced.pixel_fields`).
        stand_in: the starts race and descend as the effect's stand-in
            (`Effect.fit_stand_in`: the same fields read more cheaply, where
            the effect names one; for `VolumetricFog` with its shadows read
            along lines, read along fewer lines on rays farther apart), and
            the polish (Levenberg-Marquardt's polish phase) takes the effect's
            own residuals with the stand-in's Jacobian: the result is the effect given with its static fields,
            its losses the effect's own (`loss_history`: the stand-in's until the polish). Without a polish
            phase (another loss or solver) the stand-in's fitted fields are returned in the effect given.
            False: every phase fits the effect itself.

    Returns:
        A `FitResult`: fitted effect, rounded-count effect, loss history and
        the losses before, after and after rounding.
    """
    frame_data = tuple(as_frames(buffers, light_xy, target, light_in_front, light_depth, other_lights))
    tints = light_tints(frame_data) if fit_light_tints else None
    if tints is not None:  # every frame's from the first's
        if len({len(beside) for beside in frame_data[5]}) > 1:
            raise ValueError("other_lights must hold as many lights in every frame to fit their tints")
        frame_data = with_light_tints(frame_data, tints)
    phases = Phases.of(
        loss=loss, space=space, solver=solver, max_steps=max_steps, rtol=rtol, atol=atol, probe_steps=probe_steps,
        coarse_factor=coarse_factor, plateau_steps=plateau_steps, plateau_rtol=plateau_rtol,
        coarse_plateau_rtol=coarse_plateau_rtol, coarse_jacobian=coarse_jacobian,
        coarse_plateau_steps=coarse_plateau_steps,
        tint_high=None if tints is None else tint_range(tints),
    )  # fmt: skip
    # Weakly typed fields (`eqx.tree_at(lambda e: e.density, effect, jnp.asarray(0.5))`) would make the
    # loss compile twice: once for them, once for the fitted effect's.
    requested = jax.tree.map(strongly_typed, effect)
    given = requested.same_on(frame_data[0])  # drawn alike, more cheaply where the frames allow (`Effect.same_on`)
    chosen = requested.fit_stand_in() if stand_in else requested
    effect = given if chosen is requested else chosen.same_on(frame_data[0])
    bounds = fitted_bounds(effect, fixed=fixed)
    names = tuple(bounds)
    frame_data = with_frames_read_once(effect, frame_data, names)
    # Fields fitted in the polish alone are held as given until then, where there is a polish to fit them.
    held = type(effect).POLISH_FIELDS if phases.polisher is not None else ()
    phases = dataclasses.replace(phases, descend={**phases.descend, "hold": held})
    check_inside_bounds(effect)
    candidates, origins = _distinct_starts(effect, starts, bounds)
    counter = StepCounter(progress)
    # GPUs multiply float32 matrices in TF32 (10-bit mantissas) by default; the solver's linear algebra needs more.
    # Every traced value stays in range (checked above, then mapped into its bounds), so the compiled steps carry
    # no run-time range check: without its host callback, JAX's persistent cache can store them.
    with jax.default_matmul_precision("highest"), ranges_guaranteed():
        problem = FitProblem.of(effect, bounds, frame_data[0], loss=loss, space=space)
        frames_given = frame_data
        loss_before, images_before = effect_loss(problem, given, frame_data)
        candidates, coarse_start, coarse, frame_data = _coarse_phase(phases, candidates, bounds, frame_data, counter)
        coarse_steps = counter.steps
        runs, winner = _descend(candidates, bounds, frame_data, counter, **phases.descend, coarse=coarse)
        start_index = origins[winner if coarse_start is None else coarse_start]
        run = runs[winner]
        frame_data = _frames_of_run(run, frame_data)
        history = run.history if coarse_start is None and start_index == 0 else [loss_before, *run.history]
        def own(positions):  # through a stand-in, the polish's residuals: the effect given, at the positions
            return _as_given(given, effect, _fitted_effects(problem, positions)[0], names)

        run, polish_history, polish_steps = _polish_phase(
            phases, run, bounds, frame_data, counter, None if given is effect else own, coarse
        )  # fmt: skip
        history = [*history, *polish_history]
        positions = run.positions_as(frame_data[0][0].color.dtype)
        frame_data = _frames_of_run(run, frame_data)
        fitted_effect, rounded = (_as_given(given, effect, e, names) for e in _fitted_effects(run.problem, positions))
        if not all(np.all(np.isfinite(np.asarray(field_value(fitted_effect, n)))) for n in names):
            raise ValueError("the fit diverged (non-finite parameters); try fewer free parameters or another start")
        loss_after, images_after = effect_loss(problem, fitted_effect, frame_data)
        # The phases descend on reduced frames and through the stand-in, whose minima are near the effect's own but
        # not at them: from a start at the frames' own minimum, or nearer it than they lead, a fit would end above
        # where it began. It hands back the start given instead.
        kept_start = bool(loss_before < loss_after)
        if kept_start:
            frame_data, fitted_effect, rounded = frames_given, given, round_counts(given)
            loss_after, images_after = loss_before, images_before
            history = [*history, loss_before]
        same = _same_values(fitted_effect, rounded, names)
        loss_rounded, images_rounded = (loss_after, images_after) if same else effect_loss(problem, rounded, frame_data)
    return FitResult(
        effect=_as_given(requested, given, fitted_effect, names),
        rounded=_as_given(requested, given, rounded, names),
        loss_history=np.asarray(history),
        loss_before=loss_before,
        loss_after=loss_after,
        loss_rounded=loss_rounded,
        images_before=images_before,
        images_after=images_after,
        images_rounded=images_rounded,
        fitted=names,
        steps=counter.steps - coarse_steps,
        converged=bool(run.converged),
        plateaued=run.plateaued,
        coarse_steps=coarse_steps,
        start=0 if kept_start else start_index,
        kept_start=kept_start,
        polish_steps=polish_steps,
        light_tints=None if tints is None else np.asarray(light_tints(frame_data)),
    )


def _distinct_starts(effect: Effect, starts: Sequence[Effect], bounds) -> tuple[list[Effect], list[int]]:
    """The starts to race: `effect` and each of `starts` like it (`_start_like`), a start that repeats an earlier
    one left out (the effect given is often one of the model's presets); and each one's index among them all."""
    candidates, origins = [], []
    for index, candidate in enumerate([effect, *[_start_like(effect, other, bounds) for other in starts]]):
        if not any(_same_values(candidate, other, tuple(bounds)) for other in candidates):
            candidates.append(candidate)
            origins.append(index)
    return candidates, origins


def _coarse_phase(
    phases: Phases, candidates, bounds, frame_data, counter
) -> tuple[list[Effect], int | None, CoarseLinearisation | None, tuple]:
    """With a coarse factor, the starts race at the reduced resolution (`reduced.downsample_buffers`) and the
    winner descends there: its result at full resolution as the one start left, the index of the start that won,
    the linearisation at the coarse resolution (`coarse_jacobian`, else None) and `frame_data` with the lights'
    tints it fitted. Without, the starts, Nones and `frame_data`."""
    factor = phases.coarse_factor
    if factor == 1:
        return candidates, None, None, frame_data
    reduced = with_frames_read_once(candidates[0], downsample_frames(frame_data, factor), bounds)
    scaled = [scale_pixel_fields(candidate, 1.0 / factor) for candidate in candidates]
    coarse_runs, winner = _descend(
        scaled, bounds, reduced, counter,
        **{**phases.descend, "plateau_rtol": phases.coarse_plateau_rtol, "plateau_steps": phases.coarse_plateau_steps},
        by_ratios=True,
    )  # fmt: skip
    fine_start = _effect_of_run(coarse_runs[winner])
    linearises = phases.coarse_jacobian and isinstance(phases.optimiser, LevenbergMarquardt)
    linearisation = CoarseLinearisation.of(coarse_runs[winner].problem, reduced, factor) if linearises else None
    fine_start = clip_to_bounds(scale_pixel_fields(fine_start, float(factor)), bounds)
    return [fine_start], winner % len(candidates), linearisation, _frames_of_run(coarse_runs[winner], frame_data)


def _polish_phase(
    phases: Phases, run: _Run, bounds, frame_data, counter, own, coarse: CoarseLinearisation | None
) -> tuple[_Run, list[float], int]:
    """The polish after Levenberg-Marquardt (Marquardt's scaling, from where `run` stopped): its run, its losses
    (one per step, as a descent's: its first where it starts) and its steps. Through a stand-in it takes the
    effect's own residuals (`own`, as `host_evaluator`'s) and the stand-in's Jacobian; after the descent's
    `coarse` one, the `SHARP_STAGES`' columns at full resolution, taken at its start and kept
    (`CoarseLinearisation.kept`), the rest coarse (every column at full resolution where the effect names none).
    Without a polish, `run`, no losses and no steps."""
    if phases.polisher is None or phases.descend["max_steps"] == 0:
        return run, [], 0
    before = counter.steps
    sharp = type(run.problem.effect).SHARP_STAGES
    linearisation = (None if coarse is None or sharp is None
                     else dataclasses.replace(coarse, sharp=tuple(sharp), kept={}))  # fmt: skip
    polish = {**phases.descend, "optimiser": phases.polisher, "own": own, "coarse": linearisation, "hold": ()}
    polished, _ = _descend([_effect_of_run(run)], bounds, frame_data, counter, **polish)
    return polished[0], polished[0].history, counter.steps - before


def _as_given(given: Effect, fitted_type: Effect, fitted: Effect, names: Sequence[str]) -> Effect:
    """`fitted`'s fields `names` in the effect given; `fitted` itself when it is of the effect given (no stand-in:
    `fitted_type` is `given`)."""
    if fitted_type is given:
        return fitted
    return replace_fields(given, {name: field_value(fitted, name) for name in names})
