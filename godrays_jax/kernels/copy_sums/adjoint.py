"""The adjoint in the image of a sum of scaled copies: transposed interpolations as banded gathers.

Copy `k` samples the image bilinearly at `light + (p - light) * scale_k`,
one axis at a time: along an axis with texel coordinates `u_i = c + (i - c) *
s` of the outputs `i` (`c` the light in texels), texel `j` gives output `i`
the weight `1 - f_i` if `floor(u_i) = j` and `f_i` if `floor(u_i) = j - 1`
(`f_i` the fraction of `u_i`). The transpose gives texel `j` the outputs of
two runs: those with `u_i` in `[j, j + 1)` (weights `1 - f_i`) and in
`[j - 1, j)` (weights `f_i`). The outputs are in order along the axis (in
reverse order for a negative scale), so each run is a range of outputs whose
bounds are closed-form (`ceil(c + (j - c) / s)`), of at most `n` outputs
when `|s| >= 1 / n`. The adjoint of a copy is then a gather of `n` output
rows per texel row and run (`n` the smallest of `BANDS` that holds the copy's
longest run), the same memory pattern as the copy
itself: rows, a transpose, rows again, in the CPU loop's blocks of rows; a GPU
gathers along one axis of the image, then the other.

With clamp-to-edge addressing, the first and last texels also take every
output clamped onto them, a run of unbounded length: its sum is read from
prefix sums of the cotangent's rows and columns, computed only when some
copy clamps (a light off screen, a scale above 1). A copy whose runs are
longer than `BANDS` allows (a scale near 0, where the whole image samples a
few texels) is transposed by a scatter instead. Every case is exact up to
rounding, and an output on a run's boundary (`u_i` an integer) gives the
same values in either run, so the bounds need not agree with `floor` to the
last bit.
"""

import functools

import jax
import jax.numpy as jnp

from godrays_jax.kernels.copy_sums.cpu_loop import rows_per_block
from godrays_jax.kernels.copy_sums.planes import Planes
from godrays_jax.primitives.sampling import Addressing, axis_taps

BANDS = (2, 4, 8)
"""The outputs a texel's run may hold in the banded gather, per copy the smallest that holds its longest run.

A run of at most `n` outputs (a scale of magnitude at least `1 / n`, up to
rounding) costs `n` gathers of rows per run. 2 covers radial rays of density
up to 1/2 and flare-outs whose copies shrink to half, at the cost of the
forward copy's two gathers; 4 and 8 the copies of smaller scales (density up
to 7/8) for less than a scatter costs. Copies with longer runs take the scatter.
"""


def _positions(light, scale, index):
    """Texel coordinates `u` of outputs `index` along an axis, as the forward copy computes them."""
    return light + ((index.astype(light.dtype) + 0.5) - light) * scale - 0.5


def _run_bounds(size: int, light, scale, texels, addressing: Addressing):
    """For each texel `j` of `texels`: how many outputs, in walk order, have `u < j`.

    The walk is the outputs' order along the axis, reversed for a negative
    scale, so that `u` grows along it; the run of texel `j` is walk positions
    `bounds(j) .. bounds(j + 1)`. With clamping, outputs below texel 0 or at
    and past texel `size - 1` are left out of every run (see `_edge_runs`).
    """
    dtype = light.dtype
    centre = light - 0.5
    if addressing == "clamp":
        texels = jnp.clip(texels, 0, size - 1)
    texels = texels.astype(dtype)
    magnitude = jnp.where(scale == 0, 1.0, jnp.abs(scale))
    start = jnp.where(scale < 0, size - 1 - centre, centre)
    bounds = jnp.clip(jnp.ceil(start + (texels - centre) / magnitude), 0, size)
    # A zero scale puts every output at the light.
    bounds = jnp.where(scale == 0, jnp.where(centre < texels, size, 0), bounds)
    return bounds.astype(jnp.int32)


def _band_taps(size: int, light, scale, first, count: int, addressing: Addressing, band: int):
    """The banded gather's taps for texels `first .. first + count - 1` along an axis of `size`, runs up to `band` long.

    Returns `band` taps `(low, high)`, each `(outputs, weights)` for those
    texels: `low` reads texel `j`'s run (weights `1 - f`), `high` the run of
    `j - 1` (weights `f`), with weight 0 past a run's end.
    """
    texels = first - 1 + jnp.arange(count + 2)
    bounds = _run_bounds(size, light, scale, texels, addressing)
    starts, ends = bounds[:-1], bounds[1:]
    runs = texels[:-1].astype(light.dtype)
    taps = []
    for step in range(band):
        walk = starts + step
        outputs = jnp.clip(jnp.where(scale < 0, size - 1 - walk, walk), 0, size - 1)
        fraction = _positions(light, scale, outputs) - runs
        inside = walk < ends
        low_weight, high_weight = jnp.where(inside, 1.0 - fraction, 0.0), jnp.where(inside, fraction, 0.0)
        taps.append(((outputs[1:], low_weight[1:]), (outputs[:-1], high_weight[:-1])))
    return taps


def _gathered_rows(values, taps, planes: int, plane_rows: int):
    """`sum over taps of values[outputs] * weights`, rows of each of `planes` stacked planes of `plane_rows` rows."""
    plane_starts = (jnp.arange(planes) * plane_rows)[:, None]
    total = 0.0
    for low_and_high in taps:
        for outputs, weights in low_and_high:
            rows = values.at[(plane_starts + outputs).reshape(-1)].get(mode="promise_in_bounds")
            total = total + rows * jnp.tile(weights, planes)[:, None]
    return total


def copy_adjoint_cpu(addressing, cotangent, light_xy, scales, weights):
    """`copy_adjoint` for a CPU: the forward loop's layout (`Planes`) and blocks of rows, one copy per step."""
    dtype = cotangent.dtype
    planes = Planes(cotangent.shape)
    height, width, channels = planes.height, planes.width, planes.channels
    by_rows = planes.by_rows(cotangent)
    block = rows_per_block(height, width, channels)
    band = band_of_copies(cotangent.shape, light_xy, scales, addressing)

    def adjoint_of_block(first_row):
        """Texel rows `first_row .. first_row + block` of every plane, in the column layout `(W, C * block)`."""

        def add_copy(k, total):
            scale = scales[k]

            def add_band(total, width_of_band):
                row_taps = _band_taps(height, light_xy[1], scale, first_row, block, addressing, width_of_band)
                col_taps = _band_taps(width, light_xy[0], scale, 0, width, addressing, width_of_band)
                rows = _gathered_rows(by_rows, row_taps, channels, height)
                return total + weights[k] * _gathered_rows(planes.rows_to_columns(k, rows), col_taps, 1, width)

            # The conditional also keeps XLA from fusing the gathers with their operands' computation.
            branches = [functools.partial(add_band, width_of_band=n) for n in BANDS] + [lambda total: total]
            return jax.lax.switch(band[0][k], branches, total)

        return jax.lax.fori_loop(0, scales.shape[0], add_copy, jnp.zeros((width, channels * block), dtype))

    if block == height:
        columns = adjoint_of_block(0)
    else:
        blocks = jax.lax.map(adjoint_of_block, jnp.arange(0, height, block))
        split = blocks.reshape(blocks.shape[0], width, channels, block)
        columns = jnp.moveaxis(split, 0, 2).reshape(width, channels * height)
    banded = planes.image_from_columns(columns)
    return _with_runs_outside_band(addressing, cotangent, light_xy, scales, weights, band, banded)


COPIES_PER_STEP = 8
"""Copies the GPU adjoint loop sums per step (the loop unrolled), as the forward GPU loop does."""


def copy_adjoint_gpu(addressing, cotangent, light_xy, scales, weights):
    """`copy_adjoint` for a GPU: per copy, a gather along the rows of the image, then along its columns."""
    height, width, _ = cotangent.shape
    band = band_of_copies(cotangent.shape, light_xy, scales, addressing)

    def add_copy(k, total):
        scale = scales[k]

        def add_band(total, width_of_band):
            row_taps = _band_taps(height, light_xy[1], scale, 0, height, addressing, width_of_band)
            col_taps = _band_taps(width, light_xy[0], scale, 0, width, addressing, width_of_band)
            rows = sum(
                cotangent.at[outputs].get(mode="promise_in_bounds") * tap_weights[:, None, None]
                for low_and_high in row_taps for outputs, tap_weights in low_and_high
            )  # fmt: skip
            copy = sum(
                rows.at[:, outputs].get(mode="promise_in_bounds") * tap_weights[None, :, None]
                for low_and_high in col_taps for outputs, tap_weights in low_and_high
            )  # fmt: skip
            return total + weights[k] * copy

        branches = [functools.partial(add_band, width_of_band=n) for n in BANDS] + [lambda total: total]
        return jax.lax.switch(band[0][k], branches, total)

    count = scales.shape[0]
    total = jax.lax.fori_loop(
        0, count, add_copy, jnp.zeros_like(cotangent), unroll=max(1, min(COPIES_PER_STEP, count))
    )
    return _with_runs_outside_band(addressing, cotangent, light_xy, scales, weights, band, total)


def copy_adjoint(addressing: Addressing, cotangent, light_xy, scales, weights):
    """`sum_k weights[k] * A_k^T cotangent`: the transpose, in the image, of `copies.copy_sums`' total.

    `cotangent (H, W, C)`; returns the image's adjoint `(H, W, C)`. The CPU
    and other platforms get different loops (same values).
    """
    return jax.lax.platform_dependent(
        cotangent, light_xy, scales, weights,
        cpu=functools.partial(copy_adjoint_cpu, addressing),
        default=functools.partial(copy_adjoint_gpu, addressing),
    )  # fmt: skip


def band_of_copies(shape, light_xy, scales, addressing: Addressing):
    """Per copy: the index in `BANDS` of its band (`len(BANDS)`: none, the scatter), and per axis (y, x) the walk
    positions where its band starts and ends."""

    def of_copy(scale):
        longest, edges = 0, []
        for size, light in ((shape[0], light_xy[1]), (shape[1], light_xy[0])):
            bounds = _run_bounds(size, light, scale, jnp.arange(-1, size + 1), addressing)
            longest = jnp.maximum(longest, jnp.max(bounds[1:] - bounds[:-1]))
            edges.append((bounds[1], bounds[-2]))
        return jnp.sum(longest > jnp.asarray(BANDS)), edges

    return jax.vmap(of_copy)(scales)


def _transposed_by_scatter(values, axis: int, size: int, u, addressing: Addressing, keep=None):
    """The exact transpose of interpolating along `axis` at texel coordinates `u`, a scatter; outputs `keep` (0/1) only."""
    low, high, low_weight, high_weight = axis_taps(size, u, addressing)
    if keep is not None:
        low_weight, high_weight = low_weight * keep, high_weight * keep
    moved = jnp.moveaxis(values, axis, 0)
    shape = (-1,) + (1,) * (moved.ndim - 1)
    result = jnp.zeros((size,) + moved.shape[1:], values.dtype)
    result = result.at[low].add(moved * low_weight.reshape(shape)).at[high].add(moved * high_weight.reshape(shape))
    return jnp.moveaxis(result, 0, axis)


def _with_runs_outside_band(addressing: Addressing, cotangent, light_xy, scales, weights, band, banded):
    """`banded` plus what the band leaves out: the clamped outputs' runs and the copies whose runs are too long."""
    height, width, channels = cotangent.shape
    dtype = cotangent.dtype
    which, ((first_y, end_y), (first_x, end_x)) = band
    fits = which < len(BANDS)

    def add_wide_copy(k, total):
        scale = scales[k]

        def add(total):
            us = [_positions(light_xy[axis], scale, jnp.arange(size)) for axis, size in ((1, height), (0, width))]
            rows = _transposed_by_scatter(cotangent, 0, height, us[0], addressing)
            return total + weights[k] * _transposed_by_scatter(rows, 1, width, us[1], addressing)

        return jax.lax.cond(fits[k], lambda total: total, add, total)

    result = jax.lax.cond(
        jnp.all(fits), lambda total: total, lambda total: jax.lax.fori_loop(0, scales.shape[0], add_wide_copy, total),
        banded,
    )  # fmt: skip
    if addressing != "clamp":
        return result
    clamps = fits & ((first_y > 0) | (end_y < height) | (first_x > 0) | (end_x < width))
    no_edges = (jnp.zeros((2, height, channels), dtype), jnp.zeros((2, width, channels), dtype))
    columns, rows = jax.lax.cond(
        jnp.any(clamps), _edge_runs, lambda *_: no_edges, cotangent, light_xy, scales, weights, band
    )
    result = result.at[:, 0].add(columns[0]).at[:, width - 1].add(columns[1])
    return result.at[0].add(rows[0]).at[height - 1].add(rows[1])


def _prefix_sums(values, reverse: bool = False):
    """Along axis 0, `size + 1` entries: `[m]` sums `values[:m]` (reversed: `values[m:]`); a scan (XLA's CPU cumsum is slow)."""

    def step(carry, row):
        return carry + row, carry

    last, sums = jax.lax.scan(step, jnp.zeros_like(values[0]), values, reverse=reverse)
    return jnp.concatenate([last[None], sums]) if reverse else jnp.concatenate([sums, last[None]])


def _edge_runs(cotangent, light_xy, scales, weights, band):
    """With clamping, the sums the first and last texel columns `(2, H, C)` and rows `(2, W, C)` take from clamped outputs.

    In one axis the transpose is the band's part plus the runs clamped onto
    the edge texels; in two, `A_y^T G A_x = B_y^T G B_x + B_y^T G E_x + E_y^T G
    A_x` (`B` band, `E` edge runs): the edge columns take the x runs' sums of
    the cotangent, transposed in y by the band only, the edge rows the y runs'
    sums, transposed in x wholly. Both edge sums of every copy come from
    prefix sums of the cotangent's rows and columns, summed from each end so
    that no sum is a difference.
    """
    height, width, channels = cotangent.shape
    dtype = cotangent.dtype
    planes = Planes(cotangent.shape)
    rows_below, rows_above = _prefix_sums(cotangent), _prefix_sums(cotangent, reverse=True)
    by_columns = planes.rows_to_columns(0, planes.by_rows(cotangent))  # (W, C*H)
    columns_below, columns_above = _prefix_sums(by_columns), _prefix_sums(by_columns, reverse=True)

    def run_sums(below, above, size, scale, band_start, band_end):
        """The sums of the outputs before and after the band, in walk order."""
        mirrored = scale < 0
        low = jnp.where(mirrored, above[size - band_start], below[band_start])
        high = jnp.where(mirrored, below[size - band_end], above[band_end])
        return jnp.stack([low, high])

    def add_copy(k, sums):
        column_sums, row_sums = sums
        scale = scales[k]
        which, ((first_y, end_y), (first_x, end_x)) = jax.tree.map(lambda values: values[k], band)
        weight = jnp.where(which < len(BANDS), weights[k], 0.0)
        ys, xs = jnp.arange(height), jnp.arange(width)
        walk_y = jnp.where(scale < 0, height - 1 - ys, ys)
        in_band_y = ((walk_y >= first_y) & (walk_y < end_y)).astype(dtype)
        columns = run_sums(columns_below, columns_above, width, scale, first_x, end_x).reshape(2, channels, height)
        columns = _transposed_by_scatter(
            jnp.moveaxis(columns, 1, 2), 1, height, _positions(light_xy[1], scale, ys), "clamp", in_band_y
        )
        rows = run_sums(rows_below, rows_above, height, scale, first_y, end_y)
        rows = _transposed_by_scatter(rows, 1, width, _positions(light_xy[0], scale, xs), "clamp")
        return column_sums + weight * columns, row_sums + weight * rows

    zeros = (jnp.zeros((2, height, channels), dtype), jnp.zeros((2, width, channels), dtype))
    return jax.lax.fori_loop(0, scales.shape[0], add_copy, zeros)
