"""Where the light is, found from a frame and a target: a start read from the target's halo, refined with gradients.

`find_light(effect, buffers, target)` estimates the light's screen position for a target rendered without one
(a reference with no `godrays:light_px`): the effect is drawn with the light as an unknown beside the effect's
colours, which a light's position trades against (a halo moved to one side and dimmed looks like one in place),
and the least squares `fit` minimises (the MSE in display space by default) is minimised over them all.
"""

import dataclasses
import functools
import itertools
import math
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from godrays_jax.effects.base import Effect
from godrays_jax.effects.fields import field_value, parameter_bounds, replace_fields
from godrays_jax.kernels.blur import gaussian_blur
from godrays_jax.kernels.losses import Space, check_space, to_space
from godrays_jax.pipeline.problem import (
    check_inside_bounds,
    fitted_bounds,
    from_unit,
    strongly_typed,
    to_unit,
)
from godrays_jax.pipeline.reduced import (
    clip_to_bounds,
    downsample_buffers,
    scale_pixel_fields,
)
from godrays_jax.primitives.buffers import Buffers
from godrays_jax.primitives.checks import ranges_guaranteed
from godrays_jax.primitives.resample import downsample_box

SEARCH_PIXELS = 80 * 45
"""Without `factor`, `find_light` searches at the smallest integer fraction of the frame's size with at most this
many pixels: a halo is broad, so a coarse frame places it (docs/fitting.md, "When the light's position is not
known")."""

HALO_SIGMA = 0.1
"""The blur that turns a target's excess over its frame into one smooth halo, a fraction of the frame's larger side:
wide enough that noise, shafts and the occluder that hides the light do not make peaks of their own."""

HALO_LEVEL = 0.7
"""The halo's brightest part, whose centroid is a start: above this fraction of the way from its least to its most."""

OFF_SCREEN_PUSHES = (0.2, 0.6)
"""How far beyond the edge, in the frame's larger side, the starts of a halo whose peak lies on an edge are pushed:
the peak of a light off screen is on the edge nearest it, however far out it is."""

LIGHT_REACH = 0.5
"""How far the light may move from its starts, in the frame's larger side, in x and in y: a model that cannot match
the target would otherwise carry its light far off to draw less of a halo it cannot shape, where the target's
halo says the light is near (a light off screen has starts pushed past the edge, `OFF_SCREEN_PUSHES`)."""

VISIBLE_CHANGE = 1e-3
"""The RMS change of the compared image (display space by default) taken as visible: a quarter of an 8-bit step, the
threshold `determination` uses."""

QUANTISATION_VARIANCE = (1.0 / 255.0) ** 2 / 12.0
"""The least variance `find_light` takes the residuals to have: an 8-bit step's rounding, uniform over the step."""

PROBE_STEPS = 4
"""The solver's evaluations each start takes before the best of them goes on alone."""


@dataclasses.dataclass(frozen=True)
class LightSearch:
    """What `find_light` returns; positions in pixels of the frame given (x right, y down, pixel centres at `i + 0.5`,
    off screen beyond `[0, W] x [0, H]`).

    Attributes:
        light_xy: `(2,)` the light found.
        standard_error: `(2,)` its standard error in x and in y, pixels: the square roots of the diagonal of
            `covariance`. Large (or `inf`) where the frames do not show the light: a target the effect does not
            change, a light so far off screen that only its direction shows.
        covariance: `(2, 2)` the position's covariance, pixels squared: the residuals' variance times the inverse
            of the Gauss-Newton curvature of the squared residuals, the colours offsetting a move as well as they can.
        visible_shift: `(2,)` the move in x (in y) that changes the compared image by `VISIBLE_CHANGE` RMS while the
            other unknowns offset it as well as they can, pixels: below it a move goes unseen.
        start_xy: `(2,)` the light's start the light found descended from.
        start: which effect the fields descended from: 0 the effect given, `i` `starts[i - 1]`.
        effect: the effect given with `fields` as fitted beside the light found (at the search's resolution).
        fields: the effect's fields fitted beside the light, in the effect's order.
        loss: the MSE in the search's space at the light found, at the search's resolution.
        factor: the search ran on the frame and target at `1 / factor` of their resolution.
        steps: the solver's evaluations, every start's in both descents.
    """

    light_xy: np.ndarray
    standard_error: np.ndarray
    covariance: np.ndarray
    visible_shift: np.ndarray
    start_xy: np.ndarray
    start: int
    effect: Effect
    fields: tuple[str, ...]
    loss: float
    factor: int
    steps: int


def colour_fields(effect: Effect) -> tuple[str, ...]:
    """The fittable fields of `effect` that colour or scale its light (`tint`, `medium.light_color`,
    `medium.ambient_color`): what `find_light` fits beside the light by default."""
    return tuple(
        name for name in parameter_bounds(effect) if name.rpartition(".")[2] == "tint" or name.endswith("_color")
    )


def search_factor(height: int, width: int) -> int:
    """The smallest factor that brings a `height x width` frame to at most `SEARCH_PIXELS` pixels (1: full size)."""
    factor = 1
    while -(-height // factor) * -(-width // factor) > SEARCH_PIXELS:
        factor += 1
    return factor


def halo_starts(
    buffers: Buffers, target: Float[ArrayLike, "H W C"], *, space: Space = "display"
) -> Float[np.ndarray, "K 2"]:
    """Where the target's halo puts the light: starts for `find_light`, pixels, a few pixels apart at least.

    The target's excess over the frame's colour (`space`, channels averaged) is blurred by `HALO_SIGMA` of the
    frame's larger side. Its brightest pixel's centre is one start; the centroid of its brightest part (above
    `HALO_LEVEL` of the way from its least to its most) another: an occluder in front of the light splits the
    halo in two lobes, whose centroid lies between them. A start within the blur of an edge is what a light off
    screen past that edge makes, however far out it is: it is also pushed outward, across that edge (a corner's
    two), by each of `OFF_SCREEN_PUSHES` of the larger side. A light behind the camera has no halo on screen and
    is not looked for.
    """
    check_space(space)
    target = _checked_target(buffers, target)
    channels = min(buffers.color.shape[-1], target.shape[-1], 3)
    excess = to_space(target[..., :channels], space) - to_space(buffers.color[..., :channels], space)
    side = max(buffers.height, buffers.width)
    sigma = HALO_SIGMA * side
    halo = np.asarray(gaussian_blur(jnp.mean(excess, axis=-1, keepdims=True), sigma=sigma), np.float64)[..., 0]
    rows, columns = np.indices(halo.shape) + 0.5
    row, column = np.unravel_index(int(np.argmax(halo)), halo.shape)
    weights = np.maximum(halo - (np.min(halo) + HALO_LEVEL * np.ptp(halo)), 0.0)
    centroid = np.asarray([np.sum(weights * columns), np.sum(weights * rows)]) / max(np.sum(weights), 1e-30)
    starts = []
    for point in (np.asarray([column + 0.5, row + 0.5]), centroid):
        outward = np.asarray([_side_of(point[0], buffers.width, sigma), _side_of(point[1], buffers.height, sigma)])
        starts.append(point)
        if np.any(outward):
            starts += [point + push * side * outward / np.linalg.norm(outward) for push in OFF_SCREEN_PUSHES]
    return np.stack(_apart(starts, HALO_SIGMA * side / 4))


def _apart(points: list[np.ndarray], distance: float) -> list[np.ndarray]:
    """`points` less each that lies within `distance` of an earlier one."""
    kept = []
    for point in points:
        if all(np.linalg.norm(point - other) >= distance for other in kept):
            kept.append(point)
    return kept


def _side_of(position: float, size: int, band: float) -> float:
    """-1 when `position` lies within `band` of 0, +1 within `band` of `size`, else 0."""
    return -1.0 if position < band else 1.0 if position > size - band else 0.0


def _checked_target(buffers: Buffers, target) -> Array:
    target = jnp.asarray(target, buffers.color.dtype)
    if target.ndim != 3 or target.shape[:2] != buffers.color.shape[:2]:
        raise ValueError(f"target must be (H, W, C) with the frame's size {buffers.color.shape[:2]}, got {target.shape}")
    return target


def find_light(
    effect: Effect,
    buffers: Buffers,
    target: Float[ArrayLike, "H W C"],
    *,
    start_xy: Float[ArrayLike, "2"] | None = None,
    fields: Sequence[str] | None = None,
    starts: Sequence[Effect] = (),
    light_depth: float = math.inf,
    space: Space = "display",
    factor: int | None = None,
    max_steps: int = 40,
    stand_in: bool = True,
    progress: Callable[[int, float], None] | None = None,
) -> LightSearch:
    """The light's screen position that makes `effect(buffers, light_xy)` look most like `target`.

    The light's position is an unknown beside the effect's `fields` (by default its colours, `colour_fields`: a
    light moved off a halo's centre and brightened can look like one in place); every other field is held. They
    minimise the mean squared difference in `space` (`"display"`, `x / (1 + |x|)`, as `fit` compares by default)
    by Levenberg-Marquardt with Marquardt's scaling, the Jacobian in forward mode, on the frame and target at
    `1 / factor` of their size (by default the smallest fraction with at most `SEARCH_PIXELS` pixels) through
    `effect.fit_stand_in()` (`stand_in`), as `fit`'s coarse phase draws them.

    Two descents, each a race of its starts by successive halving as `fit` races its own (every start takes
    `PROBE_STEPS` evaluations, the better half twice as many, and so on; the last goes on to `max_steps`):

    1. the light and the colours among `fields`, from each of `halo_starts` (or from `start_xy` alone, to
       refine a light known roughly): few unknowns, so a start far off still moves;
    2. when `fields` holds more than colours, the light and all of `fields`, from where the first ended, with
       the fields of the effect as the first left it and of each of `starts` (effects of `effect`'s type, their
       values clipped to the fitting ranges, as `fit` takes its starts). A light is placed where the model's
       halo matches the target's, and a model whose medium differs places it elsewhere: on the path-traced
       references `fit`'s starts for the medium brought it from tens of pixels off to a few (docs/fitting.md,
       "When the light's position is not known").

    The light moves at most `LIGHT_REACH` of the frame's larger side from its starts: off screen is allowed, and
    a light there is placed as well as its halo shows it (`LightSearch.standard_error`). Lights behind the
    camera are out of scope: the light is taken to be in front. A point light's distance is not searched:
    `light_depth` (scene units along its ray, `inf` for the sun) is held as given.

    Args:
        effect: the model drawn (its values inside their fitting ranges).
        buffers: the frame.
        target: the reference, linear `(H, W, C)` of the frame's size; the first `min(C, 3)` channels compared.
        start_xy: a first guess of the light, pixels `(x, y)`; None reads starts from the target's halo.
        fields: the fittable fields fitted beside the light (`()`: the light alone).
        starts: other effects of `effect`'s type whose `fields` start the second descent.
        light_depth: the light's distance, scene units (> 0, `inf`: the sun).
        space: `"display"` or `"linear"`.
        factor: a Python int >= 1, the search's reduction; None picks it from `SEARCH_PIXELS`.
        max_steps: a Python int >= 1, the evaluations (residuals and Jacobian) of each descent's winner at most,
            its race's included.
        stand_in: draw `effect.fit_stand_in()` (cheaper, the same fields) instead of `effect`.
        progress: None, or called after every evaluation of the residuals and Jacobian, of every start and both
            descents, with the evaluations so far and the loss at the point evaluated (which a rejected step
            raises): a search takes a minute or more on a small CPU.

    Raises:
        ValueError: naming the argument: a target of another size, a `start_xy` that is not two finite numbers,
            `fields` that are not fittable, `starts` of another type, a `factor` or `max_steps` below 1, a
            `light_depth` not > 0.
    """
    check_space(space)
    target = _checked_target(buffers, target)
    if not (isinstance(max_steps, int) and max_steps >= 1):
        raise ValueError(f"max_steps must be an int >= 1, got {max_steps!r}")
    factor = search_factor(buffers.height, buffers.width) if factor is None else factor
    if not (isinstance(factor, int) and factor >= 1):
        raise ValueError(f"factor must be an int >= 1, got {factor!r}")
    if not float(light_depth) > 0:
        raise ValueError(f"light_depth must be a distance > 0 in scene units (inf: the sun), got {light_depth!r}")
    bounds = _field_bounds(effect, colour_fields(effect) if fields is None else tuple(fields))
    names, colours = tuple(bounds), set(colour_fields(effect))
    check_inside_bounds(effect)
    lights = halo_starts(buffers, target, space=space) if start_xy is None else _checked_start(start_xy)

    def drawn_of(candidate):
        candidate = jax.tree.map(strongly_typed, candidate)
        return _reduced((candidate.fit_stand_in() if stand_in else candidate).same_on([buffers]), factor)

    drawn = drawn_of(effect)
    candidates = [drawn, *(_fields_of(drawn, drawn_of(other), bounds) for other in starts)]
    frame, reference = downsample_buffers(buffers, factor), downsample_box(target, factor)
    side = max(frame.height, frame.width)  # the light's unknowns are in frame sizes of the reduced frame
    lights = lights / factor / side
    box = (np.min(lights, axis=0) - LIGHT_REACH, np.max(lights, axis=0) + LIGHT_REACH)
    evaluations = itertools.count(1)

    def evaluated(loss):
        if progress is not None:
            progress(next(evaluations), loss)

    descend = functools.partial(
        _descend, frame=frame, reference=reference, light_depth=_static_sun(light_depth, frame.color.dtype),
        space=space, side=float(side), box=box, max_steps=max_steps, evaluated=evaluated,
    )  # fmt: skip
    first = tuple(name for name in names if name in colours)
    with jax.default_matmul_precision("highest"), ranges_guaranteed():
        kept, start = _distinct(candidates, names), 0
        search, run, light_start, steps = descend([(drawn, xy) for xy in lights], first, bounds)
        candidates[0] = drawn = search.effect_at(drawn, run.y)
        if first != names:
            search, run, best, more = descend([(candidates[index], run.y[:2]) for index in kept], names, bounds)
            start, steps = kept[best], steps + more
            drawn = search.effect_at(candidates[start], run.y)
    covariance, visible = _light_determination(run.residuals, run.jacobian, scale=side * factor)
    return LightSearch(
        light_xy=run.y[:2] * side * factor, standard_error=np.sqrt(np.diag(covariance)), covariance=covariance,
        visible_shift=visible, start_xy=lights[light_start] * side * factor, start=start,
        effect=replace_fields(effect, {name: field_value(drawn, name) for name in names}), fields=names,
        loss=run.loss, factor=factor, steps=steps,
    )  # fmt: skip


def _static_sun(light_depth, dtype):
    """The light's distance as the search's programs take it: the sun (`inf`) as a Python number, static in them, so
    that they drop the point light's branches as `fit`'s programs do (`problem.as_frames`); a point light's as an
    array, so that one program serves every distance."""
    return math.inf if math.isinf(float(light_depth)) else jnp.asarray(light_depth, dtype)


def _reduced(effect: Effect, factor: int) -> Effect:
    """`effect` drawn on a frame `factor` times smaller: its sizes in pixels scaled (`scale_pixel_fields`), and a
    reduced resolution of its own (`resolution_factor`: a march's rays, a low-resolution target) divided by `factor`,
    so that it keeps its spacing in the frame's pixels: `volumetric_haze`'s stand-in marching rays 16 pixels apart
    put the light of the path-traced `forest_low_sun` 20 pixels off, on rays 4 pixels apart 2 (docs/fitting.md,
    "When the light's position is not known")."""
    effect = scale_pixel_fields(effect, 1.0 / factor)
    own = getattr(effect, "resolution_factor", None)
    return effect if own is None else dataclasses.replace(effect, resolution_factor=max(own // factor, 1))


def _fields_of(drawn: Effect, other: Effect, bounds) -> Effect:
    """`drawn` with the fields `bounds` names taken from `other` (an effect of its type), clipped into `bounds`."""
    if type(other) is not type(drawn):
        raise ValueError(f"starts must be {type(drawn).__name__}s like the effect, got a {type(other).__name__}")
    return clip_to_bounds(replace_fields(drawn, {n: jnp.asarray(field_value(other, n)) for n in bounds}), bounds)


def _distinct(candidates: list[Effect], names: tuple[str, ...]) -> list[int]:
    """The indices of `candidates` whose fields `names` repeat no earlier one's (the effect given is often a preset)."""
    kept = []
    for index, candidate in enumerate(candidates):
        values = [np.asarray(field_value(candidate, name)) for name in names]
        if not any(
            all(np.array_equal(value, np.asarray(field_value(candidates[other], name))) for value, name in zip(values, names))
            for other in kept
        ):
            kept.append(index)
    return kept


def _descend(candidates, names, bounds, *, frame, reference, light_depth, space, side, box, max_steps, evaluated):
    """Levenberg-Marquardt over the light and the fields `names` (their `bounds`) from each of `candidates`,
    `(effect, light)` pairs (the light `(2,)` in frame sizes of `frame`): each takes `PROBE_STEPS` evaluations
    when there are several, the best then goes on to `max_steps` evaluations in all; `evaluated(loss)` after each.
    Returns the search, the best run, its index and the evaluations."""
    effect = candidates[0][0]
    shapes = tuple(np.shape(field_value(effect, name)) for name in names)
    search = _Search(names=names, bounds=tuple(bounds[n] for n in names), shapes=shapes, side=side, space=space)

    def unknowns(effect, light):
        fields = [np.ravel(to_unit(np.asarray(field_value(effect, n), np.float64), *bounds[n])) for n in names]
        return np.concatenate([np.clip(light, *box), *fields])

    def evaluator(effect):
        def evaluate(y):
            values = _residuals_and_jacobian(search, effect, frame, reference, light_depth, jnp.asarray(y, frame.color.dtype))
            residuals, jacobian = (np.asarray(value, np.float64) for value in values)
            evaluated(float(residuals @ residuals))
            return residuals, jacobian

        return evaluate

    evaluators = [evaluator(effect) for effect, _ in candidates]
    runs = [_Descent.start(each, unknowns(*candidate), *box) for each, candidate in zip(evaluators, candidates)]
    alive, budget = list(range(len(runs))), PROBE_STEPS
    while len(alive) > 1:  # successive halving, as `fit` races its starts
        for index in alive:
            runs[index].advance(evaluators[index], min(budget, max_steps))
        alive = sorted(alive, key=lambda index: runs[index].loss)[: (len(alive) + 1) // 2]
        budget *= 2
    best = alive[0]
    runs[best].advance(evaluators[best], max_steps)
    return search, runs[best], best, sum(run.steps for run in runs)


def _checked_start(start) -> np.ndarray:
    xy = np.asarray(start, np.float64)
    if xy.shape != (2,) or not np.all(np.isfinite(xy)):
        raise ValueError(f"start_xy must be a light position (x, y) in pixels, two finite numbers, got {start!r}")
    return xy[None]


def _field_bounds(effect: Effect, names: tuple[str, ...]) -> dict[str, tuple[float, float]]:
    """The fitting ranges of `names` (`fitted_bounds`), in the effect's order, or a `ValueError` naming `fields`."""
    every = parameter_bounds(effect)
    unknown = sorted(set(names) - set(every))
    if unknown:
        raise ValueError(f"fields names unknown or static field(s) {', '.join(unknown)}; fittable: {', '.join(every)}")
    return fitted_bounds(effect, fixed=[name for name in every if name not in names]) if names else {}


class _Search(eqx.Module):
    """The search's unknowns and residuals: the light in frame sizes (`side` pixels), then the fields `names` as
    `problem.from_unit` maps unknowns into their `bounds`."""

    names: tuple[str, ...] = eqx.field(static=True)
    bounds: tuple[tuple[float, float], ...] = eqx.field(static=True)
    shapes: tuple[tuple[int, ...], ...] = eqx.field(static=True)
    side: float = eqx.field(static=True)
    space: str = eqx.field(static=True)

    def values(self, y) -> list:
        """The fields' values from the unknowns `y`, in `names`' order."""
        values, offset = [], 2
        for (low, high), shape in zip(self.bounds, self.shapes):
            size = math.prod(shape)
            values.append(jnp.reshape(from_unit(y[offset : offset + size], low, high), shape))
            offset += size
        return values

    def effect_at(self, effect, y):
        """`effect` with the fields `names` set from the unknowns `y`."""
        if not self.names:
            return effect
        values = [value.astype(field_value(effect, n).dtype) for n, value in zip(self.names, self.values(y))]
        return eqx.tree_at(lambda e: [field_value(e, n) for n in self.names], effect, values)

    def residuals(self, effect, frame, reference, light_depth, y):
        """Per-value differences in `space`, scaled so that their squares sum to the mean squared error."""
        image = self.effect_at(effect, y)(frame, y[:2] * self.side, light_in_front=True, light_depth=light_depth)
        channels = min(image.shape[-1], reference.shape[-1], 3)
        difference = to_space(image[..., :channels], self.space) - to_space(reference[..., :channels], self.space)
        return jnp.ravel(difference) / math.sqrt(difference.size)


@eqx.filter_jit
def _residuals_and_jacobian(search, effect, frame, reference, light_depth, y):
    """The residuals at `y` and their Jacobian, forward mode (a handful of unknowns, thousands of residuals)."""

    def residuals(y):
        values = search.residuals(effect, frame, reference, light_depth, y)
        return values, values

    jacobian, values = jax.jacfwd(residuals, has_aux=True)(y)
    return values, jacobian


INITIAL_DAMPING = 1e-2
"""Levenberg-Marquardt's first damping, a fraction of each unknown's own curvature (Marquardt's scaling)."""

STOP_RTOL = 1e-5
"""A descent stops once an accepted step lowers the loss by less than this fraction of it."""


@dataclasses.dataclass
class _Descent:
    """One start's Levenberg-Marquardt on the host: unknowns `y` (the light's two clipped to `[low, high]`), the
    residuals and Jacobian there, its loss, damping and evaluations."""

    y: np.ndarray
    residuals: np.ndarray
    jacobian: np.ndarray
    low: np.ndarray
    high: np.ndarray
    damping: float = INITIAL_DAMPING
    steps: int = 1
    stopped: bool = False

    @classmethod
    def start(cls, evaluate, y, low, high) -> "_Descent":
        return cls(y, *evaluate(y), low=low, high=high)

    @property
    def loss(self) -> float:
        return float(self.residuals @ self.residuals)

    def advance(self, evaluate, until: int) -> None:
        """Steps until `until` evaluations in all, or until it stops."""
        while self.steps < until and not self.stopped:
            self._step(evaluate)

    def _step(self, evaluate) -> None:
        curvature, gradient = self.jacobian.T @ self.jacobian, self.jacobian.T @ self.residuals
        # Each unknown damped by its own curvature: a pixel of light and a unit of colour are not alike.
        scale = np.maximum(np.diag(curvature), 1e-12 * max(float(np.max(np.diag(curvature))), 1e-300))
        move = np.linalg.solve(curvature + self.damping * np.diag(scale), -gradient)
        y = self.y + move
        y[:2] = np.clip(y[:2], self.low, self.high)
        residuals, jacobian = evaluate(y)
        self.steps += 1
        loss = float(residuals @ residuals)
        if loss < self.loss:
            self.stopped = self.loss - loss <= STOP_RTOL * self.loss
            self.y, self.residuals, self.jacobian = y, residuals, jacobian
            self.damping /= 3.0
        else:
            self.damping *= 4.0
            self.stopped = self.damping > 1e8  # no step the model trusts lowers the loss


def _light_determination(residuals, jacobian, *, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """The light's covariance `(2, 2)` (pixels squared) and its `visible_shift` `(2,)` (pixels) from the residuals
    and Jacobian at the solution, the light's unknowns `scale` pixels each.

    The curvature of the light's unknowns with the others offsetting them (the Schur complement of the others'
    block of `J^T J`) inverted: a move `d` in x then changes the image by `d / sqrt(inv[0, 0])` RMS at best (a
    direction the image does not see is infinite). The covariance is that inverse times the residuals' variance
    (their squares' sum over the values less the unknowns, at least `QUANTISATION_VARIANCE`: a target matched
    exactly is still known only to its last 8-bit step, and a light it does not show stays undetermined) over
    their count.
    """
    count, unknowns = jacobian.shape
    curvature = jacobian.T @ jacobian
    light, others = curvature[:2, :2], curvature[:2, 2:]
    schur = light - others @ np.linalg.pinv(curvature[2:, 2:]) @ others.T if unknowns > 2 else light
    eigenvalues, vectors = np.linalg.eigh(schur)
    with np.errstate(divide="ignore", over="ignore"):
        inverse = (vectors / np.maximum(eigenvalues, np.finfo(np.float64).tiny)) @ vectors.T * scale**2
        # The residuals are scaled by 1 / sqrt(count) (their squares sum to the mean), so is the variance.
        variance = max(count * float(residuals @ residuals) / max(count - unknowns, 1), QUANTISATION_VARIANCE)
        return inverse * variance / count, VISIBLE_CHANGE * np.sqrt(np.diag(inverse))
