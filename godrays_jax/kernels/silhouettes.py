"""How much of each pixel its surface covers at a silhouette, and what the rest of the pixel sees.

A renderer's pixel filter blends a silhouette pixel's colour from both sides
while its depth buffer keeps one depth per pixel; an effect that lights each
pixel by its depth (`kernels.volumetric`) blends its terms for both sides by
these shares. Planes are `(H, W)`, depth in scene units along each ray
(`inf` on sky), colour linear.
"""

import functools

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

# The share of a pixel's filter that falls on each neighbour in each direction (silhouette_mix).
_FILTER_SPILL = 0.15
# How far apart the brightness (the mean of the colour channels) of a silhouette's two sides must be for the pixel's
# to say how much of it each covers, in units of how much each side's varies (display space, x / (1 + x)) plus a
# floor: no trust below the first, full trust from their sum on.
_UNMIX_CONTRAST, _UNMIX_RAMP, _UNMIX_FLOOR = 3.0, 3.0, 0.002
# Depths within this fraction of a surface's depth belong to that surface (silhouette_mix).
_SAME_SURFACE = 0.05
# The pixels whose sides are found at once on a large frame (`silhouette_mix`: whole rows).
_BAND_PIXELS = 1 << 17
# The silhouette pixels whose colour is read at once (`silhouette_mix`); a frame with more reads them in turns.
_READ_PIXELS = 1 << 16
# Two surfaces meet at a silhouette where a neighbour's depth is this many times the pixel's, or less than 1 / it.
_SILHOUETTE_RATIO = 1.1


def _neighbours(plane):
    """The eight neighbours of every pixel of an `(H, W)` plane (edge pixels repeated at the border), a list."""
    height, width = plane.shape
    padded = jnp.pad(plane, 1, mode="edge")
    return [padded[dy : dy + height, dx : dx + width] for dy in range(3) for dx in range(3) if (dy, dx) != (1, 1)]


def _on(depth, surface_depth):
    """Whether `depth` lies on the surface at `surface_depth` (within `_SAME_SURFACE`; `inf`: the sky)."""
    finite = jnp.isfinite(depth)
    near = finite & (jnp.abs(jnp.where(finite, depth, 0.0) - surface_depth) <= _SAME_SURFACE * surface_depth)
    return jnp.where(jnp.isfinite(surface_depth), near, ~finite)


# Batcher's sorting network for eight values (19 compare-exchanges): the median of a pixel's neighbours with min and
# max on whole planes, where a sort along a short axis costs many times more.
_SORT_EIGHT = ((0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6), (3, 7), (0, 1), (2, 3), (4, 5), (6, 7),
               (2, 4), (3, 5), (1, 4), (3, 6), (1, 2), (3, 4), (5, 6))  # fmt: skip


def _median_of_members(values, members):
    """Per pixel, the median of the eight planes `values` over those where `members` holds (NaN where none)."""
    ordered = [jnp.where(member, value, jnp.inf) for value, member in zip(values, members)]
    for i, j in _SORT_EIGHT:
        ordered[i], ordered[j] = jnp.minimum(ordered[i], ordered[j]), jnp.maximum(ordered[i], ordered[j])
    count = sum(member.astype(jnp.int32) for member in members)
    low, high = jnp.full_like(ordered[0], jnp.nan), jnp.full_like(ordered[0], jnp.nan)
    for k, value in enumerate(ordered):
        low = jnp.where((count - 1) // 2 == k, value, low)
        high = jnp.where(count // 2 == k, value, high)
    return 0.5 * (low + high), count


def _unmixed_share(brightness, depth, first, second, depths, values):
    """`(share, trust)`: how much of each pixel the surface at `first` covers against the one at `second`
    (depths; `inf`: the sky), read from its brightness (the mean of its colour channels), and how far to trust that;
    `depths` and `values` its eight neighbours' depths and brightnesses. Any shape, pixel by pixel.

    The pixel's brightness is taken as a mix of each side's (the median of its
    neighbours on that side): the share is where it lies between them, clipped
    to [0, 1]. A pixel with no neighbour on its own side is its own sample of
    it. Medians, so that a bright emitter beside the pixel does not stand for
    the sky.
    """
    display = lambda c: c / (1 + jnp.abs(c))

    def side(side_depth):
        """The side's brightness (median) and how much its members' vary (mean absolute deviation from it in
        display space, the largest left out: one emitter among them)."""
        members = [_on(d, side_depth) for d in depths]
        median, count = _median_of_members(values, members)
        deviations = [jnp.where(m, jnp.abs(display(v) - display(median)), 0.0) for v, m in zip(values, members)]
        deviation = (sum(deviations) - functools.reduce(jnp.maximum, deviations)) / jnp.maximum(count - 1, 1)
        some = count > 0
        return jnp.where(some, median, jnp.where(_on(depth, side_depth), brightness, jnp.nan)), jnp.where(some, deviation, 0.0)

    (first_value, first_spread), (second_value, second_spread) = side(first), side(second)
    known = jnp.isfinite(first_value) & jnp.isfinite(second_value)
    first_value, second_value = jnp.nan_to_num(first_value), jnp.nan_to_num(second_value)
    apart = first_value - second_value
    share = (brightness - second_value) * apart / jnp.maximum(apart * apart, 1e-20)
    contrast = jnp.abs(display(first_value) - display(second_value))
    noise = first_spread + second_spread + _UNMIX_FLOOR
    trust = jnp.where(known, jnp.clip((contrast / noise - _UNMIX_CONTRAST) / _UNMIX_RAMP, 0.0, 1.0), 0.0)
    return jnp.clip(share, 0.0, 1.0), trust


@jax.jit
def silhouette_mix(
    coverage: Float[Array, "H W"], depth: Float[Array, "H W"], color: Float[Array, "H W C"]
) -> tuple[Float[Array, "H W"], Float[Array, "H W"]]:
    """`(coverage, uncovered_depth)`: how much of each pixel its surface covers, and what the rest sees.

    A renderer's pixel filter blends each silhouette pixel's colour from both
    sides, while its depth is one side's (Cycles' `Z` is one sample's). Each
    pixel's surface is its own depth (on sky, its nearest neighbour's, as
    `kernels.volumetric` takes it); the rest of the pixel sees the sky, or at a
    silhouette between two surfaces (a neighbour more than `_SILHOUETTE_RATIO`
    times nearer or farther) the neighbour's depth most unlike its own. How
    much each side covers is read from the pixel's brightness (the mean of its
    colour channels) where the two sides' beside it differ enough to tell (by
    more than `_UNMIX_CONTRAST` times how much each side's varies, plus a
    floor, in display space; full trust `_UNMIX_RAMP` times further). Elsewhere: between two surfaces, the
    pixel's own; at the sky, the frame's coverage pass where it has one (any
    value strictly between 0 and 1, or a covered sky pixel: used as it is),
    else the pixel filter's spread of the depth's hard coverage, taps `[.15,
    .7, .15]` in each direction (`.15`: what Cycles' frames of
    `benchmarks/references/blender` blend across a silhouette, on average).
    """
    hard = jnp.all(coverage == jnp.isfinite(depth).astype(coverage.dtype))
    fallback, surface_depth, uncovered_depth, told = _sides_in_bands(coverage, depth, hard)
    # The shares are read off the frame, not fitted: no gradient flows through them into the colour or the depth.
    brightness = jnp.mean(color[..., :3].astype(coverage.dtype), axis=-1)
    read_off = jax.lax.stop_gradient((brightness, depth, surface_depth, uncovered_depth))
    trust, weighted = _read_where(told, *read_off)
    return weighted + (1.0 - trust) * fallback, uncovered_depth


def _sides_in_bands(coverage, depth, hard):
    """`_sides` of a large frame a band of rows at a time, each with the rows around it: every pixel reads only its
    eight neighbours, and a whole frame's at once (each neighbour's plane for each of its uses) weighed more than the
    fog itself. The frame's first and last rows repeated above and below it are what the whole frame's edge padding
    reads; the rows that fill the last band repeat its last and are cut off again."""
    height, width = coverage.shape
    band = max(_BAND_PIXELS // width, 1)
    if band >= height:
        return _sides(coverage, depth, hard)
    bands = -(-height // band)
    planes = [jnp.pad(plane, [(1, bands * band - height + 1), (0, 0)], mode="edge") for plane in (coverage, depth)]

    def one_band(first_row):
        rows = [jax.lax.dynamic_slice_in_dim(plane, first_row, band + 2) for plane in planes]
        return [term[1:-1] for term in _sides(*rows, hard)]

    sides = jax.lax.map(one_band, jnp.arange(bands) * band)
    return [side.reshape(bands * band, width)[:height] for side in sides]


def _sides(coverage, depth, hard):
    """`(fallback, surface_depth, uncovered_depth, told)` of every pixel (`silhouette_mix`): its coverage where the
    colour cannot tell, its surface's depth, what the rest of it sees, and whether its colour can tell (a surface
    with the other side among its neighbours: elsewhere the trust in the colour is 0)."""
    height, width = coverage.shape
    padded = jnp.pad(coverage, 1, mode="edge")
    taps = (_FILTER_SPILL, 1.0 - 2.0 * _FILTER_SPILL, _FILTER_SPILL)
    spread = sum(
        wy * wx * padded[dy : dy + height, dx : dx + width] for dy, wy in enumerate(taps) for dx, wx in enumerate(taps)
    )  # fmt: skip
    at_sky = jnp.where(hard, spread, coverage)
    around = _neighbours(depth)
    finite = jnp.isfinite(depth)
    surface_depth = jnp.where(finite, depth, functools.reduce(jnp.minimum, around))
    beside_sky = ~finite | ~functools.reduce(jnp.logical_and, [jnp.isfinite(a) for a in around])
    # Depths of 0 (a surface at the eye) have no ratio: such a pixel and its neighbours are not told apart.
    positive = finite & (depth > 0)
    own = jnp.where(positive, depth, 1.0)
    # The neighbour most unlike the pixel (the first of equals), by their depths' ratio, the larger over the smaller
    # (the order of the log of their ratio's size, without a log per neighbour).
    most_unlike, other = None, None
    for neighbour in around:
        both = positive & jnp.isfinite(neighbour) & (neighbour > 0)
        ratio = jax.lax.stop_gradient(jnp.where(both, neighbour, 1.0) / own)
        unlike = jnp.where(both, jnp.maximum(ratio, 1.0 / ratio), 1.0)
        if most_unlike is None:
            most_unlike, other = unlike, neighbour
        else:
            further = unlike > most_unlike
            most_unlike, other = jnp.where(further, unlike, most_unlike), jnp.where(further, neighbour, other)
    between_surfaces = ~beside_sky & (most_unlike > _SILHOUETTE_RATIO)
    uncovered_depth = jnp.where(between_surfaces, other, jnp.inf)
    # Between two surfaces the colour decides on every frame; at the sky, where the frame has no coverage pass.
    told = jnp.isfinite(surface_depth) & (hard | between_surfaces) & (between_surfaces | beside_sky)
    return jnp.where(between_surfaces, 1.0, at_sky), surface_depth, uncovered_depth, told


def _read_where(told, brightness, depth, surface_depth, uncovered_depth):
    """`(trust, trust * share)` planes of `_unmixed_share`, read only at the pixels `told` picks (0 elsewhere),
    `_READ_PIXELS` of them at a time: a silhouette is a thin share of a frame, and its reads (each side's median of
    eight neighbours) are most of the mix's work and memory."""
    height, width = depth.shape
    count = height * width
    chunk = min(_READ_PIXELS, count)
    total = jnp.sum(told, dtype=jnp.int32)
    # The told pixels in order, then the frame's size: past the frame, so that their reads are dropped.
    told_pixels = jnp.nonzero(told.reshape(count), size=count, fill_value=count)[0].astype(jnp.int32)
    planes = [plane.reshape(count) for plane in (brightness, depth, surface_depth, uncovered_depth)]
    # The eight neighbours of each pixel in the frame padded by its edges (`_neighbours`), by their flat offsets.
    padded = [jnp.pad(plane, 1, mode="edge").reshape(-1) for plane in (depth, brightness)]
    offsets = [dy * (width + 2) + dx for dy in range(3) for dx in range(3) if (dy, dx) != (1, 1)]

    def read_chunk(state):
        first, trust, weighted = state
        # A last chunk that would run past the list starts earlier instead (`dynamic_slice` clamps): it reads some
        # pixels again and writes the same values.
        pixels = jax.lax.dynamic_slice_in_dim(told_pixels, first, chunk)
        at = jnp.minimum(pixels, count - 1)
        corner = (at // width) * (width + 2) + at % width
        depths, values = ([plane[corner + offset] for offset in offsets] for plane in padded)
        share, chunk_trust = _unmixed_share(*[plane[at] for plane in planes], depths, values)
        trust = trust.at[pixels].set(chunk_trust, mode="drop")
        weighted = weighted.at[pixels].set(chunk_trust * share, mode="drop")
        return first + chunk, trust, weighted

    zeros = jnp.zeros(count, brightness.dtype)
    _, trust, weighted = jax.lax.while_loop(lambda state: state[0] < total, read_chunk, (jnp.int32(0), zeros, zeros))
    return trust.reshape(height, width), weighted.reshape(height, width)
