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

from godrays_jax.kernels.fog_march import (
    MarchedPieces,
    bound_fraction,
    segment_fraction,
)
from godrays_jax.primitives.sampling import bilinear_corners


def read_at_depth(lit, first, last, optical, even_in_light, row, col, ray_end):
    """The in-scattering along the march rays `(row, col)` up to `ray_end` (clamped to the piece's bounds) from
    one piece's segments' light `lit` (`(h, w, M)`, segments from `first` to `last`, each `(h, w)`, placed by
    the piece's optical depth `optical` as `bound_fraction` places them), the
    segment holding `ray_end` taken in proportion to the light it receives up to there (`even_in_light`: a
    function of distances along the rays, rows and columns, even in the light's irradiance; a point light's
    falls off within a segment near it)."""
    count = lit.shape[-1]
    first, last, optical = first[row, col], last[row, col], optical[row, col]
    distance = jnp.clip(ray_end, first, last)
    # `last >= first`; an empty piece reads 0 at its start. Not `safe_divide`: its select on `|last - first|`
    # made XLA's algebraic simplifier mix the lanes of the fit's vmapped Jacobian (`pipeline/fit.py`,
    # `fit_programs.forward_mode`) once a loss took `abs` of the image (tests/test_fit.py).
    length = jnp.where(last > first, last - first, 1.0)
    segments_before = jax.lax.stop_gradient(segment_fraction((distance - first) / length, optical) * count)
    index = jnp.clip(jnp.floor(segments_before), 0, count - 1)
    lower, upper = (first + length * bound_fraction((index + offset) / count, optical) for offset in (0.0, 1.0))
    start, reached, end = (even_in_light(u, row, col) for u in (lower, distance, upper))
    share = jnp.clip((reached - start) / jnp.where(end > start, end - start, 1.0), 0.0, 1.0)
    index = index.astype(jnp.int32)
    before = jnp.cumsum(lit, axis=-1) - lit
    return before[row, col, index] + lit[row, col, index] * share


def upsample_by_depth(marched: MarchedPieces, ray_end, xs, ys, spacing, first_row=0):
    """The in-scattering of the march rays at `(xs, ys)` (`spacing` pixels apart; their pieces `marched`) at
    every pixel of the rows from `first_row` on: each of its four nearest rays read up
    to the pixel's own `ray_end` (`(rows, W)`, scene units, `inf` on sky: read as it is, so that a read beyond a
    piece's end takes the piece whole with the piece's own derivatives), by bilinear weights at the rays' true
    positions."""
    lit, firsts, lasts, opticals, even_in_light = marched
    height, width = ray_end.shape
    _, small_h, small_w, _ = lit.shape
    dtype = lit.dtype
    x = (jnp.arange(width, dtype=dtype) + 0.5 - xs[0]) / spacing
    y = (jnp.arange(height, dtype=dtype) + first_row + 0.5 - ys[0]) / spacing
    row, col, tent = bilinear_corners(x[None, :], y[:, None], small_h, small_w)
    read = sum(read_at_depth(*piece, even_in_light, row, col, ray_end) for piece in zip(lit, firsts, lasts, opticals))
    return jnp.sum(tent * read, axis=0)
