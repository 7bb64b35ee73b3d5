"""Radial light shafts: GPU Gems 3 radial rays (seeds 003, 004) and kbEngine flare-outs (seed 002).

All positions are pixels (x right, y down, pixel centres at `i + 0.5`). The light
may be anywhere: on screen, off screen or on a pixel centre; the kernels never
divide by the distance to it, so every case gives finite values and gradients.

Integer counts (`num_samples`, `num_iters`) accept a Python int (the exact
kernel) or a float / traced scalar with a static upper bound (the continuous
relaxation used for fitting); see each function for the relaxation.

Both kernels are sums of copies of the image scaled about the light,
`sum_k weight_k * image(light + (p - light) * scale_k)`, and share one
implementation, `scaled_copies`. Scaling about a point keeps x and y
separate, so on a CPU each bilinear copy is two 1-D interpolations: whole
rows, then, after a transpose, whole rows again (the columns), equal to
`sampling.sample_bilinear` up to rounding and several times faster there
than a 2-D gather per pixel or a gather along columns. On a GPU
(`lax.platform_dependent` chooses) the copies are 2-D gathers,
`COPIES_PER_STEP` of them per loop step, which XLA fuses into one kernel.

Derivatives need memory proportional to the image, not to the number of
copies, in forward and reverse mode. Inputs of few numbers (the copies'
parameters such as density and decay, the light, an emitter's radius) are
differentiated in forward mode inside the loop that sums the copies: it also
sums, per number, the copies' derivative in it, so a gradient costs one such
loop and one reduction per number, and a forward-mode Jacobian the same
loop. The copies' scales and weights come from separate functions of their
own parameters, so a number that only weights the copies (decay) adds a sum
of copies and one that only moves them (density / samples, seed 003's step)
a sum of radial derivatives. Inputs of many numbers (a whole image, one
weight per copy) get a tangent loop that recomputes each copy and that
reverse mode transposes (scattering the image's adjoint). See `FEW_NUMBERS`.
"""

import functools
import math

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero
from jaxtyping import Array, ArrayLike, Float

from godrays_jax.primitives.checks import check_image, check_light, check_scalar, checked_count, resolve_count
from godrays_jax.primitives.sampling import Addressing, _axis_taps


def _copy_positions(shape, light_xy, scale, dtype):
    """Sample positions `light + (p - light) * scale` of the pixel centres: xs (W,) and ys (H,)."""
    height, width = shape
    rows = jnp.arange(height, dtype=dtype) + 0.5
    cols = jnp.arange(width, dtype=dtype) + 0.5
    return light_xy[0] + (cols - light_xy[0]) * scale, light_xy[1] + (rows - light_xy[1]) * scale


def _taps_and_slopes(size: int, u, addressing: Addressing):
    """`_axis_taps` at texel coordinates `u`, plus the taps' weights' derivatives with respect to `u`."""
    taps, (_, _, low_slope, high_slope) = jax.jvp(
        lambda u: _axis_taps(size, u, addressing), (u,), (jnp.ones_like(u),)
    )
    return taps, (taps[0], taps[1], low_slope, high_slope)


def _transposed_apart(step, values):
    """`_tiled_transpose(values)`, kept out of its consumers' fusions.

    XLA fuses a gather with the computation of its operand and then evaluates
    that operand once per gathered element, through strided transposed reads:
    30x slower on a CPU than gathering from a stored array. A conditional is
    not fused with its surroundings, and its predicate (a loop counter
    `step >= 0`, always true) cannot be folded at compile time. The branch
    never taken fills the result with one of the values: a constant there
    (zeros) is hoisted out of an enclosing loop over blocks of rows and stored
    once per copy, and returning the values themselves (reshaped) made XLA
    copy them every step (forward 50 % slower at 480x270).
    """
    never_taken = lambda rows: jnp.broadcast_to(rows[0, 0], rows.shape[::-1])  # noqa: E731
    return jax.lax.cond(step >= 0, _tiled_transpose, never_taken, values)


class _Planes:
    """An `(H, W, C)` image as stacked channel planes: `(C*H, W)` by rows, `(W, C*H)` by columns.

    Both interpolations of a copy then gather whole rows (contiguous slices)
    of a stored 2-D array, the columns' from the transposed rows; transposes
    are plain 2-D ones (XLA's CPU transposes of interleaved channels are
    several times slower), and every reduction reverse mode makes is over a
    2-D array (XLA's CPU library reduction is ~40x slower over three
    dimensions).
    """

    def __init__(self, shape):
        self.height, self.width, self.channels = shape

    def by_rows(self, image):
        return jnp.moveaxis(jnp.asarray(image), 2, 0).reshape(self.channels * self.height, self.width)

    def plane_taps(self, taps, first=0):
        """`taps` (for one plane) for every plane of `by_rows`, whose first row is row `first` of the array read."""
        plane_starts = (first + jnp.arange(self.channels) * self.height)[:, None]
        low, high, low_weight, high_weight = taps
        return (
            (plane_starts + low).reshape(-1),
            (plane_starts + high).reshape(-1),
            jnp.tile(low_weight, self.channels),
            jnp.tile(high_weight, self.channels),
        )

    def sample_rows(self, by_rows, taps):
        """Every plane interpolated between the rows given by `taps` (for one plane)."""
        return _lerp_rows(by_rows, self.plane_taps(taps))

    def rows_to_columns(self, step, rows):
        return _transposed_apart(step, rows)

    def along_columns(self, values):
        """A per-row quantity (H,) laid along the column layout's columns."""
        return jnp.tile(values, self.channels)[None, :]

    def zeros(self, dtype):
        return jnp.zeros((self.width, self.channels * self.height), dtype)

    def image_from_columns(self, columns):
        return columns.reshape(self.width, self.channels, self.height).transpose(2, 0, 1)


def _tile(size: int) -> int:
    """The tile edge for transposing an axis of `size`: the divisor of `size` nearest 32 (at most 64)."""
    return min((d for d in range(1, 65) if size % d == 0), key=lambda d: abs(d - 32))


def _tiled_transpose(values):
    """`values.T`, stored, block by block.

    XLA's CPU transpose walks one axis with the other's stride: at 1920x1080
    every read misses the cache. Tiles of about 32x32 (a 4-D transpose) keep
    both sides in cache: 30 % faster there. It also makes the result a stored
    array (XLA would give a plain 2-D transpose a column-major layout instead,
    and gathering rows from that is strided again).
    """
    rows, cols = values.shape
    tile_rows, tile_cols = _tile(rows), _tile(cols)
    blocks = values.reshape(rows // tile_rows, tile_rows, cols // tile_cols, tile_cols)
    return blocks.transpose(2, 3, 0, 1).reshape(cols, rows)


def _lerp_rows(values, taps):
    """Interpolation between whole rows of a 2-D array: `values[low] * low_weight + values[high] * high_weight`."""
    low, high, low_weight, high_weight = taps
    lower = values.at[low].get(mode="promise_in_bounds")
    upper = values.at[high].get(mode="promise_in_bounds")
    return lower * low_weight[:, None] + upper * high_weight[:, None]


def _copy_taps(planes: _Planes, light_xy, scale, addressing: Addressing, dtype):
    """Row and column taps (with the weights' slopes) of the copy sampled at `light + (p - light) * scale`."""
    xs, ys = _copy_positions((planes.height, planes.width), light_xy, scale, dtype)
    return _taps_and_slopes(planes.width, xs - 0.5, addressing), _taps_and_slopes(planes.height, ys - 0.5, addressing)


FEW_NUMBERS = 8
"""Differentiated inputs with at most this many numbers in all (counted for the image's inputs, and for the copies'
scales' and weights' together) are differentiated in forward mode inside the loop.

Their derivative images (of the copies' weights and scales, the light, or
the few numbers an image is computed from) are accumulated alongside the
copies, so reverse mode needs one reduction per number after the loop, and
no scatter of the image's adjoint. Larger inputs (a whole image, a vector of
weights per copy) get a tangent loop that reverse mode transposes.
"""


def _split_varying(args, tangents, budget):
    """The flattened `args` and tangents, and the differentiated leaves' indices: few (`budget` numbers in all), many."""
    leaves, tree = jax.tree.flatten(args)
    tangent_leaves = tree.flatten_up_to(tangents)
    few, many = [], []
    for index, (leaf, tangent) in enumerate(zip(leaves, tangent_leaves)):
        if type(tangent) is SymbolicZero:
            continue
        if np.size(leaf) <= budget:
            few.append(index)
            budget -= np.size(leaf)
        else:
            many.append(index)
    return leaves, tree, tangent_leaves, few, many


def _replaced(leaves, tree, indices, values):
    """The arguments rebuilt from `leaves`, with the leaves at `indices` replaced by `values`."""
    leaves = list(leaves)
    for index, value in zip(indices, values):
        leaves[index] = value
    return tree.unflatten(leaves)


def _forward_derivatives(function, leaves, tree, tangent_leaves, indices):
    """`function(*args)`, its Jacobian in the leaves at `indices` (last axis), and those leaves' tangents, flattened."""
    flat, unflatten = jax.flatten_util.ravel_pytree([leaves[i] for i in indices])
    direction, _ = jax.flatten_util.ravel_pytree([jnp.asarray(tangent_leaves[i], flat.dtype) for i in indices])

    def of_flat(flat):
        return function(*_replaced(leaves, tree, indices, unflatten(flat)))

    value, jacobian = jax.vmap(lambda basis: jax.jvp(of_flat, (flat,), (basis,)), out_axes=(None, -1))(
        jnp.eye(flat.size, dtype=flat.dtype)
    )
    return value, jacobian, direction


def _offsets(planes: _Planes, light_xy, dtype):
    """Pixel centres minus the light in the column layout `(W, C*H)`, where a pixel's x is its row and y its column."""
    col_offsets = (jnp.arange(planes.width, dtype=dtype) + 0.5 - light_xy[0])[:, None]
    row_offsets = planes.along_columns(jnp.arange(planes.height, dtype=dtype) + 0.5 - light_xy[1])
    return col_offsets, row_offsets


def _copy_derivatives(planes: _Planes, by_rows, k, columns, col_taps, col_slopes, row_slopes):
    """A copy's x and y derivatives (at its sample positions) in the column layout."""
    x_derivative = _lerp_rows(columns, col_slopes)
    y_derivative = _lerp_rows(planes.rows_to_columns(k, planes.sample_rows(by_rows, row_slopes)), col_taps)
    return x_derivative, y_derivative


BLOCKED_SIZE = 2**21
"""Images of at least this many numbers (`H * W` times the planes sampled) are summed in blocks of output rows on a CPU.

All copies of one block of `ROWS_PER_BLOCK` output rows are summed before the
next block, so a block's sums and rows stay in cache instead of streaming
through memory once per copy. A step samples the image's planes, and for
derivatives also their y-slopes and any derivative image's planes. Measured on
2 cores, GodRays with 128 samples (forward pass / value and gradient of six
fields, one plane for the disc emitter, three for the sky's RGB): in blocks at
1920x1080 the sky's forward pass is 2.2x faster, the disc's value and gradient
(3 planes) 1.3x; at 1280x720 the sky's forward pass 1.6x (234 -> 145 ms), the
disc's value and gradient 1.3x (370 -> 289 ms); at 960x540 the sky's value and
gradient (6 planes) 1.6x (405 -> 257 ms). Below the threshold blocks cost more
than they save: the disc's forward pass at 1280x720 (55 -> 70 ms), its value
and gradient at 960x540 (148 -> 184 ms), the sky's at 480x270 (57 -> 62 ms).
"""

ROWS_PER_BLOCK = 64
"""Output rows per block: the divisor of the image's height nearest to it, if within a factor 2 of it."""


def _rows_per_block(height: int, width: int, channels: int) -> int:
    """Rows per block, or `height` (one block) for a small image or a height with no divisor near `ROWS_PER_BLOCK`."""
    if height * width * channels < BLOCKED_SIZE:
        return height
    rows = min((d for d in range(1, height + 1) if height % d == 0), key=lambda d: abs(d - ROWS_PER_BLOCK))
    # Blocks of a few rows (a prime height) would cost a loop step per copy and row.
    return rows if ROWS_PER_BLOCK // 2 <= rows <= 2 * ROWS_PER_BLOCK else height


def _copy_sums_by_planes(addressing, light_varies, image, derivative_image, light_xy, scales, weights, jacobians):
    """`_copy_sums` for a CPU: one copy per loop step, as rows gathered, transposed and gathered again (`_Planes`).

    Every plane a step samples (the image's; the derivative image's; for
    derivatives in the scales or the light, the image's y-slopes) is
    interpolated between rows by one gather of the stacked planes and
    transposed as one array: XLA fuses a gather into its consumer only when
    it has one, and stores it otherwise. Large images are summed block by
    block of output rows (`BLOCKED_SIZE`).
    """
    dtype = image.dtype
    planes = _Planes(image.shape)
    stacked_rows = planes.by_rows(image)
    if derivative_image is not None:
        derivative_planes = _Planes(derivative_image.shape)
        stacked_rows = jnp.concatenate([stacked_rows, derivative_planes.by_rows(derivative_image)])
    scale_jacobian, weight_jacobian = jacobians
    moves = scale_jacobian is not None or light_varies
    height, width, channels = planes.height, planes.width, planes.channels
    derivative_channels = 0 if derivative_image is None else derivative_planes.channels
    block = _rows_per_block(height, width, channels * (2 if moves else 1) + derivative_channels)
    col_offsets, _ = _offsets(planes, light_xy, dtype)
    # The transposed planes' columns: the image's, the derivative image's, the y-slopes'.
    image_width, derivative_width = channels * block, derivative_channels * block

    def sums_of_block(first_row):
        """The sums for output rows `first_row .. first_row + block` of every plane: `(W, C * block)` each."""
        rows = jax.lax.dynamic_slice_in_dim(jnp.arange(height, dtype=dtype) + 0.5 - light_xy[1], first_row, block)
        row_offsets = jnp.tile(rows, channels)[None, :]

        def add_copy(k, sums):
            total, derivative_total, scale_sums, weight_sums, light_sums = sums
            (col_taps, col_slopes), (row_taps, row_slopes) = _copy_taps(planes, light_xy, scales[k], addressing, dtype)
            row_taps, row_slopes = (
                tuple(jax.lax.dynamic_slice_in_dim(values, first_row, block) for values in taps)
                for taps in (row_taps, row_slopes)
            )
            plane_taps = [planes.plane_taps(row_taps)]
            if derivative_image is not None:
                plane_taps.append(derivative_planes.plane_taps(row_taps, first=channels * height))
            if moves:
                plane_taps.append(planes.plane_taps(row_slopes))
            sampled_rows = _lerp_rows(stacked_rows, tuple(jnp.concatenate(parts) for parts in zip(*plane_taps)))
            columns = planes.rows_to_columns(k, sampled_rows)
            image_columns = columns[:, :image_width]
            copy = _lerp_rows(image_columns, col_taps)
            total = total + weights[k] * copy
            if derivative_image is not None:
                derivative_columns = columns[:, image_width : image_width + derivative_width]
                derivative_total = derivative_total + weights[k] * _lerp_rows(derivative_columns, col_taps)
            if moves:
                x_derivative = _lerp_rows(image_columns, col_slopes)
                y_derivative = _lerp_rows(columns[:, image_width + derivative_width :], col_taps)
            # The numbers along the last axis: each copy is read once for all of them.
            if scale_jacobian is not None:
                radial_derivative = x_derivative * col_offsets + y_derivative * row_offsets
                scale_sums = scale_sums + (weights[k] * scale_jacobian[k]) * radial_derivative[..., None]
            if weight_jacobian is not None:
                weight_sums = weight_sums + weight_jacobian[k] * copy[..., None]
            if light_varies:
                # Positions `light + (p - light) * scale`: d/d(light) = 1 - scale.
                step = weights[k] * (1.0 - scales[k])
                light_sums = (light_sums[0] + step * x_derivative, light_sums[1] + step * y_derivative)
            return total, derivative_total, scale_sums, weight_sums, light_sums

        zeros = jnp.zeros((width, image_width), dtype)
        sums = (
            zeros,
            None if derivative_image is None else jnp.zeros((width, derivative_width), dtype),
            *(None if jac is None else jnp.zeros(zeros.shape + jac.shape[1:], dtype) for jac in jacobians),
            (zeros, zeros) if light_varies else None,
        )
        return jax.lax.fori_loop(0, scales.shape[0], add_copy, sums)

    if block == height:
        return sums_of_block(0)
    blocks = jax.lax.map(sums_of_block, jnp.arange(0, height, block))

    def joined(values):
        """`(blocks, W, C * block, ...)` back to the column layout `(W, C * H, ...)`."""
        count, _, planes_and_rows = values.shape[:3]
        split = values.reshape((count, width, planes_and_rows // block, block) + values.shape[3:])
        return jnp.moveaxis(split, 0, 2).reshape((width, planes_and_rows // block * height) + values.shape[3:])

    return jax.tree.map(joined, blocks)


COPIES_PER_STEP = 8
"""Copies a GPU sums per loop step (the loop unrolled), each from 2-D gathers of its four bilinear corners.

XLA fuses a step's gathers and the copies' sum into one kernel and stores no
copy: at 1920x1080 on an H100, 128 copies of an RGB image take 2.8 ms against
15 ms one copy per step through `_Planes`' transposes. When several sums read
the copies (the derivative sums) XLA stores the step's gathered values
instead (about 500 MiB at 1920x1080), still 2-6x faster than the CPU loop there.
"""


def _bilinear(corners, row_weights, col_weights):
    """A copy `(H, W, C)` from its four corner values and its row `(H,)` and column `(W,)` weights."""
    top_left, top_right, bottom_left, bottom_right = corners
    top, bottom = (weight[:, None, None] for weight in row_weights)
    left, right = (weight[None, :, None] for weight in col_weights)
    return top * (left * top_left + right * top_right) + bottom * (left * bottom_left + right * bottom_right)


def _corners(image, row_taps, col_taps):
    """A copy's values at its four bilinear corners: 2-D gathers `(H, W, C)` of `image`."""
    rows = [index[:, None] for index in row_taps[:2]]
    cols = [index[None, :] for index in col_taps[:2]]
    return tuple(image.at[row, col].get(mode="promise_in_bounds") for row in rows for col in cols)


def _copy_sums_batched(addressing, light_varies, image, derivative_image, light_xy, scales, weights, jacobians):
    """`_copy_sums` for a GPU: one copy per loop step, unrolled `COPIES_PER_STEP` times so XLA fuses those copies."""
    height, width, _ = image.shape
    dtype = image.dtype
    x_offsets = jnp.arange(width, dtype=dtype) + 0.5 - light_xy[0]
    y_offsets = jnp.arange(height, dtype=dtype) + 0.5 - light_xy[1]
    scale_jacobian, weight_jacobian = jacobians
    moves = scale_jacobian is not None or light_varies

    def add_copy(k, sums):
        total, derivative_total, scale_sums, weight_sums, light_sums = sums
        scale, weight = scales[k], weights[k]
        col_taps, col_slopes = _taps_and_slopes(width, light_xy[0] + x_offsets * scale - 0.5, addressing)
        row_taps, row_slopes = _taps_and_slopes(height, light_xy[1] + y_offsets * scale - 0.5, addressing)
        corners = _corners(image, row_taps, col_taps)
        copy = _bilinear(corners, row_taps[2:], col_taps[2:])
        total = total + weight * copy
        if derivative_image is not None:
            derivative_corners = _corners(derivative_image, row_taps, col_taps)
            derivative_total = derivative_total + weight * _bilinear(derivative_corners, row_taps[2:], col_taps[2:])
        if moves:
            x_derivative = _bilinear(corners, row_taps[2:], col_slopes[2:])
            y_derivative = _bilinear(corners, row_slopes[2:], col_taps[2:])
        if scale_jacobian is not None:
            radial = x_derivative * x_offsets[:, None] + y_derivative * y_offsets[:, None, None]
            scale_sums = tuple(sum_ + (weight * factor) * radial for sum_, factor in zip(scale_sums, scale_jacobian[k]))
        if weight_jacobian is not None:
            weight_sums = tuple(sum_ + factor * copy for sum_, factor in zip(weight_sums, weight_jacobian[k]))
        if light_varies:
            moved = weight * (1.0 - scale)
            light_sums = (light_sums[0] + moved * x_derivative, light_sums[1] + moved * y_derivative)
        return total, derivative_total, scale_sums, weight_sums, light_sums

    zeros = jnp.zeros(image.shape, dtype)
    sums = (
        zeros,
        None if derivative_image is None else jnp.zeros(derivative_image.shape, dtype),
        *(None if jacobian is None else (zeros,) * jacobian.shape[1] for jacobian in jacobians),
        (zeros, zeros) if light_varies else None,
    )
    count = scales.shape[0]
    sums = jax.lax.fori_loop(0, count, add_copy, sums, unroll=max(1, min(COPIES_PER_STEP, count)))
    total, derivative_total, scale_sums, weight_sums, light_sums = sums

    def as_columns(values):
        """`(H, W, C, ...)` in `_Planes`' column layout `(W, C*H, ...)`."""
        moved = jnp.moveaxis(values, (1, 2, 0), (0, 1, 2))
        return moved.reshape((width, values.shape[2] * height) + values.shape[3:])

    return (
        as_columns(total),
        None if derivative_image is None else as_columns(derivative_total),
        *(None if number_sums is None else as_columns(jnp.stack(number_sums, axis=-1))
          for number_sums in (scale_sums, weight_sums)),
        None if light_sums is None else tuple(as_columns(light_sum) for light_sum in light_sums),
    )


def _copy_sums(addressing, light_varies, image, derivative_image, light_xy, scales, weights, jacobians):
    """The copies' sum and, for forward-mode derivatives, the sums of their derivative images.

    With `image (H, W, C)` and `K` copies: the weighted copies' sum; if
    `derivative_image (H, W, C')` is given, its copies' sum; `jacobians` is the
    scales' Jacobian `(K, S)` and the weights' `(K, V)` in the few numbers each
    depends on (either may be None): per scale number the sum of every copy's
    radial derivative `(p - light) . grad` times its weight and its scale's
    derivative, per weight number the sum of every copy times its weight's
    derivative; if `light_varies`, the sums of the copies' x and y
    derivatives times `1 - scale` (their derivatives in the light). Returns
    `(total, derivative_total, scale_sums, weight_sums, light_sums)` in
    `_Planes`' column layout `(W, C*H)` (numbers last); absent ones are None.
    The CPU and other platforms get different loops (same values).
    """
    operands = (image, derivative_image, light_xy, scales, weights, jacobians)
    return jax.lax.platform_dependent(
        *operands,
        cpu=functools.partial(_copy_sums_by_planes, addressing, light_varies),
        default=functools.partial(_copy_sums_batched, addressing, light_varies),
    )


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2))
def _scaled_copies(image_fn, schedule, addressing, image_args, light_xy, schedule_args):
    """`scaled_copies(image_fn(*image_args), light_xy, scales, weights)`, differentiable in every argument.

    `schedule = (scales_fn, weights_fn)` and `schedule_args = (scale_args,
    weight_args)`: `scales = scales_fn(*scale_args)`, `weights =
    weights_fn(*weight_args)`. Keeping them apart lets the derivative loop sum
    radial derivatives only for the numbers that move the copies and copies
    only for the numbers that weight them.
    """
    image = image_fn(*image_args)
    (scales_fn, weights_fn), (scale_args, weight_args) = schedule, schedule_args
    total, _, _, _, _ = _copy_sums(
        addressing, False, image, None, light_xy, scales_fn(*scale_args), weights_fn(*weight_args), (None, None)
    )
    return _Planes(image.shape).image_from_columns(total)


def _differentiated(function, args, tangents, budget=FEW_NUMBERS):
    """`function(*args)`, with its forward-mode Jacobian in the few differentiated numbers of `args`.

    Returns the value, the Jacobian (numbers on the last axis; None without
    few numbers), those numbers' tangents (flattened) and the inputs of many
    numbers `(leaves, tree, tangent_leaves, indices)`: the leaves that fit in
    `budget` numbers are few (see `FEW_NUMBERS`).
    """
    leaves, tree, tangent_leaves, few, many = _split_varying(args, tangents, budget)
    if few:
        value, jacobian, direction = _forward_derivatives(function, leaves, tree, tangent_leaves, few)
    else:
        value, jacobian, direction = function(*args), None, None
    return value, jacobian, direction, (leaves, tree, tangent_leaves, many)


def _tangent_of(function, part):
    """The tangent of `function` in the inputs of many numbers of `part` (from `_differentiated`), or None."""
    leaves, tree, tangent_leaves, many = part
    if not many:
        return None
    _, tangent = jax.jvp(
        lambda *values: function(*_replaced(leaves, tree, many, values)),
        [leaves[i] for i in many],
        [jnp.asarray(tangent_leaves[i]) for i in many],
    )
    return tangent


@functools.partial(_scaled_copies.defjvp, symbolic_zeros=True)
def _scaled_copies_jvp(image_fn, schedule, addressing, primals, tangents):
    image_args, light_xy, (scale_args, weight_args) = primals
    image_tangents, light_dot, (scale_tangents, weight_tangents) = tangents
    scales_fn, weights_fn = schedule
    light_varies = type(light_dot) is not SymbolicZero
    image, image_jacobian, image_direction, image_part = _differentiated(image_fn, image_args, image_tangents)
    scales, scale_jacobian, scale_direction, scale_part = _differentiated(scales_fn, scale_args, scale_tangents)
    # The scales and weights share one budget: vectors of a weight per copy are many numbers even when the scales
    # are few (a sum per number would cost more than the tangent loop).
    weight_budget = FEW_NUMBERS - (0 if scale_direction is None else scale_direction.size)
    weights, weight_jacobian, weight_direction, weight_part = _differentiated(
        weights_fn, weight_args, weight_tangents, weight_budget
    )
    dtype = image.dtype
    planes = _Planes(image.shape)
    # One loop computes the copies' sum and, for every differentiated input
    # of few numbers, the image its tangent multiplies: the sum over copies of
    # the copy's derivative in that input. The copies' scales act through
    # their radial derivatives `(p - light) . grad`, the weights through the
    # copies, the light's sampling through their x and y derivatives times
    # `1 - scale`, and the image's few inputs through their derivative images
    # sampled like it.
    total, derivative_total, scale_sums, weight_sums, light_sums = _copy_sums(
        addressing,
        light_varies,
        image,
        None if image_jacobian is None else image_jacobian.reshape(planes.height, planes.width, -1),
        light_xy,
        scales,
        weights,
        (scale_jacobian, weight_jacobian),
    )

    tangent = jnp.zeros_like(total)
    if image_jacobian is not None:
        by_number = derivative_total.reshape(planes.width, planes.channels, image_direction.size, planes.height)
        tangent += jnp.einsum("wcqh,q->wch", by_number, image_direction, precision="highest").reshape(total.shape)
    for number_sums, direction in ((scale_sums, scale_direction), (weight_sums, weight_direction)):
        if number_sums is not None:
            tangent += jnp.matmul(number_sums, direction, precision="highest")
    if light_varies:
        tangent += jnp.tensordot(jnp.asarray(light_dot, dtype), jnp.stack(light_sums), 1, precision="highest")

    # Inputs of many numbers: a tangent loop, rematerialised so that reverse
    # mode recomputes each copy instead of storing one image per copy. The
    # image's tangent is sampled like the image (reverse mode scatters whole
    # rows); per-copy weight and scale tangents multiply the copy and its
    # radial derivative (reverse mode reduces the cotangent against them).
    image_dot, scales_dot, weights_dot = (
        _tangent_of(function, part)
        for function, part in ((image_fn, image_part), (scales_fn, scale_part), (weights_fn, weight_part))
    )
    if image_dot is not None or scales_dot is not None or weights_dot is not None:
        tangent += _tangent_of_many(
            planes, addressing, image, light_xy, scales, weights, image_dot, scales_dot, weights_dot
        )
    return planes.image_from_columns(total), planes.image_from_columns(tangent)


def _tangent_of_many(planes, addressing, image, light_xy, scales, weights, image_dot, scales_dot, weights_dot):
    """The copies' sum's tangent in the image's, scales' and weights' tangents (None: zero), in the column layout."""
    dtype = image.dtype
    by_rows = planes.by_rows(image)
    col_offsets, row_offsets = _offsets(planes, light_xy, dtype)
    if image_dot is not None:
        image_dot_by_rows = planes.by_rows(image_dot)

    @jax.checkpoint
    def add_tangent(k, total_dot):
        (col_taps, col_slopes), (row_taps, row_slopes) = _copy_taps(planes, light_xy, scales[k], addressing, dtype)
        if image_dot is not None:
            columns_dot = planes.rows_to_columns(k, planes.sample_rows(image_dot_by_rows, row_taps))
            total_dot += weights[k] * _lerp_rows(columns_dot, col_taps)
        if scales_dot is not None or weights_dot is not None:
            columns = planes.rows_to_columns(k, planes.sample_rows(by_rows, row_taps))
        if weights_dot is not None:
            total_dot += weights_dot[k] * _lerp_rows(columns, col_taps)
        if scales_dot is not None:
            x_derivative, y_derivative = _copy_derivatives(planes, by_rows, k, columns, col_taps, col_slopes, row_slopes)
            radial_derivative = x_derivative * col_offsets + y_derivative * row_offsets
            total_dot += (weights[k] * scales_dot[k]) * radial_derivative
        return total_dot

    return jax.lax.fori_loop(0, scales.shape[0], add_tangent, planes.zeros(dtype))


def _identity(image):
    return image


def scaled_copies(
    image: Float[Array, "H W C"],
    light_xy: Float[ArrayLike, "2"],
    scales: Float[ArrayLike, "K"],
    weights: Float[ArrayLike, "K"],
    *,
    addressing: Addressing = "clamp",
) -> Float[Array, "H W C"]:
    """`sum_k weights[k] * image(light + (p - light) * scales[k])` for every pixel centre `p`.

    The building block of radial rays and flare-outs: copy `k` is the image
    enlarged `1 / scales[k]` times about the light (`scales[k] = 1` is the image
    itself, `0` fills it with the value under the light), sampled bilinearly.

    Args:
        image: the texture.
        light_xy: the centre of scaling, in pixels; any real position.
        scales: `K` scale factors (any reals; negative ones mirror through the light).
        weights: `K` weights.
        addressing: off-image texels: `"clamp"` repeats the edge, `"zero"` is 0
            (see `sampling.sample_bilinear`).

    Returns:
        The weighted sum, same shape and dtype as `image`. Differentiable in
        every argument, forward and reverse mode, with memory O(image) for any `K`.
    """
    check_image(image)
    check_light(light_xy)
    if addressing not in ("clamp", "zero"):
        raise ValueError(f"addressing must be 'clamp' or 'zero', got {addressing!r}")
    image = jnp.asarray(image)
    dtype = image.dtype
    scales = jnp.asarray(scales, dtype)
    weights = jnp.asarray(weights, dtype)
    if scales.ndim != 1 or scales.shape != weights.shape:
        raise ValueError(f"scales and weights must be vectors of one length, got {scales.shape} and {weights.shape}")
    light_xy = jnp.asarray(light_xy, dtype)
    return _scaled_copies(_identity, (_identity, _identity), addressing, (image,), light_xy, ((scales,), (weights,)))


def _powers(base, length: int, dtype):
    """`[1, base, base**2, ...]`, `length` terms; unlike `base ** k` its gradient is finite at `base = 0`."""
    factors = jnp.concatenate([jnp.ones((1,), dtype), jnp.full((length - 1,), base, dtype)])
    return jnp.cumprod(factors)


def radial_rays(
    image: Float[Array, "H W C"],
    light_xy: Float[ArrayLike, "2"],
    *,
    num_samples: int | Float[ArrayLike, ""],
    density: Float[ArrayLike, ""],
    decay: Float[ArrayLike, ""],
    weight: Float[ArrayLike, ""],
    exposure: Float[ArrayLike, ""],
    max_samples: int | None = None,
    source_radius: float | None = None,
) -> Float[Array, "H W C"]:
    """The GPU Gems 3 (ch. 13) radial-blur loop, exactly as seed 003 writes it.

    For each pixel centre `p`, with `delta = (p - light) * density / num_samples`:
    `exposure * (image(p) + sum_{i=1..n} weight * decay**(i-1) * image(p - i * delta))`,
    bilinear samples with clamp-to-edge addressing. With `density = 1` the last
    sample lands on the light; lights off screen read the clamped edge.

    Value and gradient (reverse or forward mode) need memory O(image), not
    O(samples x image). `godrays_jax.kernels.fast` has cheaper approximations.

    Args:
        image: the occlusion image (light source bright, occluders black).
        light_xy: the light's position in pixels.
        num_samples: samples per pixel. A Python int >= 1 runs the exact loop.
            A float (or traced) value `n` is the continuous relaxation: the step
            uses `n` and sample `i` (i = 1..max_samples) is weighted by
            `clip(n - i + 1, 0, 1)`, so whole samples are in or out and the last
            one fades in; at integer `n` it equals the exact loop. `n = 0` gives
            `exposure * image`.
        density: fraction of the way to the light the samples cover.
        decay: per-sample falloff, usually in (0, 1].
        weight: per-sample weight.
        exposure: overall scale.
        max_samples: static loop length for a relaxed `num_samples`.
        source_radius: optional promise, in pixels, that `image` is 0 farther
            than this from the light (a light-source disc). When the sample
            scales are known at trace time (concrete `density` and
            `num_samples`) and all lie in (0, 1], every sample of a pixel lies
            between it and the light and clamping only moves samples away from
            the light, so the rays are 0 farther than
            `(source_radius + 2) / min(scale)` from the light: the loop then
            runs on that window around the light (same result, fewer pixels;
            e.g. 8x fewer at 1920x1080 with seed 003's radius 120 px and
            density 0.5). An image that breaks the promise gives wrong rays.

    Returns:
        The rays image, same shape and dtype as `image`.
    """
    check_image(image)
    return _radial_rays(
        _identity,
        (jnp.asarray(image),),
        light_xy,
        num_samples=num_samples,
        density=density,
        decay=decay,
        weight=weight,
        exposure=exposure,
        max_samples=max_samples,
        source_radius=source_radius,
    )


def _radial_scales(loop_length: int, step):
    """Seed 003's sample scales `1 - i * step` (i = 1..loop_length), `step = density / n`."""
    return 1.0 - jnp.arange(1, loop_length + 1, dtype=step.dtype) * step


def _faded_powers(loop_length: int, relaxed: bool, decay, count):
    """Weights `decay**j` (j = 0..loop_length-1); relaxed, times the fade-in `clip(count - j, 0, 1)`."""
    weights = _powers(decay, loop_length, decay.dtype)
    if relaxed:
        weights = weights * jnp.clip(count - jnp.arange(loop_length, dtype=decay.dtype), 0.0, 1.0)
    return weights


def _window_of(image_fn, size, origin, *image_args):
    return jax.lax.dynamic_slice(image_fn(*image_args), (origin[0], origin[1], jnp.int32(0)), size)


def _radial_rays(image_fn, image_args, light_xy, *, num_samples, density, decay, weight, exposure, max_samples=None,
                 source_radius=None):  # fmt: skip
    """`radial_rays(image_fn(*image_args), ...)`.

    Differentiated inputs of `image_fn` with few numbers (a light-source
    disc's radius) are differentiated in forward mode inside the sample loop,
    so their reverse-mode gradient costs no adjoint of the image.
    """
    check_light(light_xy)
    if source_radius is not None and not (isinstance(source_radius, (int, float)) and source_radius >= 0):
        raise ValueError(f"source_radius must be a Python number >= 0 (pixels) or None, got {source_radius!r}")
    for name, value in (("density", density), ("decay", decay), ("weight", weight), ("exposure", exposure)):
        check_scalar(value, name)
    loop_length, relaxed = resolve_count(num_samples, max_samples, "num_samples", "max_samples")
    shape = jax.eval_shape(image_fn, *image_args)
    dtype = shape.dtype
    if relaxed:
        count = checked_count(num_samples, loop_length, "num_samples", "max_samples", dtype)
    else:
        count = jnp.asarray(num_samples, dtype)
    schedule = (functools.partial(_radial_scales, loop_length), functools.partial(_faded_powers, loop_length, relaxed))
    # At n = 0 every weight is 0; a unit divisor keeps the (unused) positions finite.
    step = jnp.asarray(density, dtype) / (jnp.where(count > 0, count, 1.0) if relaxed else count)
    # The scales depend on density and n only through the step: one radial derivative sum in the loop for both.
    # `weight` scales every sample alike, so it multiplies their sum: one derivative image fewer in the loop.
    schedule_args = ((step,), (jnp.asarray(decay, dtype), count))
    weight = jnp.asarray(weight, dtype)
    exposure = jnp.asarray(exposure, dtype)
    light_xy = jnp.asarray(light_xy, dtype)
    window = None
    if source_radius is not None:
        window = _rays_window(shape.shape, source_radius, density, num_samples, loop_length, relaxed)
    if window is None:
        image = image_fn(*image_args)
        copies = _scaled_copies(image_fn, schedule, "clamp", image_args, light_xy, schedule_args)
        return (image + weight * copies) * exposure
    # Every non-zero output pixel lies in the window, and so does every sample
    # it reads (or the window's edge is the image's): the windowed loop is exact.
    height, width, channels = shape.shape
    window_height, window_width, reach = window
    origin = jnp.stack(
        [
            jnp.clip(jnp.floor(light_xy[axis]) - reach, 0, size - extent).astype(jnp.int32)
            for axis, size, extent in ((1, height, window_height), (0, width, window_width))
        ]
    )
    part_fn = functools.partial(_window_of, image_fn, (window_height, window_width, channels))
    part_args = (origin, *image_args)
    local_light = light_xy - origin[::-1].astype(dtype)
    part = part_fn(*part_args)
    copies = _scaled_copies(part_fn, schedule, "clamp", part_args, local_light, schedule_args)
    rays = (part + weight * copies) * exposure
    return jax.lax.dynamic_update_slice(jnp.zeros(shape.shape, dtype), rays, (origin[0], origin[1], jnp.int32(0)))


def _rays_window(shape, source_radius: float, density, num_samples, loop_length: int, relaxed: bool):
    """`(height, width, reach)` of the window that holds all rays of a source within `source_radius` px of the light.

    None when it cannot be known at trace time (a traced `density` or
    `num_samples`), is unbounded (a sample scale outside (0, 1]) or saves little.
    """
    if isinstance(density, jax.core.Tracer) or isinstance(num_samples, jax.core.Tracer):
        return None
    density, count = float(np.asarray(density)), float(np.asarray(num_samples))
    # Sample i (1-based) sits at scale 1 - i * density / count; the relaxation
    # weights it clip(count - i + 1, 0, 1), so the last live one is below count + 1.
    last = min(loop_length, math.ceil(count)) if relaxed else loop_length
    smallest_scale = 1.0 - last * density / count if count > 0 else 1.0
    if not (density >= 0 and smallest_scale > 0):
        return None
    # Bilinear samples reach one texel past the source; one more for rounding.
    reach = math.ceil((source_radius + 2.0) / smallest_scale)
    height, width = min(shape[0], 2 * reach + 2), min(shape[1], 2 * reach + 2)
    if height * width > shape[0] * shape[1] // 2:
        return None
    return height, width, reach


def scale_iterated_flares(
    masked: Float[Array, "H W C"],
    light_xy: Float[ArrayLike, "2"],
    *,
    num_iters: int | Float[ArrayLike, ""],
    scale_step: Float[ArrayLike, ""],
    decay: Float[ArrayLike, ""] = 1.0,
    max_iters: int | None = None,
) -> Float[Array, "H W C"]:
    """kbEngine's "flare-outs": the masked flare texture repeatedly scaled about the light.

    `sum_{k=0..n-1} decay**k * masked(light + (p - light) / scale_step**k)`: copy `k`
    is the texture enlarged `scale_step**k` times about the light, sampled
    bilinearly; texels outside the image are 0 (a copy never smears the border).
    Copy 0 is `masked` itself. The sum is not normalised (seed 002 adds every
    copy into its target); scale it in the effect. Value and gradient need
    memory O(image), not O(iterations x image).

    Args:
        masked: the masked flare texture (flare times sky mask).
        light_xy: the centre of scaling, in pixels; may be off screen.
        num_iters: copies. A Python int >= 1 is exact; a float `n` is the
            relaxation: copy `k` (k = 0..max_iters-1) weighted `clip(n - k, 0, 1)`,
            equal to the exact sum at integer `n`.
        scale_step: scale between successive copies (kbEngine3: 1.03). Values
            below 1 shrink the copies toward the light.
        decay: per-copy intensity factor.
        max_iters: static loop length for a relaxed `num_iters`.
    """
    check_image(masked, "masked")
    return _scale_iterated_flares(
        _identity, (jnp.asarray(masked),), light_xy, num_iters=num_iters, scale_step=scale_step, decay=decay,
        max_iters=max_iters,
    )  # fmt: skip


def _flare_scales(loop_length: int, scale_step):
    """kbEngine's copy scales `scale_step**-k` (k = 0..loop_length-1)."""
    return _powers(1.0 / scale_step, loop_length, scale_step.dtype)


def _scale_iterated_flares(image_fn, image_args, light_xy, *, num_iters, scale_step, decay=1.0, max_iters=None):
    """`scale_iterated_flares(image_fn(*image_args), ...)`, differentiated like `_radial_rays`."""
    check_light(light_xy)
    check_scalar(scale_step, "scale_step")
    check_scalar(decay, "decay")
    loop_length, relaxed = resolve_count(num_iters, max_iters, "num_iters", "max_iters")
    dtype = jax.eval_shape(image_fn, *image_args).dtype
    if relaxed:
        count = checked_count(num_iters, loop_length, "num_iters", "max_iters", dtype)
    else:
        count = jnp.asarray(num_iters, dtype)
    schedule = (functools.partial(_flare_scales, loop_length), functools.partial(_faded_powers, loop_length, relaxed))
    schedule_args = ((jnp.asarray(scale_step, dtype),), (jnp.asarray(decay, dtype), count))
    return _scaled_copies(image_fn, schedule, "zero", image_args, jnp.asarray(light_xy, dtype), schedule_args)
