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
  `low + (high - low) * tri(z)`, `tri` the triangle wave of period 2 (the
  identity on [0, 1], mirrored beyond). Unlike a sigmoid its slope never
  vanishes, so a start on a bound (presets put `decay` at 1.0) still moves,
  and the solver's unknowns all have the same unit scale.
- Derivatives are forward-mode: the Jacobian of the residuals (or the
  gradient of a scalar loss) is one vectorised JVP per fitted parameter,
  memory O(image x parameters) whatever the loop lengths. Levenberg-Marquardt
  and Gauss-Newton need that Jacobian (millions of residuals, a handful of
  parameters), which reverse mode would build one residual at a time.
  The kernels' sample loops have custom JVPs: a handful of parameters are
  differentiated inside the loop that sums the copies (one loop for all of
  them, where vectorised JVPs of a plain loop would run one per parameter),
  so the Jacobian costs about what a reverse-mode gradient costs and memory
  O(image) for any loop length, where a plain differentiated loop would store
  every iteration; `benchmarks/bench_fit.py` compares the two.
"""

import dataclasses
import math
from collections.abc import Callable, Sequence
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float

from godrays_jax.effects.base import Effect, count_fields, field_metadata, parameter_bounds
from godrays_jax.effects.presets import preset
from godrays_jax.kernels.losses import LOSSES, Space, check_space, to_space
from godrays_jax.pipeline import exported
from godrays_jax.primitives.buffers import Buffers
from godrays_jax.primitives.checks import ranges_guaranteed

SOLVERS: tuple[str, ...] = ("auto", "levenberg_marquardt", "gauss_newton", "bfgs")


@dataclasses.dataclass(frozen=True)
class FitResult:
    """What `fit` returns.

    Attributes:
        effect: the fitted effect, same type and static fields as the start;
            counts may be fractional (the relaxation).
        rounded: `effect` with every fitted count rounded to the nearest integer.
        loss_history: the loss at the solver's last accepted parameters after
            each step; `loss_history[0]` is the starting loss.
        loss_before: the loss of the starting effect.
        loss_after: the loss of `effect`.
        loss_rounded: the loss of `rounded`.
        fitted: the names of the fields that were fitted.
        steps: solver steps taken.
        converged: whether the solver met its tolerances within `max_steps`.
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


def fitted_bounds(effect: Effect, *, fixed: Sequence[str] = ()) -> dict[str, tuple[float, float]]:
    """`{field: (low, high)}` for the fields `fit` would fit: bounds capped by their static caps (`FieldInfo.cap`).

    Raises `ValueError` naming `fixed` if it lists a field that is not fittable.
    """
    bounds = parameter_bounds(effect)
    unknown = sorted(set(fixed) - set(bounds))
    if unknown:
        raise ValueError(
            f"fixed names unknown or static field(s) {', '.join(unknown)}; fittable: {', '.join(bounds)}"
        )
    infos = field_metadata(effect)
    result = {}
    for name, (low, high) in bounds.items():
        if name in fixed:
            continue
        if infos[name].cap is not None:
            high = min(high, float(getattr(effect, infos[name].cap)))
        result[name] = (float(low), float(high))
    if not result:
        raise ValueError("fixed leaves no parameter to fit")
    return result


def _to_unit(value, low, high):
    return (value - low) / (high - low)


def _from_unit(unit, low, high):
    folded = jnp.mod(unit, 2.0)
    # Not `1 - |1 - folded|`: the derivative of |x| at 0 is 0, which would pin a start on the upper bound.
    return low + (high - low) * jnp.where(folded <= 1.0, folded, 2.0 - folded)


def round_counts(effect: Effect) -> Effect:
    """The effect with every count field (`FieldInfo.count`) rounded to the nearest integer."""
    names = count_fields(effect)
    if not names:
        return effect
    return eqx.tree_at(lambda e: [getattr(e, n) for n in names], effect, [jnp.round(getattr(effect, n)) for n in names])


def _per_frame(value, count, name):
    """One value per frame from a scalar (or bool) or a sequence of `count`."""
    values = [value] * count if isinstance(value, bool) or np.ndim(value) == 0 else list(value)
    if len(values) != count:
        raise ValueError(f"{name} must be one value or one per frame ({count})")
    return values


def _as_frames(buffers, light_xy, target, light_in_front, light_depth=math.inf):
    """Normalise one frame or a sequence of frames into equal-length lists."""
    if isinstance(buffers, Buffers):
        buffers, light_xy, target, light_in_front = [buffers], [light_xy], [target], [light_in_front]
        light_depth = [light_depth]
    else:
        buffers = list(buffers)
        count = len(buffers)
        if count == 0:
            raise ValueError("buffers must hold at least one frame")
        if not all(isinstance(frame, Buffers) for frame in buffers):
            raise ValueError("buffers must be a Buffers or a sequence of Buffers")
        light_array = np.asarray(light_xy, dtype=np.float64)
        if light_array.shape != (count, 2):
            raise ValueError(f"light_xy must hold one (x, y) per frame ({count}), got shape {light_array.shape}")
        light_xy = list(light_array)
        if isinstance(target, (list, tuple)):
            target = list(target)
        elif jnp.ndim(target) == 4:
            target = [target[i] for i in range(target.shape[0])]
        else:
            raise ValueError(f"target must hold one image per frame ({count})")
        if len(target) != count:
            raise ValueError(f"target must hold one image per frame ({count}), got {len(target)}")
        light_in_front = _per_frame(light_in_front, count, "light_in_front")
        light_depth = _per_frame(light_depth, count, "light_depth")
    lights, targets = [], []
    for index, (frame, light, image) in enumerate(zip(buffers, light_xy, target)):
        light = jnp.asarray(light, frame.color.dtype)
        if light.shape != (2,):
            raise ValueError(f"light_xy[{index}] must be (x, y) in pixels, got shape {light.shape}")
        image = jnp.asarray(image, frame.color.dtype)
        if image.ndim != 3 or image.shape[:2] != frame.color.shape[:2]:
            raise ValueError(
                f"target[{index}] must be (H, W, C) with the frame's size {frame.color.shape[:2]}, got {image.shape}"
            )
        lights.append(light)
        targets.append(image)
    depths = []
    for index, (frame, depth) in enumerate(zip(buffers, light_depth)):
        depth = np.asarray(depth, np.float64)
        if depth.shape != () or not depth > 0:
            raise ValueError(f"light_depth[{index}] must be a distance > 0 in scene units (inf: the sun), got {depth}")
        depths.append(jnp.asarray(np.asarray(depth, frame.color.dtype)))
    # From NumPy: `jnp.asarray(True)` compiles a conversion.
    return buffers, lights, targets, [jnp.asarray(np.asarray(flag)) for flag in light_in_front], depths


def _match_channels(image, target):
    channels = min(image.shape[-1], target.shape[-1], 3)
    return image[..., :channels], target[..., :channels]


def _solver(solver, loss, rtol, atol):
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
    if solver == "levenberg_marquardt":
        # Damped steps by the normal equations (J^T J + lambda I is positive definite for any lambda > 0, and
        # as small as the parameter count) instead of optimistix's default QR of the whole Jacobian, which
        # dominated a compiled fit (`benchmarks/fit_results.md`).
        return optx.LevenbergMarquardt(rtol=rtol, atol=atol, linear_solver=lx.Normal(lx.Cholesky()))
    if solver == "gauss_newton":
        return optx.GaussNewton(rtol=rtol, atol=atol)
    return optx.BFGS(rtol=rtol, atol=atol)


def _forward_mode(function):
    """`function(y)` (flat `y`) whose JVP is a precomputed forward-mode Jacobian times the tangent.

    optimistix linearises the objective; linearising the kernels' sample loops
    directly would store every iteration. Here the Jacobian is computed with
    one vectorised `jax.jvp` per parameter (memory O(output x parameters)) and
    the linearisation only keeps that Jacobian.
    """

    @jax.custom_jvp
    def wrapped(y):
        return function(y)

    @wrapped.defjvp
    def wrapped_jvp(primals, tangents):
        (y,), (tangent,) = primals, tangents
        basis = jnp.eye(y.shape[0], dtype=y.dtype)
        value, jacobian = jax.vmap(lambda direction: jax.jvp(function, (y,), (direction,)), out_axes=(None, -1))(basis)
        return value, jnp.matmul(jacobian, tangent, precision="highest")

    return wrapped


class _Problem(eqx.Module):
    """What a fit's objective needs besides the unknowns; static fields make compilations reusable.

    Every field but `effect` is static and hashable, and the objective
    functions below are module-level, so two fits of the same effect type,
    fitted names, frame sizes and options reuse one compiled solver step.
    """

    effect: Effect
    names: tuple[str, ...] = eqx.field(static=True)
    bounds: tuple[tuple[float, float], ...] = eqx.field(static=True)
    shapes: tuple[tuple[int, ...], ...] = eqx.field(static=True)
    frame_weights: tuple[float, ...] = eqx.field(static=True)
    loss: str = eqx.field(static=True)
    space: str = eqx.field(static=True)

    def effect_at(self, y):
        """The effect with the fitted fields set from the flat unit-scaled unknowns `y`."""
        values, offset = [], 0
        for name, (low, high), shape in zip(self.names, self.bounds, self.shapes):
            size = math.prod(shape)
            unit = jnp.reshape(y[offset : offset + size], shape)
            values.append(_from_unit(unit, low, high).astype(getattr(self.effect, name).dtype))
            offset += size
        return eqx.tree_at(lambda e: [getattr(e, n) for n in self.names], self.effect, values)

    def rendered(self, candidate, frame_data):
        for frame, light, image, front, depth in zip(*frame_data):
            yield _match_channels(candidate(frame, light, light_in_front=front, light_depth=depth), image)

    def residuals(self, y, frame_data):
        parts = [
            jnp.ravel(to_space(image, self.space) - to_space(reference, self.space)) * math.sqrt(weight / reference.size)
            for (image, reference), weight in zip(self.rendered(self.effect_at(y), frame_data), self.frame_weights)
        ]
        return jnp.concatenate(parts)

    def objective(self, candidate, frame_data):
        return sum(
            weight * LOSSES[self.loss](image, reference, space=self.space)
            for (image, reference), weight in zip(self.rendered(candidate, frame_data), self.frame_weights)
        )


def _residual_function(y, data):
    problem, frame_data = data
    return _forward_mode(lambda flat: problem.residuals(flat, frame_data))(y), None


def _objective_function(y, data):
    problem, frame_data = data
    return _forward_mode(lambda flat: problem.objective(problem.effect_at(flat), frame_data))(y), None


@eqx.filter_jit
def _evaluate(candidate, data):
    problem, frame_data = data
    return problem.objective(candidate, frame_data)


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
    `ValueError` naming a field outside them. Traced fields (a call inside
    `jit`) are checked by the kernels when the program runs.
    """
    if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(effect)):
        return _render(effect, buffers, light_xy, light_in_front, light_depth, True)  # traced fields: checked when run
    _check_inside_bounds(effect)
    light_depth = jnp.asarray(np.asarray(light_depth, buffers.color.dtype))
    return exported.call("render", _render, effect, buffers, light_xy, light_in_front, light_depth, False)


def _check_inside_bounds(effect: Effect) -> None:
    """`ValueError` naming the first fittable field outside its fitting range (`fitted_bounds`)."""
    for name, (low, high) in fitted_bounds(effect).items():
        value = np.asarray(getattr(effect, name))
        if not np.all((value >= low) & (value <= high)):
            raise ValueError(f"effect.{name} = {value.tolist()} lies outside its fitting range [{low:g}, {high:g}]")


@eqx.filter_jit
def _render(effect, buffers, light_xy, light_in_front, light_depth, checked):
    """`checked` is static: a render traced without range checks is never reused for one that needs them."""
    if checked:
        return effect(buffers, light_xy, light_in_front=light_in_front, light_depth=light_depth)
    with ranges_guaranteed():
        return effect(buffers, light_xy, light_in_front=light_in_front, light_depth=light_depth)


@eqx.filter_jit
def _start_point(problem, dtype):
    """The flat unit-scaled unknowns of the starting effect."""
    return jnp.concatenate([
        jnp.ravel(_to_unit(jnp.asarray(getattr(problem.effect, name), dtype), low, high))
        for name, (low, high) in zip(problem.names, problem.bounds)
    ])  # fmt: skip


@eqx.filter_jit
def _fitted_effects(problem, y):
    """The fitted effect and its counts rounded, compiled (op by op each scalar operation compiles on its own)."""
    effect = problem.effect_at(y)
    return effect, round_counts(effect)


def _first_state(optimiser, function, y, data):
    f_struct = jax.eval_shape(lambda: function(y, data)[0])
    return optimiser.init(function, y, data, {}, f_struct, None, frozenset())


@eqx.filter_jit
def _init(optimiser, function, y, data):
    """The solver's first state (its array leaves), whether it is done already and whether that is a success.

    The residuals' shape is found here, not by tracing the effect again on
    every fit. The state travels between steps as its leaves alone: its
    static parts (a linearised operator's jaxpr, compared by identity) would
    make every step trace again in a later fit, and no stored program
    (`exported`) could take them.
    """
    state = _first_state(optimiser, function, y, data)
    done, result = optimiser.terminate(function, y, data, {}, state, frozenset())
    return jax.tree.leaves(eqx.filter(state, eqx.is_array)), done, result == optx.RESULTS.successful


@eqx.filter_jit
def _step(optimiser, function, y, state_leaves, data, least_squares):
    """One solver step from the state's leaves: the new unknowns and leaves, whether it is done (and a success), and
    the loss at its last accepted point."""
    template = eqx.filter_eval_shape(_first_state, optimiser, function, y, data)
    shapes, static = eqx.partition(template, lambda leaf: isinstance(leaf, jax.ShapeDtypeStruct))
    state = eqx.combine(jax.tree.unflatten(jax.tree.structure(shapes), state_leaves), static)
    y, state, _ = optimiser.step(function, y, data, {}, state, frozenset())
    done, result = optimiser.terminate(function, y, data, {}, state, frozenset())
    accepted_loss = jnp.sum(state.f_info.residual**2) if least_squares else state.f_info.f
    state_leaves = jax.tree.leaves(eqx.filter(state, eqx.is_array))
    return y, state_leaves, done, result == optx.RESULTS.successful, accepted_loss


def _strongly_typed(leaf):
    """A weakly typed array (`jnp.asarray(0.5)`) as a strongly typed one; converted on the host (no compilation)."""
    if isinstance(leaf, jax.Array) and leaf.weak_type:
        return jax.device_put(np.asarray(leaf))
    return leaf


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
    progress: Callable[[int, float], None] | None = None,
) -> FitResult:
    """Fit `effect`'s parameters so `effect(buffers, light_xy)` matches `target`.

    Args:
        effect: the starting effect; its type and static fields are kept. Its
            values must lie inside their bounds.
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
            Levenberg-Marquardt solves its damped steps by the normal
            equations (parameters x parameters, Cholesky), the others with
            optimistix's default linear solvers. Gauss-Newton takes full,
            undamped steps: use it from a start near the solution.
        fixed: names of fittable fields to leave as they are.
        max_steps: solver steps at most (each evaluates the effect and its
            Jacobian once).
        rtol, atol: the solver's convergence tolerances (on the unit-scaled
            parameters and the loss).
        light_in_front: whether each frame's light is in front of the camera.
        light_depth: each frame's light distance along its camera ray, scene units
            (`inf`: the sun), one or one per frame; effects that measure depth read it.
        progress: called as `progress(step, loss)` after every step.

    Returns:
        A `FitResult`: fitted effect, rounded-count effect, loss history and
        the losses before, after and after rounding.
    """
    if loss not in LOSSES:
        raise ValueError(f"loss must be one of {', '.join(LOSSES)}; got {loss!r}")
    if not (isinstance(max_steps, int) and max_steps >= 0):
        raise ValueError(f"max_steps must be an int >= 0, got {max_steps!r}")
    check_space(space)
    optimiser = _solver(solver, loss, rtol, atol)
    least_squares = isinstance(optimiser, optx.AbstractLeastSquaresSolver)
    # Weakly typed fields (`eqx.tree_at(lambda e: e.density, effect, jnp.asarray(0.5))`) would make the
    # loss compile twice: once for them, once for the fitted effect's.
    effect = jax.tree.map(_strongly_typed, effect)
    frames, lights, targets, in_front, depths = _as_frames(buffers, light_xy, target, light_in_front, light_depth)
    bounds = fitted_bounds(effect, fixed=fixed)
    names = tuple(bounds)
    _check_inside_bounds(effect)
    dtype = frames[0].color.dtype
    total_pixels = sum(frame.height * frame.width for frame in frames)
    problem = _Problem(
        effect=effect,
        names=names,
        bounds=tuple(bounds[name] for name in names),
        shapes=tuple(tuple(np.shape(getattr(effect, name))) for name in names),
        frame_weights=tuple(frame.height * frame.width / total_pixels for frame in frames),
        loss=loss,
        space=space,
    )
    data = (problem, (frames, lights, targets, in_front, depths))
    function = _residual_function if least_squares else _objective_function
    # GPUs multiply float32 matrices in TF32 (10-bit mantissas) by default; the solver's linear algebra needs more.
    # Every traced value stays in range (checked above, then mapped into its bounds), so the compiled steps carry
    # no run-time range check: without its host callback, JAX's persistent cache can store them.
    with jax.default_matmul_precision("highest"), ranges_guaranteed():
        loss_before = float(exported.call("fit_loss", _evaluate, effect, data))
        history = [loss_before]
        y = _start_point(problem, np.dtype(dtype))
        state, done, succeeded = exported.call("fit_init", _init, optimiser, function, y, data)
        steps = 0
        while steps < max_steps and not bool(done):
            y, state, done, succeeded, accepted_loss = exported.call(
                "fit_step", _step, optimiser, function, y, state, data, least_squares
            )
            steps += 1
            if steps > 1:  # after the first step the state holds the start's loss, already recorded
                history.append(float(accepted_loss))
            if progress is not None:
                progress(steps, history[-1])
        fitted_effect, rounded = _fitted_effects(problem, y)
        if not all(np.all(np.isfinite(np.asarray(getattr(fitted_effect, n)))) for n in names):
            raise ValueError("the fit diverged (non-finite parameters); try fewer free parameters or another start")
        loss_after = float(exported.call("fit_loss", _evaluate, fitted_effect, data))
        loss_rounded = float(exported.call("fit_loss", _evaluate, rounded, data))
    return FitResult(
        effect=fitted_effect,
        rounded=rounded,
        loss_history=np.asarray(history),
        loss_before=loss_before,
        loss_after=loss_after,
        loss_rounded=loss_rounded,
        fitted=names,
        steps=steps,
        converged=bool(done) and bool(succeeded),
    )


@eqx.filter_jit
def _jacobian(problem, y, frame_data):
    """The residuals' Jacobian in the unit-scaled unknowns, `(residuals, unknowns)`, one JVP per unknown."""
    basis = jnp.eye(y.shape[0], dtype=y.dtype)
    tangents = jax.vmap(lambda direction: jax.jvp(lambda flat: problem.residuals(flat, frame_data), (y,), (direction,))[1])
    return tangents(basis).T


@dataclasses.dataclass(frozen=True)
class Determination:
    """How well a fit's frames pin each fitted field down (`determination`).

    Attributes:
        sensitivity: field -> the RMS change of the compared image (in the
            fit's space) when the field moves by `change` of its fitting range
            and the other fitted fields move to offset it as well as they can;
            for a vector field, its least determined component.
        poorly_determined: the fields whose sensitivity is below `threshold`,
            in fitting order.
        offsets: for each poorly determined field, its step and the others'
            offsetting steps, in the fields' own units: `{"num_samples":
            {"num_samples": 6.3, "decay": -0.004, "weight": 0.05}}` (a vector
            field's component as `name[k]`; offsets under 1 % of a field's
            range are left out, a field on a bound that the offset would
            push out holds still). Every field stays inside its fitting range:
            the step is `change` of the field's range, or the part of it
            (in either direction) that keeps every offset field inside.
        offset_change: for each poorly determined field, the RMS change of
            the image its offsets leave (`sensitivity` times the part of the
            step taken).
        on_bound: the fitted fields (components `name[k]`) that sit on a
            bound of their fitting range, with that bound: `{"num_samples":
            32.0}` (a cap such as `max_samples` included); the frames may ask
            for a value beyond it.
        condition: the Jacobian's condition number (largest over smallest
            singular value; `inf` when some combination leaves the image
            unchanged).
    """

    sensitivity: dict[str, float]
    poorly_determined: tuple[str, ...]
    offsets: dict[str, dict[str, float]]
    offset_change: dict[str, float]
    on_bound: dict[str, float]
    condition: float


def determination(
    effect: Effect,
    buffers: Buffers | Sequence[Buffers],
    light_xy: Float[ArrayLike, "2"] | Sequence[Float[ArrayLike, "2"]],
    target: Float[ArrayLike, "H W C"] | Sequence[Float[ArrayLike, "H W C"]],
    *,
    fitted: Sequence[str],
    space: Space = "display",
    light_in_front: Bool[ArrayLike, ""] | bool | Sequence[bool] = True,
    light_depth: float | Sequence[float] = math.inf,
    change: float = 0.1,
    threshold: float = 1e-3,
) -> Determination:
    """Which fitted fields the frames determine poorly, from the Jacobian at a fit's solution.

    `J` is the Jacobian of the per-pixel differences (the residuals of the
    MSE in `space`, scaled so that `|r|^2` is the mean squared error) with
    respect to the fields in units of their fitting ranges (`fitted_bounds`).
    Moving field `i` by `change` of its range while the others offset it
    optimally (least squares) changes the image by `change / sqrt(inv(J^T
    J)_ii)` RMS; the field is poorly determined when that is below
    `threshold` (the default, 1e-3 in display space, is a quarter of an 8-bit
    step: a change nobody sees). The answer depends on the frames: a field is
    determined only as far as their pixels show it.

    Args:
        effect: the solution (e.g. `FitResult.effect`); values inside bounds.
        buffers, light_xy, target, light_in_front, light_depth: as for `fit`.
        fitted: the fields to examine (e.g. `FitResult.fitted`).
        space: `"display"` or `"linear"`, as the fit compared.
        change: the step, a fraction of each field's range (> 0).
        threshold: RMS image change below which a step goes unseen (> 0).

    Raises:
        ValueError: an unknown or static field in `fitted`, bad frames, or a
            non-positive `change` / `threshold`.
    """
    if not (change > 0 and threshold > 0):
        raise ValueError(f"change and threshold must be > 0, got {change!r} and {threshold!r}")
    check_space(space)
    effect = jax.tree.map(_strongly_typed, effect)
    frames, lights, targets, in_front, depths = _as_frames(buffers, light_xy, target, light_in_front, light_depth)
    every = parameter_bounds(effect)
    if not fitted or not set(fitted) <= set(every):
        raise ValueError(f"fitted must name fittable fields of {type(effect).__name__}, got {list(fitted)}")
    _check_inside_bounds(effect)
    bounds = fitted_bounds(effect, fixed=[name for name in every if name not in fitted])
    names = tuple(bounds)
    total_pixels = sum(frame.height * frame.width for frame in frames)
    problem = _Problem(
        effect=effect,
        names=names,
        bounds=tuple(bounds[name] for name in names),
        shapes=tuple(tuple(np.shape(getattr(effect, name))) for name in names),
        frame_weights=tuple(frame.height * frame.width / total_pixels for frame in frames),
        loss="mse",
        space=space,
    )
    # The unknowns map into the fields' bounds (as in `fit`): no run-time range check, so the cache keeps the Jacobian.
    with jax.default_matmul_precision("highest"), ranges_guaranteed():
        y = _start_point(problem, np.dtype(frames[0].color.dtype))
        frame_data = (frames, lights, targets, in_front, depths)
        jacobian = np.asarray(exported.call("determination_jacobian", _jacobian, problem, y, frame_data), np.float64)
    owners, labels, lows, spans = [], [], [], []
    for name, shape in zip(names, problem.shapes):
        size = math.prod(shape)
        owners += [name] * size
        labels += [name] if size == 1 and not shape else [f"{name}[{k}]" for k in range(size)]
        lows += [bounds[name][0]] * size
        spans += [bounds[name][1] - bounds[name][0]] * size
    # Where each unknown sits in its range: 0 on the lower bound, 1 on the upper.
    position = np.clip(np.asarray(y, np.float64), 0.0, 1.0)
    pinned = np.minimum(position, 1.0 - position) <= ON_BOUND
    on_bound = {label: low + span * float(round(where)) for label, low, span, where, on in
                zip(labels, lows, spans, position, pinned) if on}  # fmt: skip
    # J = QR with Q's columns orthonormal: |J v| = |R v| for every v, so the SVD and every least-squares offset below
    # are R's, a parameters-by-parameters matrix, instead of the pixels-by-parameters Jacobian's.
    # The cut-off below which `lstsq` treats singular values as zero stays the Jacobian's (it scales with the rows).
    cutoff = np.finfo(np.float64).eps * max(jacobian.shape)
    jacobian = np.linalg.qr(jacobian, mode="r")
    singular, vectors = np.linalg.svd(jacobian, full_matrices=False)[1:]
    floor = singular.max() * 1e-12 + 1e-300
    inverse_diagonal = ((vectors.T / np.maximum(singular, floor)) ** 2).sum(axis=1)
    per_unknown = change / np.sqrt(inverse_diagonal)
    sensitivity, worst = {}, {}
    for index, name in enumerate(owners):
        if name not in sensitivity or per_unknown[index] < sensitivity[name]:
            sensitivity[name], worst[name] = float(per_unknown[index]), index
    poorly = tuple(name for name in names if sensitivity[name] < threshold)
    offsets, offset_change = {}, {}
    for name in poorly:
        index = worst[name]
        others = [k for k in range(len(owners)) if k != index]
        direction = _offset(jacobian, index, others, change, cutoff)
        # A field on a bound that the offset would push out holds still, and the others offset without it.
        outward = [
            k for k in others if pinned[k] and abs(direction[k]) >= 0.01 and (direction[k] > 0) == (position[k] > 0.5)
        ]
        if outward:
            others = [k for k in others if k not in outward]
            direction = _offset(jacobian, index, others, change, cutoff)
        direction[np.abs(direction) < 0.01] = 0.0  # offsets under 1 % of a range are left out
        direction *= _inside_part(position, direction)
        moves = {labels[index]: float(direction[index] * spans[index])}
        moves |= {labels[k]: float(direction[k] * spans[k]) for k in others if direction[k] != 0}
        offsets[name] = moves
        offset_change[name] = sensitivity[name] * abs(direction[index]) / change
    smallest = singular.min()
    return Determination(
        sensitivity=sensitivity,
        poorly_determined=poorly,
        offsets=offsets,
        offset_change=offset_change,
        on_bound=on_bound,
        condition=float(singular.max() / smallest) if smallest > 0 else math.inf,
    )


ON_BOUND = 1e-4
"""A fitted value within this fraction of its range from a bound sits on that bound."""


def _offset(jacobian, index, others, change, cutoff):
    """Unknown `index` stepped by `change` and the `others` moved to offset it (least squares), the rest still."""
    direction = np.zeros(jacobian.shape[1])
    direction[index] = change
    direction[others] = np.linalg.lstsq(jacobian[:, others], -jacobian[:, index] * change, rcond=cutoff)[0]
    return direction


def _inside_part(position, direction) -> float:
    """The signed part `t` of a step, `|t| <= 1`, that keeps `position + t * direction` inside [0, 1] everywhere.

    An offset is a line through the solution, so either direction shows it;
    the one that keeps more of the step is taken (forward on a tie).
    """
    moving = direction != 0
    ahead = np.where(direction > 0, 1.0 - position, -position)[moving] / direction[moving]
    behind = np.where(direction > 0, position, position - 1.0)[moving] / direction[moving]
    forward, backward = min(1.0, *ahead), min(1.0, *behind)
    return forward if forward >= backward else -backward


def default_fit_effect() -> Effect:
    """The model `godrays-jax fit` starts from without `--preset` / `--params`: `preset("volumetric_haze")`.

    Chosen by fitting the path-traced references (`benchmarks/fit_volumetric.py`, table in
    `benchmarks/README.md`): against a volumetric path tracer's fog, additive effects can only add
    light while real fog also removes it; of the two media, `VolumetricFog` (each view ray lit
    segment by segment, its shadows read from the depth buffer) fits every reference measured
    closer than `ScatteringFog` (one lit fraction per ray from a radial blur of the open sky).
    When the camera's field of view is known, set it and keep it fixed
    (`fixed=("fov_x_deg", ...)`); the command line does so when the frame carries it.
    """
    return preset("volumetric_haze")


