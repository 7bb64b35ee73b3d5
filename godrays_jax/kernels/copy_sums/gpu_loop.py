"""The GPU loop that sums scaled copies: 2-D gathers of each copy's four bilinear corners.

`COPIES_PER_STEP` copies per loop step (the loop unrolled), which XLA fuses
into one kernel. GPU timings: `benchmarks/README.md`.
"""

import jax
import jax.numpy as jnp

from godrays_jax.kernels.copy_sums.planes import taps_and_slopes

COPIES_PER_STEP = 8
"""Copies a GPU sums per loop step (the loop unrolled), each from 2-D gathers of its four bilinear corners.

XLA fuses a step's gathers and the copies' sum into one kernel and stores no
copy, far faster on a GPU than one copy per step through `Planes`'
transposes. When several sums read the copies (the derivative sums) XLA
stores the step's gathered values instead. GPU figures: `benchmarks/README.md`.
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


def copy_sums_gpu(addressing, light_varies, image, derivative_image, light_xy, scales, weights, jacobians):
    """`copy_sums` for a GPU: one copy per loop step, unrolled `COPIES_PER_STEP` times so XLA fuses those copies."""
    height, width, _ = image.shape
    dtype = image.dtype
    x_offsets = jnp.arange(width, dtype=dtype) + 0.5 - light_xy[0]
    y_offsets = jnp.arange(height, dtype=dtype) + 0.5 - light_xy[1]
    scale_jacobian, weight_jacobian = jacobians
    moves = scale_jacobian is not None or light_varies

    def add_copy(k, sums):
        total, derivative_total, scale_sums, weight_sums, light_sums = sums
        scale, weight = scales[k], weights[k]
        col_taps, col_slopes = taps_and_slopes(width, light_xy[0] + x_offsets * scale - 0.5, addressing)
        row_taps, row_slopes = taps_and_slopes(height, light_xy[1] + y_offsets * scale - 0.5, addressing)
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
        """`(H, W, C, ...)` in `Planes`' column layout `(W, C*H, ...)`."""
        moved = jnp.moveaxis(values, (1, 2, 0), (0, 1, 2))
        return moved.reshape((width, values.shape[2] * height) + values.shape[3:])

    return (
        as_columns(total),
        None if derivative_image is None else as_columns(derivative_total),
        *(None if number_sums is None else as_columns(jnp.stack(number_sums, axis=-1))
          for number_sums in (scale_sums, weight_sums)),
        None if light_sums is None else tuple(as_columns(light_sum) for light_sum in light_sums),
    )
