"""The light placed by whole fits around it: the loss a fit reaches at each light tried, lowest where the light is.

`find_light` fits the light beside a few of the effect's fields at a reduced resolution; its light lies where
those fields, not the whole medium, match the target best, and a medium fitted there keeps it (a medium traded
against a light lower on screen stays a local minimum of the two together). The loss `fit` reaches with every
field refitted, as a function of the light, is lowest near the light the target was drawn with, but each fit
stops where its own stopping rule says, so that function is noisy on the scale of a few pixels
(benchmarks/README.md, "Finding the light"). `profile_light` walks it along y, then x, with a few fits each
(where a side is lower it moves there), and goes to the minimum of a quadratic in x and y fitted by least squares
to the losses near the lowest; then the same again at a third of the step. How well the fits place it is how far
it moves before a whole fit's loss rises visibly (`LightProfile.visible_shift`).
"""

import dataclasses
from collections.abc import Callable

import numpy as np
from jaxtyping import ArrayLike, Float

PROFILE_STEP = 0.03
"""The first round's step, a fraction of the frame's larger side: about the distance `find_light`'s light lies from
the one drawn (benchmarks/README.md, "Finding the light")."""

PROFILE_ROUNDS = 2
"""Rounds along both axes, each at a third of the step before it."""

MAX_MOVES = 3
"""The most steps an axis moves in a round while one side is lower, before it takes the parabola's vertex."""


@dataclasses.dataclass(frozen=True)
class LightProfile:
    """What `profile_light` returns; positions in pixels of the frame (x right, y down, pixel centres at `i + 0.5`).

    Attributes:
        light_xy: `(2,)` the light placed.
        tried: `(N, 2)` every light a fit was run at, in order.
        losses: `(N,)` the loss each of those fits reached.
        visible_shift: `(2,)` the move in x (in y) that raises a whole fit's loss by `visible_rise`, pixels: the
            curvature of a quadratic fitted to the losses of the lights tried within the first round's step of
            `light_xy`. `inf` where they do not rise that much within the step along that axis (the frames do
            not place the light along it), `nan` where it was not measured (no `visible_rise`, or fewer than six such fits).
    """

    light_xy: np.ndarray
    tried: np.ndarray
    losses: np.ndarray
    visible_shift: np.ndarray


def profile_light(
    fitted_loss: Callable[[np.ndarray], float],
    start_xy: Float[ArrayLike, "2"],
    *,
    step: float,
    rounds: int = PROFILE_ROUNDS,
    max_moves: int = MAX_MOVES,
    visible_rise: float | None = None,
) -> LightProfile:
    """The light near `start_xy` (pixels) whose fit reaches the lowest loss, from the losses `fitted_loss(xy)` of a
    few fits: at most three per axis and round (the light and a step either side, each light fitted once), and one
    per move.

    Along y, then x, in each round: the loss at the light and `step` pixels either side; while a side is lower,
    the light moves there (at most `max_moves` times, the next point a step beyond); then it goes to the vertex of
    the parabola through the three, which lies within a step of the middle one. After both axes the light goes to
    the minimum of `a + b x + c y + d x^2 + e y^2` fitted by least squares to the losses within the round's step
    of the lowest in x and in y (where that quadratic has one within a step of the lowest; else the lowest's
    coordinate): one fit's loss is noisy on the scale of a few pixels. Each next round's step is a third of the
    one before. A loss that is not finite counts as higher than any other.

    `visible_rise`: the rise of a fit's loss taken as visible, for `LightProfile.visible_shift` (for the MSE, the
    square of the RMS change of the fitted frame: a fit at a light that far off can do no better than a frame
    that much unlike the one at the light placed); None leaves it unmeasured.

    Raises:
        ValueError: `step` not positive, `rounds` or `max_moves` not a non-negative int, `start_xy` not two finite
            numbers, `visible_rise` not positive.
    """
    if not (isinstance(step, (int, float)) and step > 0):
        raise ValueError(f"step must be > 0 pixels, got {step!r}")
    for name, value in (("rounds", rounds), ("max_moves", max_moves)):
        if not (isinstance(value, int) and value >= 0):
            raise ValueError(f"{name} must be an int >= 0, got {value!r}")
    if visible_rise is not None and not (isinstance(visible_rise, (int, float)) and visible_rise > 0):
        raise ValueError(f"visible_rise must be > 0 or None, got {visible_rise!r}")
    light = np.asarray(start_xy, np.float64)
    if light.shape != (2,) or not np.all(np.isfinite(light)):
        raise ValueError(f"start_xy must be two finite numbers (x, y) in pixels, got {start_xy!r}")
    tried, losses = [], []

    def loss_at(xy):
        for earlier, loss in zip(tried, losses):
            if np.array_equal(earlier, xy):
                return loss
        loss = float(fitted_loss(xy.copy()))
        tried.append(xy.copy())
        losses.append(loss if np.isfinite(loss) else np.inf)
        return losses[-1]

    for round_index in range(rounds):
        size = step / 3**round_index
        for axis in (1, 0):
            along = np.zeros(2)
            along[axis] = size
            middle = loss_at(light)
            below, above = loss_at(light - along), loss_at(light + along)
            for _ in range(max_moves):
                if min(below, above) >= middle:
                    break
                if below < above:
                    light, above, middle = light - along, middle, below
                    below = loss_at(light - along)
                else:
                    light, below, middle = light + along, middle, above
                    above = loss_at(light + along)
            light = light + along * _vertex(below, middle, above)
        light = _quadratic_minimum(np.asarray(tried), np.asarray(losses), size)
    tried, losses = np.asarray(tried).reshape(-1, 2), np.asarray(losses)
    shift = np.full(2, np.nan) if visible_rise is None else _visible_shift(tried, losses, light, step, visible_rise)
    return LightProfile(light, tried, losses, shift)


def _quadratic(tried: np.ndarray, losses: np.ndarray, centre: np.ndarray, size: float, least: int):
    """The coefficients of `a + b x + c y + d x^2 + e y^2` (`x`, `y` in units of `size` from `centre`) fitted by least
    squares to the finite losses of the lights tried within `size` of `centre` in x and in y; None with fewer than
    `least` of them."""
    offsets = (tried - centre) / size
    near = np.isfinite(losses) & np.all(np.abs(offsets) <= 1.0 + 1e-9, axis=1)
    if near.sum() < least:
        return None
    dx, dy = offsets[near].T
    design = np.stack([np.ones_like(dx), dx, dy, dx * dx, dy * dy], axis=1)
    return np.linalg.lstsq(design, losses[near], rcond=None)[0]


def _visible_shift(tried: np.ndarray, losses: np.ndarray, light: np.ndarray, size: float, rise: float) -> np.ndarray:
    """`LightProfile.visible_shift`: from the curvature of the quadratic of the losses within `size` of `light`
    along each axis (six fits at least, one more than its coefficients, so that their noise shows); `inf` beyond
    `size`, where no fit measured it."""
    coefficients = _quadratic(tried, losses, light, size, least=6)
    if coefficients is None:
        return np.full(2, np.nan)
    curvature = coefficients[3:] / size**2  # loss per pixel squared
    with np.errstate(divide="ignore"):
        shift = np.sqrt(rise / np.maximum(curvature, 0.0))
    return np.where(shift <= size, shift, np.inf)


def _quadratic_minimum(tried: np.ndarray, losses: np.ndarray, size: float) -> np.ndarray:
    """The minimum of `a + b x + c y + d x^2 + e y^2` fitted by least squares to the losses of the lights tried
    within `size` (a step) of the lowest in x and in y: the noise of single fits averaged out. An axis whose
    quadratic has no minimum within a step of the lowest keeps the lowest's coordinate."""
    finite = np.isfinite(losses)
    best = tried[finite][np.argmin(losses[finite])] if np.any(finite) else tried[0]
    coefficients = _quadratic(tried, losses, best, size, least=5)
    if coefficients is None:
        return best
    light = best.astype(np.float64).copy()
    for axis, (slope, curvature) in enumerate([(coefficients[1], coefficients[3]), (coefficients[2], coefficients[4])]):
        if curvature > 0 and abs(slope / (2.0 * curvature)) <= 1.0:
            light[axis] += -slope / (2.0 * curvature) * size
    return light


def _vertex(below: float, middle: float, above: float) -> float:
    """Where the parabola through `(-1, below), (0, middle), (1, above)` is lowest, within [-1, 1]; the lowest of the
    three where it has no minimum there (or a loss is not finite), the middle one on a tie."""
    curvature = below - 2.0 * middle + above
    if np.isfinite(curvature) and curvature > 0:
        return float(np.clip(0.5 * (below - above) / curvature, -1.0, 1.0))
    return float((0.0, -1.0, 1.0)[int(np.argmin([middle, below, above]))])
