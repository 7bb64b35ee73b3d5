"""What a fit solves: the fitted fields' bounds, the frames normalised, the unknowns mapped into the bounds, the
residuals and the loss; `fit` and `determination` share it."""

import dataclasses
import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from godrays_jax.effects.base import Effect
from godrays_jax.effects.fields import field_metadata, field_value, parameter_bounds
from godrays_jax.effects.lights import Light, lit_by
from godrays_jax.kernels.losses import LOSSES, to_space
from godrays_jax.primitives.buffers import Buffers


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
            high = min(high, float(field_value(effect, infos[name].cap)))
        result[name] = (float(low), float(high))
    if not result:
        raise ValueError("fixed leaves no parameter to fit")
    return result


FOLD_ROUNDING = 0.02
"""Half-width, in unknowns' units, of the rounded turn where the map from unknowns to values folds at a bound.

A fold with a corner (the triangle wave) has no derivative on the bound: a field whose best value is its bound
(`height_falloff` 0 for a haze that does not thin with height) then jumps from side to side of the corner every
step, and Levenberg-Marquardt's trust region shrinks to that zig-zag for every other unknown too, so the fit
crawls (`docs/findings.md`, "A fold without a corner"). Rounded, the map is smooth and its slope goes to 0 on
the bound, where the loss is then quadratic in the unknown, as the solver's model assumes."""

START_INSET = FOLD_ROUNDING / 4
"""How far inside its range a start on a bound is moved, in unknowns' units: on the bound itself the map has
no slope and the field could not move; here it has a quarter of its slope, and its value moves by about
`FOLD_ROUNDING / 32` of its range."""


def _rounded_fold(unit):
    """[0, 1] -> [0, 1]: linear inside, parabolas within `FOLD_ROUNDING` of each end (slope 0 on the ends)."""
    rounding, slope = FOLD_ROUNDING, 1.0 / (1.0 - FOLD_ROUNDING)
    near_low = slope * unit**2 / (2.0 * rounding)
    near_high = 1.0 - slope * (1.0 - unit) ** 2 / (2.0 * rounding)
    inside = slope * (unit - rounding / 2.0)
    return jnp.where(unit < rounding, near_low, jnp.where(unit > 1.0 - rounding, near_high, inside))


def to_unit(value, low, high):
    """The unknown whose `from_unit` is `value` (in `[low, high]`), in `[0, 1]`; a bound maps to 0 or 1."""
    return _unfolded((value - low) / (high - low), jnp)


def _unfolded(position, xp):
    """`_rounded_fold`'s inverse on `[0, 1]`, in the array module `xp` (`jnp`, or `np` for the host's float64)."""
    rounding, slope = FOLD_ROUNDING, 1.0 / (1.0 - FOLD_ROUNDING)
    edge = slope * rounding / 2.0  # the position where the parabola meets the line
    near_low = xp.sqrt(xp.maximum(2.0 * rounding * position / slope, 0.0))
    near_high = 1.0 - xp.sqrt(xp.maximum(2.0 * rounding * (1.0 - position) / slope, 0.0))
    inside = position / slope + rounding / 2.0
    return xp.where(position < edge, near_low, xp.where(position > 1.0 - edge, near_high, inside))


def warp_of(effect: Effect | type[Effect], name: str) -> float:
    """Field `name`'s warp where it is moved by ratios (`folded_positions`): its `FieldInfo.decades` in natural-log
    units, 0 for a field moved by differences alone."""
    return field_metadata(effect)[name].decades * math.log(10.0)


def folded_positions(unit: np.ndarray, warps: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """`from_unit`'s map of the unknowns to positions in their ranges (0 on the lower bound, 1 on the upper) and its
    slope, in NumPy float64: for the solver that runs on the host (`marquardt`). `warps` (`FitProblem.warps`, per
    unknown): the map by ratios, each position `t` spread over the range as `expm1(warp t) / expm1(warp)`, where
    equal steps scale the value by equal ratios over the top `warp / ln 10` decades (a warp of 0: as without)."""
    folded = np.mod(np.asarray(unit, np.float64), 2.0)
    mirrored = folded > 1.0
    inside = np.where(mirrored, 2.0 - folded, folded)
    rounding, slope = FOLD_ROUNDING, 1.0 / (1.0 - FOLD_ROUNDING)
    near_low, near_high = inside < rounding, inside > 1.0 - rounding
    position = np.where(
        near_low, slope * inside**2 / (2.0 * rounding),
        np.where(near_high, 1.0 - slope * (1.0 - inside) ** 2 / (2.0 * rounding), slope * (inside - rounding / 2.0)),
    )  # fmt: skip
    gradient = np.where(near_low, slope * inside / rounding, np.where(near_high, slope * (1.0 - inside) / rounding, slope))
    if warps is not None and np.any(warps):
        warp = np.where(warps > 0, warps, 1.0)  # a warp of 0 is the identity: any other value, then not taken
        gradient = gradient * np.where(warps > 0, warp * np.exp(warp * position) / np.expm1(warp), 1.0)
        position = np.where(warps > 0, np.expm1(warp * position) / np.expm1(warp), position)
    return position, np.where(mirrored, -gradient, gradient)


def warped_start(unit: np.ndarray, warps: np.ndarray, *, inset: bool = True) -> np.ndarray:
    """The unknowns of `folded_positions` by `warps` at the positions of the unknowns `unit` (`start_point`'s, of the
    map without warps; the unknowns without a warp as they are), in float64, so that both maps start at the same
    positions to float32's last bit; a start on a bound `START_INSET` inside it (`inset`), as `start_point`'s."""
    warp = np.where(warps > 0, warps, 1.0)
    positions = folded_positions(unit)[0]
    along = _unfolded(np.log1p(positions * np.expm1(warp)) / warp, np)
    low_end = START_INSET if inset else 0.0
    return np.where(warps > 0, np.clip(along, low_end, 1.0 - low_end), unit)


def _linear(position, low, high):
    return low + (high - low) * position


def from_unit(unit, low, high):
    """Any real unknown -> a value in `[low, high]`: `_rounded_fold` of the unknown folded into `[0, 1]` (period 2,
    mirrored), so every unknown is in range and the map is smooth everywhere."""
    folded = jnp.mod(unit, 2.0)
    return low + (high - low) * _rounded_fold(jnp.where(folded <= 1.0, folded, 2.0 - folded))


def _per_frame(value, count, name):
    """One value per frame from a scalar (or bool) or a sequence of `count`."""
    values = [value] * count if isinstance(value, bool) or np.ndim(value) == 0 else list(value)
    if len(values) != count:
        raise ValueError(f"{name} must be one value or one per frame ({count})")
    return values


def as_frames(buffers, light_xy, target, light_in_front, light_depth=math.inf, other_lights=()):
    """Normalise one frame or a sequence of frames into equal-length lists: `(frames, lights, targets, in_front,
    depths, others)`, `others` each frame's lights beside its first (`effects.lights.Light`s, checked)."""
    if isinstance(buffers, Buffers):
        buffers, light_xy, target, light_in_front = [buffers], [light_xy], [target], [light_in_front]
        light_depth, other_lights = [light_depth], [other_lights]
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
        other_lights = list(other_lights) or [()] * count
        if len(other_lights) != count:
            raise ValueError(
                f"other_lights must hold one sequence of Light per frame ({count}), got {len(other_lights)}"
            )  # fmt: skip
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
        # The sun as a Python number: static in every compiled program, which then drops the point light's branches
        # (`kernels.bounded_medium.light_geometry`), as `apply`'s render does.
        depths.append(math.inf if np.isinf(depth) else jnp.asarray(np.asarray(depth, frame.color.dtype)))
    others = [_other_lights(frame_lights, frame.color.dtype, index) for index, (frame, frame_lights)
              in enumerate(zip(buffers, other_lights))]  # fmt: skip
    # Python bools: static in every compiled program, so an effect that reads the light's side (the shadows read
    # along lines, outward from a light in front, inward from one behind) compiles the side it has alone.
    return buffers, lights, targets, [bool(np.asarray(flag)) for flag in light_in_front], depths, others


def _other_lights(lights, dtype, frame: int) -> tuple[Light, ...]:
    """A frame's lights beside its first, as compiled programs take them: position, distance and tint arrays of
    the frame's dtype, the side a Python bool (static, as the first light's)."""
    if isinstance(lights, Light) or not all(isinstance(light, Light) for light in lights):
        raise ValueError(f"other_lights[{frame}] must be a sequence of Light, got {lights!r}")
    checked = []
    for index, light in enumerate(lights):
        name = f"other_lights[{frame}][{index}]"
        xy, depth = np.asarray(light.xy, np.float64), np.asarray(light.depth, np.float64)
        tint = np.broadcast_to(np.asarray(light.tint, np.float64), (3,))
        if xy.shape != (2,) or not np.isfinite(xy).all():
            raise ValueError(f"{name}.xy must be a finite (x, y) in pixels, got {light.xy!r}")
        if depth.shape != () or not depth > 0:
            raise ValueError(f"{name}.depth must be a distance > 0 in scene units (inf: the sun), got {light.depth!r}")
        if not (np.isfinite(tint).all() and (tint >= 0).all()):
            raise ValueError(f"{name}.tint must be finite and >= 0 (linear RGB), got {light.tint!r}")
        xy, depth, tint = (jnp.asarray(value.astype(dtype)) for value in (xy, depth, tint))
        checked.append(Light(xy=xy, in_front=bool(np.asarray(light.in_front)), depth=depth, tint=tint))
    return tuple(checked)


def drawn(effect: Effect, frame: Buffers, light_xy, light_in_front: bool, light_depth, others=()):
    """A fit's frame: `effect` under its light, and under `others` beside it their light added (`lit_by`); one
    light is the effect's own call, whose program a fit of one light has always compiled."""
    if others:
        return lit_by(effect, frame, [Light(light_xy, light_in_front, light_depth), *others])
    return effect(frame, light_xy, light_in_front=light_in_front, light_depth=light_depth)


def _match_channels(image, target):
    channels = min(image.shape[-1], target.shape[-1], 3)
    return image[..., :channels], target[..., :channels]


def with_frames_read_once(effect, frame_data, fitted) -> tuple:
    """`frame_data` with what `effect` reads off its frames alone read beforehand (`Effect.frames_read_once`, with
    the field names `fitted`): a fit's programs then take it as data, not read again in every step."""
    return (effect.frames_read_once(frame_data[0], fitted=tuple(fitted)), *frame_data[1:])


def light_tints(frame_data) -> jax.Array | None:
    """The tints of the lights beside each frame's first (`as_frames`' `others`), `(K, 3)`, the first frame's (a fit
    shares them over its frames); None where the frames have no other light."""
    others = frame_data[5][0]
    return jnp.stack([jnp.asarray(light.tint) for light in others]) if others else None


def with_light_tints(frame_data, tints) -> tuple:
    """`frame_data` with the `k`-th light beside every frame's first tinted `tints[k]`."""
    others = [
        tuple(dataclasses.replace(light, tint=tint) for light, tint in zip(beside, tints)) for beside in frame_data[5]
    ]
    return (*frame_data[:5], others)


TINT_RANGE = 8.0
"""The fitted tints' upper bound, in units of the largest tint they start from (and at least this): a light's
tint over the first's, which the fit moves from the tint given."""


def tint_range(light_tints) -> float:
    """The upper bound of fitted tints that start at `light_tints` (`TINT_RANGE` times the largest, at least)."""
    return TINT_RANGE * max(1.0, float(np.max(light_tints))) if light_tints is not None else TINT_RANGE


class FitProblem(eqx.Module):
    """What a fit's objective needs besides the unknowns; static fields make compilations reusable.

    Every field but `effect`, `light_tints` and `tint_high` is static and hashable, and the objective
    functions below are module-level, so two fits of the same effect type,
    fitted names, frame sizes and options reuse one compiled solver step.

    `light_tints`, where not None, are fitted too: the tints of the lights beside each frame's first (`(K, 3)`,
    shared by every frame, their start), unknowns after the fields' in `[0, tint_high]`, in the effect's
    `LIGHT_TINT_STAGE`; the frames then render with the tints the unknowns give (`frames_at`).
    """

    effect: Effect
    names: tuple[str, ...] = eqx.field(static=True)
    bounds: tuple[tuple[float, float], ...] = eqx.field(static=True)
    shapes: tuple[tuple[int, ...], ...] = eqx.field(static=True)
    frame_weights: tuple[float, ...] = eqx.field(static=True)
    loss: str = eqx.field(static=True)
    space: str = eqx.field(static=True)
    stages: tuple[str, ...] = eqx.field(static=True)
    light_tints: jax.Array | None = None
    tint_high: jax.Array | None = None  # an argument of the compiled programs, not a constant: any bound shares them

    @classmethod
    def of(
        cls, effect: Effect, bounds: dict[str, tuple[float, float]], frames, *, loss: str, space: str,
        light_tints: jax.Array | None = None, tint_high: float | None = None,
    ):  # fmt: skip
        """The problem of fitting `bounds`' fields of `effect` (and `light_tints`, where given, in `[0, tint_high]`:
        by default `TINT_RANGE` times the largest of them, and at least that) to `frames`, each frame weighted by
        its pixel count."""
        total_pixels = sum(frame.height * frame.width for frame in frames)
        if light_tints is not None:
            tint_high = jnp.asarray(tint_range(light_tints) if tint_high is None else tint_high, light_tints.dtype)
        return cls(
            effect=effect,
            names=tuple(bounds),
            bounds=tuple(bounds.values()),
            shapes=tuple(tuple(np.shape(field_value(effect, name))) for name in bounds),
            frame_weights=tuple(frame.height * frame.width / total_pixels for frame in frames),
            loss=loss,
            space=space,
            stages=tuple(type(effect).FIELD_STAGES.get(name, "") for name in bounds),
            light_tints=light_tints,
            tint_high=None if light_tints is None else tint_high,
        )

    @property
    def blocks(self) -> list[tuple[tuple[float, float], tuple[int, ...], str]]:
        """Each block of unknowns' bounds, shape and stage: the fields', then the tints' where they are fitted."""
        blocks = list(zip(self.bounds, self.shapes, self.stages))
        if self.light_tints is not None:
            blocks.append(((0.0, self.tint_high), tuple(self.light_tints.shape), type(self.effect).LIGHT_TINT_STAGE))
        return blocks

    @property
    def warps(self) -> np.ndarray:
        """Each unknown's warp where the fields are moved by ratios (`warp_of`; the tints' 0), in order."""
        warps = [warp_of(self.effect, name) for name in self.names] + [0.0]
        return np.concatenate([np.full(math.prod(shape), warp) for warp, (_, shape, _) in zip(warps, self.blocks)])

    @property
    def group_stages(self) -> tuple[str, ...]:
        """The stage of each of `lane_groups`, in its order."""
        return tuple(dict.fromkeys(stage for _, _, stage in self.blocks))

    @property
    def differenced_groups(self) -> tuple[int, ...]:
        """The positions in `lane_groups` of the groups whose columns are differences (`Effect.DIFFERENCED_STAGES`)."""
        differenced = type(self.effect).DIFFERENCED_STAGES
        return tuple(index for index, stage in enumerate(self.group_stages) if stage in differenced)

    def unknowns_of(self, names) -> tuple[int, ...]:
        """The indices of the unknowns of the fitted fields among `names`, in order."""
        offsets = np.cumsum([0, *(math.prod(shape) for _, shape, _ in self.blocks)])
        return tuple(i for k, name in enumerate(self.names) if name in names for i in range(offsets[k], offsets[k + 1]))

    def stage_unknowns(self, stages) -> tuple[int, ...]:
        """The indices of the unknowns whose fields belong to `stages`, in order."""
        chosen = (group for group, stage in zip(self.lane_groups, self.group_stages) if stage in stages)
        return tuple(sorted(index for group in chosen for index in group))

    @property
    def lane_groups(self) -> tuple[tuple[int, ...], ...]:
        """The unknowns' indices grouped by their fields' stage (`Effect.FIELD_STAGES`), in order of first appearance."""
        groups, offset = {}, 0
        for _, shape, stage in self.blocks:
            size = math.prod(shape)
            groups.setdefault(stage, []).extend(range(offset, offset + size))
            offset += size
        return tuple(tuple(group) for group in groups.values())

    def effect_of_groups(self, vectors, *, positions: bool = False):
        """`effect_at` of the unknowns given as one vector per group of `lane_groups`, in its order (a field's
        value then carries a derivative only where its own group's vector does); `positions`: the vectors hold
        positions in the fields' ranges (`effect_at_positions`) instead."""
        return self._effect_of(self._in_order(vectors), to_value=_linear if positions else from_unit)

    def frames_of_groups(self, vectors, frame_data, *, positions: bool = False):
        """`frame_data` with the lights' tints the unknowns give (`frames_at`), from one vector per group."""
        return self._frames_of(self._in_order(vectors), frame_data, to_value=_linear if positions else from_unit)

    def _in_order(self, vectors):
        """The unknowns in order from one vector per group of `lane_groups` (a list of scalars where several)."""
        if len(vectors) == 1:  # one stage: the unknowns in order
            return vectors[0]
        unknowns = {}
        for vector, group in zip(vectors, self.lane_groups):
            unknowns |= {index: vector[position] for position, index in enumerate(group)}
        return [unknowns[index] for index in range(len(unknowns))]

    def effect_at(self, y):
        """The effect with the fitted fields set from the flat unit-scaled unknowns `y`."""
        return self._effect_of(y)

    def frames_at(self, y, frame_data):
        """`frame_data` with the fitted tints from the flat unit-scaled unknowns `y` (as given without them)."""
        return self._frames_of(y, frame_data)

    def frames_at_positions(self, positions, frame_data):
        """`frame_data` with the fitted tints at `positions` in their range (`effect_at_positions`'s map)."""
        return self._frames_of(positions, frame_data, to_value=_linear)

    def start_values(self, dtype) -> list:
        """The fitted fields' values in the effect, then the tints' where they are fitted: one array per block."""
        values = [jnp.asarray(field_value(self.effect, name), dtype) for name in self.names]
        return values if self.light_tints is None else [*values, jnp.asarray(self.light_tints, dtype)]

    def positions(self, dtype):
        """Where the effect's fitted values (then the tints) sit in their ranges, flat: 0 on the lower bound, 1 on
        the upper."""
        return jnp.concatenate([jnp.ravel((value - low) / (high - low)) for value, ((low, high), _, _) in
                                zip(self.start_values(dtype), self.blocks)])  # fmt: skip

    def effect_at_positions(self, positions):
        """The effect with each fitted field at `low + (high - low) * position`, linear and unfolded: derivatives
        in `positions` are per unit of each field's range, whatever the solver's map (`determination`'s)."""
        return self._effect_of(positions, to_value=_linear)

    def _effect_of(self, unknowns, to_value=from_unit):
        """The effect from the unknowns: a flat array or a list of scalars, in `names`' order."""
        values, offset = [], 0
        for name, (low, high), shape in zip(self.names, self.bounds, self.shapes):
            size = math.prod(shape)
            piece = unknowns[offset : offset + size]
            unit = jnp.reshape(piece if isinstance(piece, jax.Array) else jnp.stack(piece), shape)
            values.append(to_value(unit, low, high).astype(field_value(self.effect, name).dtype))
            offset += size
        return eqx.tree_at(lambda e: [field_value(e, n) for n in self.names], self.effect, values)

    def _tints_of(self, unknowns, to_value):
        """The fitted tints from the unknowns (a flat array or a list of scalars), after the fields'."""
        start = sum(math.prod(shape) for shape in self.shapes)
        piece = unknowns[start:]
        unit = jnp.reshape(piece if isinstance(piece, jax.Array) else jnp.stack(piece), self.light_tints.shape)
        return to_value(unit, 0.0, self.tint_high).astype(self.light_tints.dtype)

    def _frames_of(self, unknowns, frame_data, to_value=from_unit):
        if self.light_tints is None:
            return frame_data
        return with_light_tints(frame_data, self._tints_of(unknowns, to_value))

    def rendered(self, candidate, frame_data):
        for frame, light, image, front, depth, others in zip(*frame_data):
            yield _match_channels(drawn(candidate, frame, light, front, depth, others), image)

    def residuals(self, y, frame_data):
        return self.residuals_of(self.effect_at(y), self.frames_at(y, frame_data))

    def residuals_of(self, candidate, frame_data):
        return self.residuals_of_images([image for image, _ in self.rendered(candidate, frame_data)], frame_data)

    def residuals_of_images(self, images, frame_data):
        """The residuals of rendered frames `images` (one per frame) against the frames' targets."""
        pairs = (_match_channels(image, reference) for image, reference in zip(images, frame_data[2]))
        parts = [
            jnp.ravel(to_space(image, self.space) - to_space(reference, self.space)) * math.sqrt(weight / reference.size)
            for (image, reference), weight in zip(pairs, self.frame_weights)
        ]
        return jnp.concatenate(parts)

    def objective(self, candidate, frame_data):
        return self.objective_of_images([image for image, _ in self.rendered(candidate, frame_data)], frame_data)

    def objective_of_images(self, images, frame_data):
        """The loss of rendered frames `images` (one per frame) against the frames' targets."""
        pairs = (_match_channels(image, reference) for image, reference in zip(images, frame_data[2]))
        return sum(
            weight * LOSSES[self.loss](image, reference, space=self.space)
            for (image, reference), weight in zip(pairs, self.frame_weights)
        )


def check_inside_bounds(effect: Effect) -> None:
    """`ValueError` naming the first fittable field outside its fitting range (`fitted_bounds`)."""
    for name, (low, high) in fitted_bounds(effect).items():
        value = np.asarray(field_value(effect, name))
        if not np.all((value >= low) & (value <= high)):
            raise ValueError(f"effect.{name} = {value.tolist()} lies outside its fitting range [{low:g}, {high:g}]")


@eqx.filter_jit
def start_point(problem, dtype, *, inset: bool = True):
    """The flat unknowns of the starting effect (then tints); a value on a bound starts `START_INSET` inside it
    (`inset`; else on the bound, where the fold's slope is 0 and a solver cannot move it)."""
    low_end = START_INSET if inset else 0.0
    return jnp.concatenate([
        jnp.ravel(jnp.clip(to_unit(value, low, high), low_end, 1.0 - low_end))
        for value, ((low, high), _, _) in zip(problem.start_values(dtype), problem.blocks)
    ])  # fmt: skip


def strongly_typed(leaf):
    """A weakly typed array (`jnp.asarray(0.5)`) as a strongly typed one, a NumPy value (`np.float32(50.0)`) as a JAX
    array; converted on the host (no compilation). So every compiled program takes the effect's fields as arguments:
    a NumPy value would be a constant of the program, which then differs wherever it does."""
    if isinstance(leaf, jax.Array) and leaf.weak_type or isinstance(leaf, (np.ndarray, np.generic)):
        return jax.device_put(np.asarray(leaf))
    return leaf
