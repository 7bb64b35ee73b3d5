"""How well a fit's frames determine each fitted field (`determination`), from the Jacobian at the solution."""

import dataclasses
import math
from collections.abc import Sequence

import jax
import numpy as np
from jaxtyping import ArrayLike, Bool, Float

from godrays_jax.effects.base import Effect
from godrays_jax.effects.fields import parameter_bounds
from godrays_jax.effects.lights import Light
from godrays_jax.kernels.losses import Space, check_space
from godrays_jax.pipeline import exported, fit_programs
from godrays_jax.pipeline.fit_programs import CoarseLinearisation, residuals_and_jacobian
from godrays_jax.pipeline.problem import (
    FitProblem,
    as_frames,
    check_inside_bounds,
    fitted_bounds,
    light_tints,
    strongly_typed,
    with_frames_read_once,
)
from godrays_jax.pipeline.reduced import downsample_frames, scale_pixel_fields
from godrays_jax.primitives.buffers import Buffers
from godrays_jax.primitives.checks import ranges_guaranteed


@dataclasses.dataclass(frozen=True)
class Determination:
    """How well a fit's frames pin each fitted field down (`determination`).

    Attributes:
        sensitivity: field -> the RMS change of the compared image (in the
            fit's space) when the field moves by `change` of its fitting range
            and the other fitted fields move to offset it as well as they can;
            for a vector field, its least determined component; `light_tints`
            the same for the other lights' tints, where the fit fitted them.
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
    other_lights: Sequence[Light] | Sequence[Sequence[Light]] = (),
    fit_light_tints: bool = True,
    change: float = 0.1,
    threshold: float = 1e-3,
    coarse_factor: int = 1,
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
        buffers, light_xy, target, light_in_front, light_depth, other_lights: as for `fit`.
        fit_light_tints: whether the fit fitted the tints of `other_lights` (as `fit`'s): they are then examined
            with the fields, as `light_tints` (a light's tint over the first's, in units of its fitting range:
            `problem.TINT_RANGE` times the largest given), and the fit's compiled Jacobian is the one taken.
        fitted: the fields to examine (e.g. `FitResult.fitted`).
        space: `"display"` or `"linear"`, as the fit compared.
        change: the step, a fraction of each field's range (> 0).
        threshold: RMS image change below which a step goes unseen (> 0).
        coarse_factor: a Python int >= 1; above 1, `J` as the polish of a
            fit with that `coarse_factor` and `coarse_jacobian` takes it: the
            effect's `SHARP_STAGES` at full resolution, the other fields'
            derivatives at `1 / coarse_factor` of it, each pixel's its block's
            (`fit_programs.CoarseLinearisation`); after such a fit, its
            compiled programs. The full resolution's alone where the effect
            names no sharp stages or a field in pixels is examined.

    Raises:
        ValueError: an unknown or static field in `fitted`, bad frames, a
            non-positive `change` / `threshold`, or derivatives that are not
            finite at the effect's values (naming their fields).
    """
    if not (change > 0 and threshold > 0):
        raise ValueError(f"change and threshold must be > 0, got {change!r} and {threshold!r}")
    if not (isinstance(coarse_factor, int) and coarse_factor >= 1):
        raise ValueError(f"coarse_factor must be an int >= 1, got {coarse_factor!r}")
    check_space(space)
    effect = jax.tree.map(strongly_typed, effect)
    frame_data = as_frames(buffers, light_xy, target, light_in_front, light_depth, other_lights)
    frames = frame_data[0]
    every = parameter_bounds(effect)
    if not fitted or not set(fitted) <= set(every):
        raise ValueError(f"fitted must name fittable fields of {type(effect).__name__}, got {list(fitted)}")
    check_inside_bounds(effect)
    bounds = fitted_bounds(effect, fixed=[name for name in every if name not in fitted])
    # Through the effect's stand-in (`Effect.same_on`, `Effect.fit_stand_in`), as `fit` differentiates it: the
    # same program as a fit's steps, which after a fit is compiled already.
    tints = light_tints(frame_data) if fit_light_tints else None
    problem = FitProblem.of(effect.fit_stand_in().same_on(frames), bounds, frames, loss="mse", space=space,
                            light_tints=tints)  # fmt: skip
    frame_data = with_frames_read_once(problem.effect, frame_data, problem.names)  # as `fit` reads them
    # The positions are the effect's own values, checked inside their bounds above: no run-time range check, so the
    # cache keeps the Jacobian.
    with jax.default_matmul_precision("highest"), ranges_guaranteed():
        positions = problem.positions(np.dtype(frames[0].color.dtype))
        coarse = _polish_linearisation(problem, frame_data, coarse_factor)
        if coarse is None:
            residuals, jacobian = exported.call("fit_jacobian", residuals_and_jacobian, problem, positions, frame_data)
            rows = jacobian.shape[0]
            _check_finite(np.sum(np.abs(np.asarray(jacobian)), axis=0), problem)
            # J = QR with Q's columns orthonormal: |J v| = |R v| for every v, so the SVD and every least-squares
            # offset below are R's, a parameters-by-parameters matrix, instead of the pixels-by-parameters Jacobian's.
            jacobian = _triangular(np.asarray(jacobian))
        else:
            residuals = fit_programs.effect_residuals(problem, problem.effect, frame_data)
            normal, _ = coarse.normal_equations(positions, np.asarray(residuals), problem, frame_data)
            rows = len(residuals)
            _check_finite(np.diag(normal), problem)
            # R with R^T R = J^T J: |R v| = |J v| for every v, as the QR decomposition's.
            values, vectors = np.linalg.eigh(normal)
            jacobian = np.sqrt(np.maximum(values, 0.0))[:, None] * vectors.T
    # The cut-off below which `lstsq` treats singular values as zero stays the Jacobian's (it scales with the rows).
    cutoff = np.finfo(np.float64).eps * max(rows, jacobian.shape[1])
    owners, labels, lows, spans = [], [], [], []
    for name, ((low, high), shape, _) in zip(_block_names(problem), problem.blocks):
        size = math.prod(shape)
        owners += [name] * size
        labels += [name] if size == 1 and not shape else [f"{name}[{k}]" for k in range(size)]
        lows += [float(low)] * size
        spans += [float(high) - float(low)] * size
    # Where each field sits in its range: 0 on the lower bound, 1 on the upper; a field moved by ratios over its top
    # decades (`problem.warps`) by where it sits among them, so that a medium reaching 10 units of a range up to 1e4
    # is not read as on its bound of 0.
    linear = np.clip(np.asarray(positions, np.float64), 0.0, 1.0)
    warps = problem.warps
    warp = np.where(warps > 0, warps, 1.0)
    position = np.where(warps > 0, np.log1p(linear * np.expm1(warp)) / warp, linear)
    pinned = np.minimum(position, 1.0 - position) <= ON_BOUND
    on_bound = {label: low + span * float(round(where)) for label, low, span, where, on in
                zip(labels, lows, spans, position, pinned) if on}  # fmt: skip
    singular, vectors = np.linalg.svd(jacobian, full_matrices=False)[1:]
    floor = singular.max() * 1e-12 + 1e-300
    inverse_diagonal = ((vectors.T / np.maximum(singular, floor)) ** 2).sum(axis=1)
    per_unknown = change / np.sqrt(inverse_diagonal)
    sensitivity, worst = {}, {}
    for index, name in enumerate(owners):
        if name not in sensitivity or per_unknown[index] < sensitivity[name]:
            sensitivity[name], worst[name] = float(per_unknown[index]), index
    poorly = tuple(name for name in _block_names(problem) if sensitivity[name] < threshold)
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


def _block_names(problem: FitProblem) -> tuple[str, ...]:
    """The name of each of the problem's blocks of unknowns: its fields', then `light_tints` where it fits them."""
    return (*problem.names, *(["light_tints"] if problem.light_tints is not None else []))


def _check_finite(columns, problem: FitProblem) -> None:
    """A `ValueError` naming the fields whose Jacobian `columns` (one number per unknown) are not finite."""
    blocks = zip(_block_names(problem), problem.blocks)
    owners = [name for name, (_, shape, _) in blocks for _ in range(math.prod(shape))]
    broken = list(dict.fromkeys(name for name, column in zip(owners, np.asarray(columns)) if not np.isfinite(column)))
    if broken:
        raise ValueError(f"the frames' derivatives in {', '.join(broken)} are not finite at these values")


def _polish_linearisation(problem: FitProblem, frame_data, factor: int) -> CoarseLinearisation | None:
    """The linearisation a fit's polish takes after a coarse phase of `factor` (`fit._polish_phase`), or None where it
    takes the full resolution's (no coarse phase, no sharp stages named, a field in pixels)."""
    sharp = type(problem.effect).SHARP_STAGES
    if factor == 1 or sharp is None:
        return None
    reduced = with_frames_read_once(problem.effect, downsample_frames(frame_data, factor), problem.names)
    scaled = scale_pixel_fields(problem.effect, 1.0 / factor)
    coarse_problem = FitProblem.of(scaled, dict(zip(problem.names, problem.bounds)), reduced[0], loss=problem.loss,
                                   space=problem.space, light_tints=problem.light_tints,
                                   tint_high=problem.tint_high)  # fmt: skip
    coarse = CoarseLinearisation.of(coarse_problem, reduced, factor)
    return None if coarse is None else dataclasses.replace(coarse, sharp=tuple(sharp))


def _triangular(jacobian: np.ndarray, rows: int = 1 << 19) -> np.ndarray:
    """`R` of the QR decomposition of the Jacobian, in float64, `rows` rows at a time (a large frame's Jacobian
    is not copied in float64 whole)."""
    triangle = np.zeros((0, jacobian.shape[1]))
    for start in range(0, jacobian.shape[0], rows):
        block = np.asarray(jacobian[start : start + rows], np.float64)
        triangle = np.linalg.qr(np.concatenate([triangle, block]), mode="r")
    return triangle


ON_BOUND = 1e-3
"""A fitted value within this fraction of its range from a bound sits on that bound: a field that does not move the
frame stays where `fit` started it, which for a start on a bound is just inside it (`problem.START_INSET`)."""


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
