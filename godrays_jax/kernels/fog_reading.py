"""The reading: every pixel takes the march rays' light up to its own depth, from its four nearest rays.

On a coarse grid of march rays (`fog_march`) a pixel reads each of its four
nearest rays' in-scattering up to its own depth, the segment holding that
depth taken in proportion to the light it receives up to there, and takes
them by bilinear weights at the rays' true positions. A ray's split only
placed its segments' bounds: when a surface's edge slides under a ray (a
pan), what it reads at a depth changes by the sampling alone.
"""

import jax
import jax.numpy as jnp

from godrays_jax.kernels.fog_march import MarchedPieces, segment_fraction
from godrays_jax.primitives.sampling import bilinear_corners


def read_at_depth(marched: MarchedPieces, piece: int, row, col, ray_end):
    """The in-scattering along the march rays `(row, col)` up to `ray_end` (clamped to the piece's bounds) from
    the segments of piece `piece` of `marched`, the segment holding `ray_end` taken in proportion to the light it
    receives up to there (in the coordinate even in the light's irradiance: a point light's falls off within a
    segment near it)."""
    count = marched.lit.shape[-1]
    first, last, optical = (values[piece, row, col] for values in (marched.firsts, marched.lasts, marched.opticals))
    distance = jnp.clip(ray_end, first, last)
    # `last >= first`; an empty piece reads 0 at its start. Not `safe_divide`: its select on `|last - first|`
    # made XLA's algebraic simplifier mix the lanes of the fit's vmapped Jacobian (`pipeline/fit.py`,
    # `fit_programs.forward_mode`) once a loss took `abs` of the image (tests/test_fit.py).
    length = jnp.where(last > first, last - first, 1.0)
    segments_before = jax.lax.stop_gradient(segment_fraction((distance - first) / length, optical) * count)
    index = jnp.clip(jnp.floor(segments_before), 0, count - 1).astype(jnp.int32)
    # The segment's bounds as the march placed them (`bound_fraction`), in the irradiance's coordinate.
    start, end = (marched.light_bounds[piece, row, col, index + offset] for offset in (0, 1))
    reached = marched.even_in_light(distance, row, col)
    share = jnp.clip((reached - start) / jnp.where(end > start, end - start, 1.0), 0.0, 1.0)
    return marched.lit_before[piece, row, col, index] + marched.lit[piece, row, col, index] * share


def upsample_by_depth(marched: MarchedPieces, ray_end, xs, ys, spacing, first_row=0):
    """The in-scattering of the march rays at `(xs, ys)` (`spacing` pixels apart; their pieces `marched`) at
    every pixel of the rows from `first_row` on: each of its four nearest rays read up
    to the pixel's own `ray_end` (`(rows, W)`, scene units, `inf` on sky: read as it is, so that a read beyond a
    piece's end takes the piece whole with the piece's own derivatives), by bilinear weights at the rays' true
    positions."""
    height, width = ray_end.shape
    pieces, small_h, small_w, _ = marched.lit.shape
    dtype = marched.lit.dtype
    x = (jnp.arange(width, dtype=dtype) + 0.5 - xs[0]) / spacing
    y = (jnp.arange(height, dtype=dtype) + first_row + 0.5 - ys[0]) / spacing
    row, col, tent = bilinear_corners(x[None, :], y[:, None], small_h, small_w)
    read = sum(read_at_depth(marched, piece, row, col, ray_end) for piece in range(pieces))
    return jnp.sum(tent * read, axis=0)
