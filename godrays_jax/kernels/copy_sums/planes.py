"""The CPU memory layout of scaled copies: an image as stacked channel planes, sampled row by row.

Scaling about a point keeps x and y apart, so on a CPU each bilinear copy of
an image is two 1-D interpolations: whole rows, then, after a transpose, whole
rows again (the columns). `Planes` holds the layout; the functions here give
a copy's taps, its derivatives and the pixel offsets in it. Used by the CPU
loop (`cpu_loop`) and by the tangent loop of `copies`.
"""

import jax
import jax.numpy as jnp

from godrays_jax.primitives.sampling import Addressing, axis_taps


def _copy_positions(shape, light_xy, scale, dtype):
    """Sample positions `light + (p - light) * scale` of the pixel centres: xs (W,) and ys (H,)."""
    height, width = shape
    rows = jnp.arange(height, dtype=dtype) + 0.5
    cols = jnp.arange(width, dtype=dtype) + 0.5
    return light_xy[0] + (cols - light_xy[0]) * scale, light_xy[1] + (rows - light_xy[1]) * scale


def taps_and_slopes(size: int, u, addressing: Addressing):
    """`axis_taps` at texel coordinates `u`, plus the taps' weights' derivatives with respect to `u`."""
    taps, (_, _, low_slope, high_slope) = jax.jvp(
        lambda u: axis_taps(size, u, addressing), (u,), (jnp.ones_like(u),)
    )
    return taps, (taps[0], taps[1], low_slope, high_slope)


def _transposed_apart(step, values):
    """`_tiled_transpose(values)`, kept out of its consumers' fusions.

    XLA fuses a gather with the computation of its operand and then evaluates
    that operand once per gathered element, through strided transposed reads:
    far slower on a CPU than gathering from a stored array. A conditional is
    not fused with its surroundings, and its predicate (a loop counter
    `step >= 0`, always true) cannot be folded at compile time. The branch
    never taken fills the result with one of the values: a constant there
    (zeros) is hoisted out of an enclosing loop over blocks of rows and stored
    once per copy, and returning the values themselves (reshaped) made XLA
    copy them every step.
    """
    never_taken = lambda rows: jnp.broadcast_to(rows[0, 0], rows.shape[::-1])
    return jax.lax.cond(step >= 0, _tiled_transpose, never_taken, values)


class Planes:
    """An `(H, W, C)` image as stacked channel planes: `(C*H, W)` by rows, `(W, C*H)` by columns.

    Both interpolations of a copy then gather whole rows (contiguous slices)
    of a stored 2-D array, the columns' from the transposed rows; transposes
    are plain 2-D ones (XLA's CPU transposes of interleaved channels are
    several times slower), and every reduction reverse mode makes is over a
    2-D array (XLA's CPU library reduction is much slower over three
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
        return lerp_rows(by_rows, self.plane_taps(taps))

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
    both sides in cache. It also makes the result a stored
    array (XLA would give a plain 2-D transpose a column-major layout instead,
    and gathering rows from that is strided again).
    """
    rows, cols = values.shape
    tile_rows, tile_cols = _tile(rows), _tile(cols)
    blocks = values.reshape(rows // tile_rows, tile_rows, cols // tile_cols, tile_cols)
    return blocks.transpose(2, 3, 0, 1).reshape(cols, rows)


def lerp_rows(values, taps):
    """Interpolation between whole rows of a 2-D array: `values[low] * low_weight + values[high] * high_weight`."""
    low, high, low_weight, high_weight = taps
    lower = values.at[low].get(mode="promise_in_bounds")
    upper = values.at[high].get(mode="promise_in_bounds")
    return lower * low_weight[:, None] + upper * high_weight[:, None]


def copy_taps(planes: Planes, light_xy, scale, addressing: Addressing, dtype):
    """Row and column taps (with the weights' slopes) of the copy sampled at `light + (p - light) * scale`."""
    xs, ys = _copy_positions((planes.height, planes.width), light_xy, scale, dtype)
    return taps_and_slopes(planes.width, xs - 0.5, addressing), taps_and_slopes(planes.height, ys - 0.5, addressing)


def offsets(planes: Planes, light_xy, dtype):
    """Pixel centres minus the light in the column layout `(W, C*H)`, where a pixel's x is its row and y its column."""
    col_offsets = (jnp.arange(planes.width, dtype=dtype) + 0.5 - light_xy[0])[:, None]
    row_offsets = planes.along_columns(jnp.arange(planes.height, dtype=dtype) + 0.5 - light_xy[1])
    return col_offsets, row_offsets


def copy_derivatives(planes: Planes, by_rows, k, columns, col_taps, col_slopes, row_slopes):
    """A copy's x and y derivatives (at its sample positions) in the column layout."""
    x_derivative = lerp_rows(columns, col_slopes)
    y_derivative = lerp_rows(planes.rows_to_columns(k, planes.sample_rows(by_rows, row_slopes)), col_taps)
    return x_derivative, y_derivative
