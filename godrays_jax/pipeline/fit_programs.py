"""The compiled programs a fit runs, each stored traced (`exported`): the residuals and their Jacobian by stages
(`residuals_and_jacobian`, all that Levenberg-Marquardt on the host and `determination` run), an effect's own
residuals and loss from its frames rendered as `apply` renders them (whose central differences give the polish its
sharp fields' columns at full resolution, `rendered_differences`), and optimistix's first state and step for the
other solvers (the objective's Jacobian by forward mode, `forward_mode`)."""

import dataclasses
import math
from collections.abc import Callable
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from godrays_jax.effects.base import Effect
from godrays_jax.pipeline import exported
from godrays_jax.pipeline.compiled import render_compiled
from godrays_jax.pipeline.marquardt import normal_equations
from godrays_jax.pipeline.problem import FitProblem, folded_positions
from godrays_jax.pipeline.reduced import pixel_fields
from godrays_jax.primitives.derivatives import values_only

DIFFERENCE_STEP = 3e-4
"""The step of a column by central differences (`differenced_columns`, `rendered_differences`), in its field's range:
small against the fields' effects, which float32 renders still resolve (benchmarks/README.md, "VolumetricFog against
the path-traced references"). Within a step of a bound the difference is one-sided there, so that no render is asked
for a value outside the range."""


def forward_mode(function, groups=None, differenced=()):
    """`function(y)` (flat `y`) whose JVP is a precomputed forward-mode Jacobian times the tangent.

    optimistix linearises the objective; linearising the kernels' sample loops
    directly would store every iteration. Here the Jacobian is computed with
    one vectorised `jax.jvp` per parameter (memory O(output x parameters)) and
    the linearisation only keeps that Jacobian.

    `groups`, a partition of `y`'s indices (`FitProblem.lane_groups`): `function` then takes one vector per group
    (`y` at its indices) and each group's columns are a vectorised JVP of their own, in which the other groups'
    unknowns are constants. A group's lanes then run only through the operations its unknowns reach, where one
    vectorised JVP of all carries every lane through every operation that any of them reaches. The groups at the
    positions `differenced` take their columns by central differences instead (`differenced_columns`).
    """
    indices = None if groups is None else [np.asarray(group) for group in groups]

    def split(y):
        return (y,) if indices is None else [y[index] for index in indices]

    @jax.custom_jvp
    def wrapped(y):
        return function(*split(y))

    @wrapped.defjvp
    def wrapped_jvp(primals, tangents):
        (y,), (tangent,) = primals, tangents
        vectors, product = split(y), 0.0
        for position, vector in enumerate(vectors):

            def along(own, position=position):
                return function(*vectors[:position], own, *vectors[position + 1 :])

            if position in differenced:
                jacobian = differenced_columns(along, vector)
            else:
                basis = jnp.eye(vector.shape[0], dtype=y.dtype)
                value, jacobian = jax.vmap(lambda direction: jax.jvp(along, (vector,), (direction,)), out_axes=(None, -1))(basis)
            own_tangent = tangent if indices is None else tangent[indices[position]]
            product = product + jnp.matmul(jacobian, own_tangent, precision="highest")
        if len(differenced) == len(vectors):  # every column differenced
            with values_only():
                value = function(*vectors)
        return value, product

    return wrapped


def differenced_columns(function, vector, *, positions: bool = False):
    """The columns of `function`'s Jacobian in `vector` by central differences (`DIFFERENCE_STEP`), of renders traced
    without derivatives (`values_only`): two renders a column, each in a frame's memory. `positions`: `vector` holds
    positions in the fields' ranges, [0, 1], kept there; else unknowns that the fit's fold maps into them."""
    columns = []
    for direction in jnp.eye(vector.shape[0], dtype=vector.dtype):
        upper, lower = vector + DIFFERENCE_STEP * direction, vector - DIFFERENCE_STEP * direction
        if positions:
            upper, lower = jnp.minimum(upper, 1.0), jnp.maximum(lower, 0.0)
        with values_only():
            change = function(upper) - function(lower)
        columns.append(change / jnp.sum((upper - lower) * direction))
    return jnp.stack(columns, axis=-1)


def residual_function(y, data):
    problem, frame_data = data
    def residuals(*vectors):
        return problem.residuals_of(problem.effect_of_groups(vectors), problem.frames_of_groups(vectors, frame_data))

    return forward_mode(residuals, problem.lane_groups, problem.differenced_groups)(y), None


def objective_function(y, data):
    problem, frame_data = data
    def objective(*vectors):
        return problem.objective(problem.effect_of_groups(vectors), problem.frames_of_groups(vectors, frame_data))

    return forward_mode(objective, problem.lane_groups, problem.differenced_groups)(y), None


@eqx.filter_jit
def residuals_and_jacobian(problem: FitProblem, positions, frame_data):
    """The residuals at the fitted fields' `positions` in their ranges (`FitProblem.effect_at_positions`) and their
    Jacobian in those positions, `(residuals, unknowns)`: one vectorised JVP per stage of the effect
    (`FitProblem.lane_groups`), so that a stage's lanes run only through the operations its fields reach, and the
    columns of `Effect.DIFFERENCED_STAGES` by central differences (`DIFFERENCE_STEP`) of renders without derivatives.

    The one compiled program of a fit by Levenberg-Marquardt (`marquardt`) and of `determination`.
    """
    groups = [np.asarray(group) for group in problem.lane_groups]
    vectors = [positions[group] for group in groups]
    residuals, columns = None, []
    for index in range(len(groups)):
        vector = vectors[index]

        def along(own, index=index):
            groups_now = [*vectors[:index], own, *vectors[index + 1 :]]
            frames_now = problem.frames_of_groups(groups_now, frame_data, positions=True)
            return problem.residuals_of(problem.effect_of_groups(groups_now, positions=True), frames_now)

        if index in problem.differenced_groups:
            columns.append(differenced_columns(along, vector, positions=True))
            continue
        basis = jnp.eye(vector.shape[0], dtype=vector.dtype)
        residuals, jacobian = jax.vmap(lambda direction: jax.jvp(along, (vector,), (direction,)), out_axes=(None, -1))(basis)
        columns.append(jacobian)
    if residuals is None:  # every column differenced
        with values_only():
            frames_now = problem.frames_of_groups(vectors, frame_data, positions=True)
            residuals = problem.residuals_of(problem.effect_of_groups(vectors, positions=True), frames_now)
    order = np.argsort(np.concatenate(groups))
    return residuals, jnp.concatenate(columns, axis=-1)[:, order]


@dataclasses.dataclass(frozen=True)
class CoarseLinearisation:
    """The fine resolution's Jacobian from the coarse resolution's: each fine pixel's derivatives taken as those of
    its `factor x factor` block (`downsample_box`'s blocks), from `problem` on the coarse frames `frame_data`
    (`reduced.downsample_frames`). A fit then compiles one Jacobian, the coarse one, and its fine steps cost a
    render and a coarse Jacobian; the residuals, the losses and what a step accepts stay the fine resolution's."""

    problem: FitProblem
    frame_data: tuple
    factor: int
    sharp: tuple[str, ...] = ()
    """Stages whose columns are the fine resolution's own instead (`Effect.SHARP_STAGES`: the fields that move
    edges a pixel wide, which a block's derivatives blur)."""
    kept: dict | None = dataclasses.field(default=None, compare=False, repr=False)
    """Where the `sharp` stages' columns are kept once taken at the first point linearised: a polish starts near the
    minimum, where they change little, and each point taken again costs two renders a sharp field
    (benchmarks/README.md, "The fit as users run it"). None: taken at every point (`determination`, at the fitted
    point)."""

    @classmethod
    def of(cls, problem: FitProblem, frame_data, factor: int) -> "CoarseLinearisation | None":
        """The linearisation, or None where positions mean other values at the two resolutions (a fitted field in
        pixels, `reduced.pixel_fields`)."""
        return None if set(pixel_fields(problem.effect)) & set(problem.names) else cls(problem, frame_data, factor)

    def jacobian(self, positions, fine_frames) -> np.ndarray:
        """Rows `J` whose `J^T J` is that of the fine residuals (one part per frame of `fine_frames`), a row per
        coarse residual: the coarse Jacobian's row times the square root of its block's fine pixels, and times
        `sqrt(coarse size / fine size)`, as a frame's residuals are scaled by the square root of its weight over
        its size."""
        _, jacobian = exported.call("fit_jacobian", residuals_and_jacobian, self.problem, positions, self.frame_data)
        jacobian = np.asarray(jacobian)
        parts, start = [], 0
        for block in self._blocks(fine_frames):
            parts.append(jacobian[start : start + block.weight.size] * block.weight[:, None])
            start += block.weight.size
        return np.concatenate(parts)

    def normal_equations(
        self, positions, residuals, fine_problem: FitProblem, fine_frame_data
    ) -> tuple[np.ndarray, np.ndarray]:
        """`(J^T J, J^T r)` of the fine `residuals` (of `fine_problem` on `fine_frame_data`): `J` is `jacobian`'s
        rows, whose product with the residuals is each block's row times the sum of the block's residuals; the
        `sharp` stages' columns are `fine_problem`'s own (`rendered_differences`: the fit's renders, no Jacobian
        of the fine resolution to compile), their products with a block's row each column's sum over the block."""
        blocks = self._blocks(fine_frame_data[0])
        if sum(block.fine_size for block in blocks) != len(residuals):
            raise ValueError(f"expected the residuals of {len(fine_frame_data[0])} fine frames, got {len(residuals)}")
        rows = self.jacobian(positions, fine_frame_data[0])
        sharp = np.asarray(fine_problem.stage_unknowns(self.sharp), int)
        if not sharp.size:  # no sharp stage, or every field of one held (`fit --fixed thickness,edge_softness`)
            return normal_equations(rows, _folded(blocks, residuals))
        rest = np.setdiff1d(np.arange(rows.shape[1]), sharp)
        if self.kept is not None and "columns" in self.kept:
            fine = self.kept["columns"]
        else:
            fine = rendered_differences(fine_problem, positions, fine_frame_data, sharp)
            if self.kept is not None:
                self.kept["columns"] = fine
        normal, gradient = np.zeros((rows.shape[1],) * 2), np.zeros(rows.shape[1])
        coarse_rows, fine_folded = np.asarray(rows[:, rest], np.float64), _folded(blocks, fine)
        normal[np.ix_(rest, rest)] = coarse_rows.T @ coarse_rows
        normal[np.ix_(rest, sharp)] = coarse_rows.T @ fine_folded
        normal[np.ix_(sharp, rest)] = normal[np.ix_(rest, sharp)].T
        normal[np.ix_(sharp, sharp)] = fine.T @ fine
        gradient[rest] = coarse_rows.T @ _folded(blocks, residuals)
        gradient[sharp] = fine.T @ np.asarray(residuals, np.float64)
        return normal, gradient

    def _blocks(self, fine_frames) -> list["_Blocks"]:
        blocks = []
        for fine, coarse, target in zip(fine_frames, self.frame_data[0], self.frame_data[2]):
            channels = min(np.shape(fine.color)[-1], np.shape(target)[-1], 3)  # as `problem._match_channels`
            shape = (fine.height, fine.width, channels)
            pad = [(0, coarse.height * self.factor - fine.height), (0, coarse.width * self.factor - fine.width), (0, 0)]
            blocks_shape = (coarse.height, self.factor, coarse.width, self.factor, channels)

            def sums(values, shape=shape, pad=pad, blocks_shape=blocks_shape):
                """Each block's sum of `values` (a frame's fine residuals, or columns of them)."""
                columns = np.reshape(values, (*shape, -1))
                summed = np.pad(columns, [*pad, (0, 0)]).reshape(*blocks_shape, -1).sum(axis=(1, 3))
                return summed.reshape(-1, *np.shape(values)[1:])

            count = sums(np.ones(math.prod(shape)))
            scale = math.sqrt(coarse.height * coarse.width / (fine.height * fine.width))
            blocks.append(_Blocks(math.prod(shape), count, scale * np.sqrt(count), sums))
        return blocks


def _folded(blocks: list["_Blocks"], values) -> np.ndarray:
    """Fine residuals (or columns of them), frame after frame, as each block's sum over the root of its count: a
    coarse row of `CoarseLinearisation.jacobian` times these is the fine rows' product with the values."""
    folded, start = [], 0
    for block in blocks:
        part = np.asarray(values[start : start + block.fine_size], np.float64)
        folded.append(block.sums(part) / np.sqrt(block.count).reshape(-1, *[1] * (part.ndim - 1)))
        start += block.fine_size
    return np.concatenate(folded)


def rendered_differences(problem: FitProblem, positions, frame_data, unknowns) -> np.ndarray:
    """The Jacobian's columns of `unknowns` (indices into `positions`) by central differences (`DIFFERENCE_STEP`) of
    `effect_residuals`: the frames rendered as a fit renders them (`render_compiled`, one compiled program for any
    values of the fields), two renders a column."""
    positions = np.asarray(positions)
    columns = []
    for index in unknowns:
        upper, lower = positions.copy(), positions.copy()
        upper[index] = min(upper[index] + DIFFERENCE_STEP, 1.0)
        lower[index] = max(lower[index] - DIFFERENCE_STEP, 0.0)
        above, below = (
            np.asarray(effect_residuals(problem, problem.effect_at_positions(at), problem.frames_at_positions(
                at, frame_data)), np.float64)
            for at in (jnp.asarray(upper), jnp.asarray(lower))
        )  # fmt: skip
        columns.append((above - below) / (float(upper[index]) - float(lower[index])))
    return np.stack(columns, axis=-1)


class _Blocks(NamedTuple):
    """A frame's fine residuals by block: their count, each block's fine pixels (times channels, a coarse
    residual each), each coarse row's weight, and the sum of fine values over each block."""

    fine_size: int
    count: np.ndarray
    weight: np.ndarray
    sums: Callable[[np.ndarray], np.ndarray]


def host_evaluator(
    problem: FitProblem, frame_data, dtype, own=None, coarse: CoarseLinearisation | None = None, warps=None, shared=None
):
    """`marquardt.Evaluate` of the unknowns `y`: the residuals, and their normal equations in `y` (the positions'
    Jacobian times the fold's slope, `problem.folded_positions`), from `residuals_and_jacobian`.

    `own`, a function of the fitted fields' positions: the effect whose own residuals replace the problem's (its
    stand-in's), which then gives the Jacobian alone (the polish of a fit through a stand-in), computed only when
    the step accepts the point. `coarse`: the normal equations from the coarse resolution's Jacobian instead, of
    `own`'s residuals (required then: the problem's own effect at the positions when it is not a polish).
    `warps`: the unknowns' map by ratios (`FitProblem.warps`), else None. `shared`: a dict of the problem's
    residuals and Jacobian by the positions they were taken at, which evaluators whose points repeat once share (a
    start raced by both maps begins at the same positions): an entry is taken out by the point that repeats it.
    """

    def evaluate(y):
        positions, slope = folded_positions(y, warps)
        positions = np.asarray(positions, dtype)
        key = None if shared is None else positions.tobytes()
        positions = jax.device_put(positions)  # cast on the host: `jnp.asarray` compiles per size

        def linearise(jacobian=None, residuals=None):
            if coarse is not None:
                normal, gradient = coarse.normal_equations(positions, residuals, problem, frame_data)
            else:
                if jacobian is None:
                    _, jacobian = exported.call("fit_jacobian", residuals_and_jacobian, problem, positions, frame_data)
                normal, gradient = normal_equations(np.asarray(jacobian), residuals)
            return normal * np.outer(slope, slope), gradient * slope

        if own is not None:
            frames_now = problem.frames_at_positions(positions, frame_data)
            residuals = np.asarray(effect_residuals(problem, own(positions), frames_now))
            return residuals, lambda: linearise(residuals=residuals)
        if key in (shared or {}):
            residuals, jacobian = shared.pop(key)
        else:
            residuals, jacobian = exported.call("fit_jacobian", residuals_and_jacobian, problem, positions, frame_data)
            residuals = np.asarray(residuals)
            if shared is not None:
                shared[key] = residuals, jacobian
        return residuals, lambda: linearise(jacobian, residuals)

    return evaluate


def _rendered(candidate: Effect, frame_data) -> list:
    return [
        render_compiled(candidate, frame, light, front, depth, other_lights=others)
        for frame, light, _, front, depth, others in zip(*frame_data)
    ]


@eqx.filter_jit
def _image_residuals(problem, images, frame_data):
    return problem.residuals_of_images(images, frame_data)


def effect_residuals(problem: FitProblem, candidate: Effect, frame_data) -> jax.Array:
    """`problem`'s residuals of `candidate`, from its frames rendered as `apply` renders them (`render_compiled`)."""
    return exported.call("fit_image_residuals", _image_residuals, problem, _rendered(candidate, frame_data), frame_data)


@eqx.filter_jit
def _image_loss(problem, images, frame_data):
    return problem.objective_of_images(images, frame_data)


def effect_loss(problem: FitProblem, candidate: Effect, frame_data) -> tuple[float, list]:
    """`problem`'s loss of `candidate` and its frames, rendered as `apply` renders them (`render_compiled`): a
    fit's losses of the effect itself share that compiled program with the frames its command then renders, and
    the command reports on these frames without rendering them again."""
    images = _rendered(candidate, frame_data)
    return float(exported.call("fit_image_loss", _image_loss, problem, images, frame_data)), images


@eqx.filter_jit
def evaluate_loss(candidate, data):
    problem, frame_data = data
    return problem.objective(candidate, frame_data)


def _first_state(optimiser, function, y, data):
    f_struct = jax.eval_shape(lambda: function(y, data)[0])
    return optimiser.init(function, y, data, {}, f_struct, None, frozenset())


@eqx.filter_jit
def solver_init(optimiser, function, y, data):
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
def solver_step(optimiser, function, y, state_leaves, data, least_squares):
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
