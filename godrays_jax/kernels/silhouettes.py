"""How much of each pixel its surface covers at a silhouette, and what the rest of the pixel sees.

A renderer's pixel filter blends a silhouette pixel's colour from both sides
while its depth buffer keeps one depth per pixel; an effect that lights each
pixel by its depth (`kernels.volumetric`) blends its terms for both sides by
these shares. Planes are `(H, W)`, depth in scene units along each ray
(`inf` on sky), colour linear.
"""

import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

# The share of a pixel's filter that falls on each neighbour in each direction (silhouette_mix).
_FILTER_SPILL = 0.15
# How far apart the colours of a silhouette's two sides must be for the pixel's colour to say how much of it each
# covers, in units of how much each side's colours vary (display space, x / (1 + x), mean over channels) plus a
# floor: no trust below the first, full trust from their sum on.
_UNMIX_CONTRAST, _UNMIX_RAMP, _UNMIX_FLOOR = 3.0, 3.0, 0.002
# Depths within this fraction of a surface's depth belong to that surface (silhouette_mix).
_SAME_SURFACE = 0.05
# Two surfaces meet at a silhouette where a neighbour's depth is this many times the pixel's, or less than 1 / it.
_SILHOUETTE_RATIO = 1.1


def _neighbours(plane):
    """The eight neighbours of every pixel (edge pixels repeated at the border), stacked along a new first axis."""
    height, width = plane.shape[:2]
    pad = [(1, 1), (1, 1)] + [(0, 0)] * (plane.ndim - 2)
    padded = jnp.pad(plane, pad, mode="edge")
    return jnp.stack([padded[dy : dy + height, dx : dx + width] for dy in range(3) for dx in range(3) if (dy, dx) != (1, 1)])


def _on(depths, surface_depth):
    """Whether each of `depths` lies on the surface at `surface_depth` (within `_SAME_SURFACE`; `inf`: the sky)."""
    finite = jnp.isfinite(depths)
    near = finite & (jnp.abs(jnp.where(finite, depths, 0.0) - surface_depth) <= _SAME_SURFACE * surface_depth)
    return jnp.where(jnp.isfinite(surface_depth), near, ~finite)


def _unmixed_share(color, depth, first, second):
    """`(share, trust)`: how much of each pixel the surface at `first` covers against the one at `second`
    (depths; `inf`: the sky), read from its colour, and how far to trust that.

    The pixel's colour is taken as a mix of each side's colour (the median of
    its neighbours on that side): the share is the projection of the colour on
    the segment between them, clipped to [0, 1]. A pixel with no neighbour on
    its own side is its own sample of it. Medians, so that a bright emitter
    beside the pixel does not stand for the sky.
    """
    color = color[..., :3]
    depths, colors = _neighbours(depth), _neighbours(color)
    display = lambda c: c / (1 + jnp.abs(c))  # noqa: E731
    def side(side_depth):
        """The side's colour (median) and how much its members' colours vary (mean absolute deviation from it,
        the largest left out: one emitter among them)."""
        members = _on(depths, side_depth)
        among = jnp.where(members[..., None], colors, jnp.nan)
        median = jnp.nanmedian(among, axis=0)
        deviations = jnp.where(members[..., None], jnp.abs(display(colors) - display(median)), 0.0)
        count = jnp.sum(members, axis=0)[..., None]
        deviation = (jnp.sum(deviations, axis=0) - jnp.max(deviations, axis=0)) / jnp.maximum(count - 1, 1)
        own = _on(depth, side_depth)[..., None]
        some = jnp.any(members, axis=0)[..., None]
        return jnp.where(some, median, jnp.where(own, color, jnp.nan)), jnp.where(some, deviation, 0.0)

    (first_color, first_spread), (second_color, second_spread) = side(first), side(second)
    known = jnp.all(jnp.isfinite(first_color) & jnp.isfinite(second_color), axis=-1)
    first_color, second_color = jnp.nan_to_num(first_color), jnp.nan_to_num(second_color)
    apart = first_color - second_color
    share = jnp.sum((color - second_color) * apart, axis=-1) / jnp.maximum(jnp.sum(apart * apart, axis=-1), 1e-20)
    contrast = jnp.mean(jnp.abs(display(first_color) - display(second_color)), axis=-1)
    noise = jnp.mean(first_spread + second_spread, axis=-1) + _UNMIX_FLOOR
    trust = jnp.where(known, jnp.clip((contrast / noise - _UNMIX_CONTRAST) / _UNMIX_RAMP, 0.0, 1.0), 0.0)
    return jnp.clip(share, 0.0, 1.0), trust


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
    much each side covers is read from the pixel's colour where the two sides'
    colours beside it differ enough to tell (by more than `_UNMIX_CONTRAST`
    times how much each side's colours vary, plus a floor, in display space;
    full trust `_UNMIX_RAMP` times further). Elsewhere: between two surfaces, the
    pixel's own; at the sky, the frame's coverage pass where it has one (any
    value strictly between 0 and 1, or a covered sky pixel: used as it is),
    else the pixel filter's spread of the depth's hard coverage, taps `[.15,
    .7, .15]` in each direction (`.15`: what Cycles' frames of
    `benchmarks/references/blender` blend across a silhouette, on average).
    """
    hard = jnp.all(coverage == jnp.isfinite(depth).astype(coverage.dtype))
    height, width = coverage.shape
    padded = jnp.pad(coverage, 1, mode="edge")
    taps = (_FILTER_SPILL, 1.0 - 2.0 * _FILTER_SPILL, _FILTER_SPILL)
    spread = sum(
        wy * wx * padded[dy : dy + height, dx : dx + width] for dy, wy in enumerate(taps) for dx, wx in enumerate(taps)
    )  # fmt: skip
    at_sky = jnp.where(hard, spread, coverage)
    around = _neighbours(depth)
    finite = jnp.isfinite(depth)
    surface_depth = jnp.where(finite, depth, jnp.min(around, axis=0))
    beside_sky = ~finite | ~jnp.all(jnp.isfinite(around), axis=0)
    both = finite & jnp.isfinite(around)
    ratio = jax.lax.stop_gradient(jnp.where(both, around, 1.0) / jnp.where(finite, depth, 1.0))
    unlike = jnp.where(both, jnp.abs(jnp.log(ratio)), 0.0)
    other = jnp.take_along_axis(around, jnp.argmax(unlike, axis=0)[None], axis=0)[0]
    between_surfaces = ~beside_sky & (jnp.max(unlike, axis=0) > math.log(_SILHOUETTE_RATIO))
    uncovered_depth = jnp.where(between_surfaces, other, jnp.inf)
    # The shares are read off the frame, not fitted: no gradient flows through them into the colour or the depth.
    read_off = jax.lax.stop_gradient((color.astype(coverage.dtype), depth, surface_depth, uncovered_depth))
    share, trust = _unmixed_share(*read_off)
    # Between two surfaces the colour decides on every frame; at the sky, a coverage pass where the frame has one.
    trust = jnp.where(jnp.isfinite(surface_depth) & (hard | between_surfaces), trust, 0.0)
    fallback = jnp.where(between_surfaces, 1.0, at_sky)
    return trust * share + (1.0 - trust) * fallback, uncovered_depth
