"""The CPU loop that sums scaled copies: one copy per step, rows gathered, transposed, gathered again.

Large images are summed in blocks of output rows so that a block's sums stay
in cache (`BLOCKED_SIZE`, `ROWS_PER_BLOCK`); how much that saves is measured
in `benchmarks/fit_results.md`.
"""

import jax
import jax.numpy as jnp

from godrays_jax.kernels.copy_sums.planes import Planes, copy_taps, lerp_rows, offsets

BLOCKED_SIZE = 2**21
"""Images of at least this many numbers (`H * W` times the planes sampled) are summed in blocks of output rows on a CPU.

All copies of one block of `ROWS_PER_BLOCK` output rows are summed before the
next block, so a block's sums and rows stay in cache instead of streaming
through memory once per copy. A step samples the image's planes, and for
derivatives also their y-slopes and any derivative image's planes. Once an
image's planes outgrow the cache, blocks are faster; below this size they cost
more than they save. The threshold was chosen from the measurements in
`benchmarks/fit_results.md` ("blocks of rows").
"""


ROWS_PER_BLOCK = 64
"""Output rows per block: the divisor of the image's height nearest to it, if within a factor 2 of it."""


def rows_per_block(height: int, width: int, channels: int) -> int:
    """Rows per block, or `height` (one block) for a small image or a height with no divisor near `ROWS_PER_BLOCK`."""
    if height * width * channels < BLOCKED_SIZE:
        return height
    rows = min((d for d in range(1, height + 1) if height % d == 0), key=lambda d: abs(d - ROWS_PER_BLOCK))
    # Blocks of a few rows (a prime height) would cost a loop step per copy and row.
    return rows if ROWS_PER_BLOCK // 2 <= rows <= 2 * ROWS_PER_BLOCK else height


def copy_sums_cpu(addressing, light_varies, image, derivative_image, light_xy, scales, weights, jacobians):
    """`copy_sums` for a CPU: one copy per loop step, as rows gathered, transposed and gathered again (`Planes`).

    Every plane a step samples (the image's; the derivative image's; for
    derivatives in the scales or the light, the image's y-slopes) is
    interpolated between rows by one gather of the stacked planes and
    transposed as one array: XLA fuses a gather into its consumer only when
    it has one, and stores it otherwise. Large images are summed block by
    block of output rows (`BLOCKED_SIZE`).
    """
    dtype = image.dtype
    planes = Planes(image.shape)
    stacked_rows = planes.by_rows(image)
    if derivative_image is not None:
        derivative_planes = Planes(derivative_image.shape)
        stacked_rows = jnp.concatenate([stacked_rows, derivative_planes.by_rows(derivative_image)])
    scale_jacobian, weight_jacobian = jacobians
    moves = scale_jacobian is not None or light_varies
    height, width, channels = planes.height, planes.width, planes.channels
    derivative_channels = 0 if derivative_image is None else derivative_planes.channels
    block = rows_per_block(height, width, channels * (2 if moves else 1) + derivative_channels)
    col_offsets, _ = offsets(planes, light_xy, dtype)
    # The transposed planes' columns: the image's, the derivative image's, the y-slopes'.
    image_width, derivative_width = channels * block, derivative_channels * block

    def sums_of_block(first_row):
        """The sums for output rows `first_row .. first_row + block` of every plane: `(W, C * block)` each."""
        rows = jax.lax.dynamic_slice_in_dim(jnp.arange(height, dtype=dtype) + 0.5 - light_xy[1], first_row, block)
        row_offsets = jnp.tile(rows, channels)[None, :]

        def add_copy(k, sums):
            total, derivative_total, scale_sums, weight_sums, light_sums = sums
            (col_taps, col_slopes), (row_taps, row_slopes) = copy_taps(planes, light_xy, scales[k], addressing, dtype)
            row_taps, row_slopes = (
                tuple(jax.lax.dynamic_slice_in_dim(values, first_row, block) for values in taps)
                for taps in (row_taps, row_slopes)
            )
            plane_taps = [planes.plane_taps(row_taps)]
            if derivative_image is not None:
                plane_taps.append(derivative_planes.plane_taps(row_taps, first=channels * height))
            if moves:
                plane_taps.append(planes.plane_taps(row_slopes))
            sampled_rows = lerp_rows(stacked_rows, tuple(jnp.concatenate(parts) for parts in zip(*plane_taps)))
            columns = planes.rows_to_columns(k, sampled_rows)
            image_columns = columns[:, :image_width]
            copy = lerp_rows(image_columns, col_taps)
            total = total + weights[k] * copy
            if derivative_image is not None:
                derivative_columns = columns[:, image_width : image_width + derivative_width]
                derivative_total = derivative_total + weights[k] * lerp_rows(derivative_columns, col_taps)
            if moves:
                x_derivative = lerp_rows(image_columns, col_slopes)
                y_derivative = lerp_rows(columns[:, image_width + derivative_width :], col_taps)
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
