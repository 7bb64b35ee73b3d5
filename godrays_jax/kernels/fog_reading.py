"""The reading: every pixel takes the march rays' light up to its own depth, from its four nearest rays.

On a coarse grid of march rays (`fog_march`) a pixel reads each of its four
nearest rays' in-scattering up to its own depth, the segment holding that
depth taken in proportion to the light it receives up to there, and takes
them by bilinear weights at the rays' true positions. A ray's split only
placed its segments' bounds: when a surface's edge slides under a ray (a
pan), what it reads at a depth changes by the sampling alone.
"""

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from godrays_jax.kernels.bounded_medium import irradiance_coordinate
from godrays_jax.kernels.fog_march import MarchedPieces, segment_fraction
from godrays_jax.primitives.sampling import bilinear_corners


def read_at_depth(marched: MarchedPieces, piece: int, row, col, ray_end):
    """The in-scattering along the march rays `(row, col)` up to `ray_end` (clamped to the piece's bounds) from
    the segments of piece `piece` of `marched`, the segment holding `ray_end` taken in proportion to the light it
    receives up to there (in the coordinate even in the light's irradiance: a point light's falls off within a
    segment near it)."""
    count = marched.lit.shape[-1]
    first, last, optical = (values[piece, row, col] for values in (marched.firsts, marched.lasts, marched.opticals))
    distance, index = _segment_holding(ray_end, first, last, optical, count)
    # The segment's bounds as the march placed them (`bound_fraction`), in the irradiance's coordinate.
    start, end = (marched.light_bounds[piece, row, col, index + offset] for offset in (0, 1))
    share = _share(marched.even_in_light(distance, row, col), start, end)
    return marched.lit_before[piece, row, col, index] + marched.lit[piece, row, col, index] * share


def _segment_holding(ray_end, first, last, optical, count):
    """`ray_end` clamped to a piece `[first, last]` of `count` segments placed by its optical depth `optical`
    (`bound_fraction`), and the index of the segment holding it."""
    distance = jnp.clip(ray_end, first, last)
    # `last >= first`; an empty piece reads 0 at its start. Not `safe_divide`: its select on `|last - first|`
    # made XLA's algebraic simplifier mix the lanes of the fit's vmapped Jacobian (`pipeline/fit.py`,
    # `fit_programs.forward_mode`) once a loss took `abs` of the image (tests/test_fit.py).
    length = jnp.where(last > first, last - first, 1.0)
    segments_before = jax.lax.stop_gradient(segment_fraction((distance - first) / length, optical) * count)
    return distance, jnp.clip(jnp.floor(segments_before), 0, count - 1).astype(jnp.int32)


def _share(reached, start, end):
    """The share of a segment `[start, end]` up to `reached` (in the irradiance's coordinate), in [0, 1]."""
    return jnp.clip((reached - start) / jnp.where(end > start, end - start, 1.0), 0.0, 1.0)


def read_every_piece(marched: MarchedPieces, row, col, ray_end):
    """The in-scattering along the march rays `(row, col)` up to `ray_end`: `read_at_depth` of every piece."""
    return sum(read_at_depth(marched, piece, row, col, ray_end) for piece in range(marched.lit.shape[0]))


class PackedPieces(NamedTuple):
    """`MarchedPieces` laid out for reading one piece per pixel (`pack_pieces`, `read_holding_piece`): two gathers
    per ray read, each of neighbouring values, where the pieces' own layout takes a dozen single values. Each ray's
    `rays` (`(h, w, 2 + 4 L)`): its `along`, `miss`, then each piece's first bound, last bound, optical depth and
    whole light; each segment's `segments` (`(L, h, w, M, 4)`): the light of the piece's segments before it, its
    own, and its bounds in the irradiance's coordinate."""

    rays: Float[Array, "h w K"]
    segments: Float[Array, "L h w M 4"]
    inverse: Float[ArrayLike, ""]


def pack_pieces(marched: MarchedPieces) -> PackedPieces:
    """`marched` as `PackedPieces`, once per frame for every pixel's reads."""
    wholes = marched.lit_before[..., -1] + marched.lit[..., -1]
    per_piece = [values[piece] for values in (marched.firsts, marched.lasts, marched.opticals, wholes)
                 for piece in range(marched.lit.shape[0])]  # fmt: skip
    rays = jnp.stack([marched.along, marched.miss, *per_piece], axis=-1)
    bounds = marched.light_bounds
    segments = jnp.stack([marched.lit_before, marched.lit, bounds[..., :-1], bounds[..., 1:]], axis=-1)
    return PackedPieces(rays, segments, marched.inverse)


def read_holding_piece(packed: PackedPieces, row, col, ray_end):
    """`read_every_piece`'s values to float rounding, reading only the piece that holds `ray_end`: the pieces before
    it whole, those after it nothing (a piece starts where the one before it ends), from `PackedPieces`. A fraction
    of reading every piece, for a forward pass (`volumetric.volumetric_fog_terms` takes derivatives through
    `read_every_piece`, whose reads a piece's end moves continuously)."""
    pieces, count = packed.segments.shape[0], packed.segments.shape[3]
    ray = packed.rays[row, col]
    along, miss = ray[..., 0], ray[..., 1]
    firsts, lasts, opticals, wholes = (ray[..., 2 + pieces * kind : 2 + pieces * (kind + 1)] for kind in range(4))
    before = [ray_end > lasts[..., piece] for piece in range(pieces - 1)]
    holding = sum(passed.astype(jnp.int32) for passed in before) if before else jnp.zeros_like(row)

    def held(values):  # the holding piece's value of `values` (`(..., L)`)
        return functools.reduce(
            lambda chosen, piece: jnp.where(holding == piece, values[..., piece], chosen), range(1, pieces), values[..., 0]
        )  # fmt: skip

    first, last, optical = held(firsts), held(lasts), held(opticals)
    distance, index = _segment_holding(ray_end, first, last, optical, count)
    segment = packed.segments[holding, row, col, index]
    reached = irradiance_coordinate(distance, along, miss, packed.inverse)
    within = _share(reached, segment[..., 2], segment[..., 3])
    whole = sum((jnp.where(passed, wholes[..., piece], 0.0) for piece, passed in enumerate(before)), start=0.0)
    return whole + segment[..., 0] + segment[..., 1] * within


def upsample_by_depth(marched: MarchedPieces, ray_end, xs, ys, spacing, first_row=0, *, pieces=read_every_piece):
    """The in-scattering of the march rays at `(xs, ys)` (`spacing` pixels apart; their pieces `marched`) at
    every pixel of the rows from `first_row` on: `read_by_depth` at the pixels' centres, `ray_end` `(rows, W)`."""
    height, width = ray_end.shape
    dtype = xs.dtype
    x = jnp.arange(width, dtype=dtype) + 0.5
    y = jnp.arange(height, dtype=dtype) + first_row + 0.5
    return read_by_depth(marched, ray_end, x[None, :], y[:, None], xs, ys, spacing, pieces=pieces)


def read_by_depth(marched: MarchedPieces, ray_end, x, y, xs, ys, spacing, *, pieces=read_every_piece):
    """The in-scattering of the march rays at `(xs, ys)` (`spacing` pixels apart; their pieces `marched`) at the
    pixel positions `(x, y)` (pixels, broadcast with `ray_end`): each of its four nearest rays read up to its own
    `ray_end` (scene units, `inf` on sky: read as it is, so that a read beyond a piece's end takes the piece whole
    with the piece's own derivatives), by bilinear weights at the rays' true positions. `pieces`: how a ray is read
    through its pieces (`read_every_piece`, `read_holding_piece`)."""
    row, col, tent = bilinear_corners((x - xs[0]) / spacing, (y - ys[0]) / spacing, ys.shape[0], xs.shape[0])
    return jnp.sum(tent * pieces(marched, row, col, ray_end), axis=0)


def blend_where_partly_covered(terms, covered, uncovered_depth, other_side, *, chunk: int):
    """The planes `terms` (`(H, W)` each: every pixel's own side), blended at the pixels partly covered
    (`0 < covered < 1`) with what their uncovered part sees, `covered * own + (1 - covered) * other`, where
    `other_side(x, y, ray_end)` gives `other`'s planes at pixel centres `(x, y)` up to `uncovered_depth`; read
    `chunk` pixels at a time. A silhouette is a thin share of a frame, and reading its other side at every pixel
    was a large part of the fog's forward (benchmarks/README.md, "The fit as users run it")."""
    height, width = covered.shape
    count = height * width
    chunk = min(chunk, count)
    dtype = terms[0].dtype
    partly = ((covered > 0) & (covered < 1)).reshape(count)
    total = jnp.sum(partly, dtype=jnp.int32)
    # The partly covered pixels in order, then the frame's size: past the frame, so that their writes are dropped.
    pixels = jnp.nonzero(partly, size=count, fill_value=count)[0].astype(jnp.int32)
    own = [plane.reshape(count) for plane in terms]
    shares, depths = covered.reshape(count), uncovered_depth.reshape(count)

    def read_chunk(state):
        first, planes = state
        # A last chunk that would run past the list starts earlier instead (`dynamic_slice` clamps): it reads some
        # pixels again and writes the same values (blended from `own`, not from what is written).
        chosen = jax.lax.dynamic_slice_in_dim(pixels, first, chunk)
        at = jnp.minimum(chosen, count - 1)
        x, y = (at % width).astype(dtype) + 0.5, (at // width).astype(dtype) + 0.5
        share = shares[at]
        others = other_side(x, y, depths[at])
        planes = tuple(
            plane.at[chosen].set(share * mine[at] + (1.0 - share) * other, mode="drop")
            for plane, mine, other in zip(planes, own, others)
        )  # fmt: skip
        return first + chunk, planes

    _, planes = jax.lax.while_loop(lambda state: state[0] < total, read_chunk, (jnp.int32(0), tuple(own)))
    return tuple(plane.reshape(height, width) for plane in planes)
