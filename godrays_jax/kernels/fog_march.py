"""The march: view rays through the medium in pieces, each piece's segments lit by the light they see.

A march ray runs through the bounded medium (`bounded_medium`) in
consecutive pieces (`scattered_pieces`; the last to the medium's end), each
in `num_view_steps` segments even in transmittance rather than in distance
(`bound_fraction`: in dense haze most of the light reaching the camera comes
from its first stretch). A segment's light is single scattering in closed
form: the transmittance from the camera across it, the light dimmed on its
way in, its irradiance (a point light's falls off), the phase function at
the angle to the light and the segment's visibility of the light
(`shadow_reading`), each taken where the segment's light comes from (near a
point light, the ray's closest approach). On a coarse grid the rays sit at
the light's position plus multiples of the spacing (`march_grid`), so under
a pan they ride with the scene. `volumetric` has the whole model.
"""

import math
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from godrays_jax.kernels.bounded_medium import (
    BoundedMedium,
    dot,
    irradiance_coordinate,
    irradiance_median,
    is_static_sun,
    light_approach,
    light_cosine,
    light_transmittance,
    medium_interval,
    optical_depth,
    safe_divide,
    segment_irradiance,
    toward_light,
)
from godrays_jax.kernels.media import henyey_greenstein

PHASE_NODES = 6
"""Gauss-Legendre points a segment's phase is averaged over near a point light on each side of the ray's closest
approach (`segment_phase`): near the exact mean for haze's anisotropies over any stretch of angle, coarser toward the
strongest fog's (benchmarks/README.md, "Several lights: a street of two lamps", has the errors)."""

# A piece's segments are even in the transmittance of a homogeneous medium of the piece's optical depth, taken
# at most this deep: beyond it the first segments are short enough, and float32 would lose the last bound's place.
_DEEPEST_PLACEMENT = 12.0


class MarchedPieces(NamedTuple):
    """March rays' pieces (`scattered_pieces`), L pieces of M segments on `(h, w)` rays: each segment's light
    `lit` and the light of the piece's segments before it `lit_before` (`(L, h, w, M)`); each piece's first and
    last bound `firsts`, `lasts` (scene units) and its optical depth `opticals` (which places its bounds,
    `bound_fraction`), each `(L, h, w)`; each segment bound in a coordinate even in the light's irradiance
    `light_bounds` (`(L, h, w, M + 1)`, `irradiance_coordinate`), and the rays' `light_approach` (`along`, `miss`,
    `(h, w)`) with the light's `inverse` distance, for the same coordinate of any distance (`even_in_light`)."""

    lit: Float[Array, "L h w M"]
    lit_before: Float[Array, "L h w M"]
    firsts: Float[Array, "L h w"]
    lasts: Float[Array, "L h w"]
    opticals: Float[Array, "L h w"]
    light_bounds: Float[Array, "L h w M+1"]
    along: Float[Array, "h w"]
    miss: Float[Array, "h w"]
    inverse: Float[ArrayLike, ""]

    def even_in_light(self, distance, row, col):
        """`irradiance_coordinate` of distances along the rays `(row, col)`."""
        return irradiance_coordinate(distance, self.along[row, col], self.miss[row, col], self.inverse)


def bound_fraction(fraction, optical):
    """Where a piece's segment bound lies, as a fraction of the piece's length, for the bound at `fraction` of the
    segments (`k / num_view_steps`): even in `1 - T` through a homogeneous medium of optical depth `optical`
    over the piece, so that each segment holds an equal share of the light a lit piece scatters toward the
    camera (even in distance, dense haze spent most segments where its light no longer reaches the camera);
    even in distance as `optical` goes to 0. `fraction` in [0, 1], 1 on the piece's end exactly."""
    small = optical < 1e-4
    x = jnp.where(small, 1.0, jnp.minimum(optical, _DEEPEST_PLACEMENT))
    placed = -jnp.log1p(jnp.minimum(fraction, 1.0 - 1e-6) * jnp.expm1(-x)) / x
    return jnp.where(small, fraction, jnp.where(fraction >= 1.0, 1.0, placed))


def placement_depth(origin, view, first, end, medium: BoundedMedium):
    """The optical depth of each piece from `first` to `end` that places its segments (`bound_fraction`), held
    under differentiation. Where the segments lie is a sampling choice: its derivative is the sampling error's
    (large where a shadow's edge crosses a segment's middle), not the medium's, and in the fit's Jacobian it made
    every Levenberg-Marquardt step fail from a fog layer's start (docs/findings.md, "The placement is held under
    differentiation"). The bounds still move with the piece's ends, as before."""
    return jax.lax.stop_gradient(
        optical_depth(origin, view, first, end, **medium.density)
    )


def segment_fraction(fraction, optical):
    """`bound_fraction`'s inverse: for a point at `fraction` of a piece's length, the fraction of the segments
    before it (not floored)."""
    small = optical < 1e-4
    x = jnp.where(small, 1.0, jnp.minimum(optical, _DEEPEST_PLACEMENT))
    return jnp.where(small, fraction, jnp.expm1(-x * fraction) / jnp.expm1(-x))


def segment_phase(lower, upper, along, miss, inverse, medium: BoundedMedium):
    """The phase function's mean over each segment `[lower, upper]` of a view ray near a point light, weighted by
    the light's irradiance there (the ray's `light_approach`: `along`, `miss`): in the coordinate even in
    irradiance, `u = arctan((t - along) / miss)` (`irradiance_coordinate`), the mean is `p`'s plain mean over the
    segment's `u` (`light_cosine`), taken by Gauss-Legendre at `PHASE_NODES` points on each side of the closest
    approach. A segment that passes the light sweeps the angle from forward to backward; its middle alone (the angle
    across the ray) misses the forward peak, and a forward medium's halo near the light came out a fraction of a path
    tracer's."""
    start, end = (irradiance_coordinate(bound, along, miss, inverse) for bound in (lower, upper))
    # Split where the ray passes the light: a ray through it turns from looking at the light to looking away there.
    closest = jnp.clip(0.0, start, end)
    nodes, weights = (jnp.asarray(value, lower.dtype) for value in np.polynomial.legendre.leggauss(PHASE_NODES))

    def add(index, total):  # one node a pass, so that no array a node deep is held (nor one per lane in a fit)
        node, weight = nodes[index % PHASE_NODES], weights[index % PHASE_NODES]
        before = index < PHASE_NODES
        low, high = jnp.where(before, start, closest), jnp.where(before, closest, end)
        half = 0.5 * (high - low)
        cosine = light_cosine(0.5 * (low + high) + half * node, miss, inverse)
        return total + weight * half * henyey_greenstein(cosine, anisotropy=medium.anisotropy)

    zero = jnp.zeros(jnp.broadcast_shapes(start.shape, miss.shape), start.dtype)
    total = jax.lax.fori_loop(0, 2 * PHASE_NODES, add, zero)
    at_start = henyey_greenstein(light_cosine(start, miss, inverse), anisotropy=medium.anisotropy)
    return safe_divide(total, end - start, at_start, tiny=1e-12)


def march_grid(light_xy, height, width, spacing, dtype):
    """Pixel positions `(xs, ys)` (`(w,)`, `(h,)`) of the march rays: the light's position plus `spacing` times integers.

    Anchored to the light, not to the pixels: under a pan the rays ride with the scene and its light, and any
    spacing works on any frame size. The count is static, the screen `[0, width] x [0, height]` plus one
    spacing on each side wherever the light is: only the light's position modulo `spacing` counts, so a far
    off-screen light is fine. No gradient flows through the grid's phase: where the rays sit is a sampling
    choice, and its derivative (of order one whatever the light's distance) is the sampling error's, which for
    a light millions of pixels away swamps the light's true, vanishing effect and overflows.
    """
    anchor = jnp.mod(jax.lax.stop_gradient(jnp.asarray(light_xy, dtype)), spacing) - spacing
    xs = anchor[0] + spacing * jnp.arange(math.ceil(width / spacing) + 2, dtype=dtype)
    ys = anchor[1] + spacing * jnp.arange(math.ceil(height / spacing) + 2, dtype=dtype)
    return xs, ys


def scattered_pieces(
    view, ray_ends, pixel_xy, *, toward, inverse, light_depth, medium: BoundedMedium, visibility: Callable,
    num_view_steps: int,
) -> "MarchedPieces":
    """Single scattering of the light along the rays `view` (unit, `(h, w, 3)`, through the pixel positions
    `pixel_xy`) in consecutive pieces, the first from the medium's start up to `ray_ends[0]`, each next one from
    where the previous ended up to its own end (`ray_ends`: a sequence of `(h, w)`, each clamped to the medium),
    each in `num_view_steps` segments even in transmittance (`bound_fraction`), as `MarchedPieces`. `toward`,
    `inverse`: the light's direction and inverse distance (`light_geometry`); `visibility`: the shadow's reading
    (`shadow_reading`'s `reader`), which the pieces share."""
    dtype = view.dtype
    origin = jnp.zeros_like(view)
    fractions = jnp.arange(num_view_steps + 1, dtype=dtype) / num_view_steps
    all_bounds, attenuated, firsts, lasts, opticals = [], [], [], [], []
    previous = None
    for ray_end in ray_ends:
        start, end = medium_interval(origin, view, ray_end, **medium.extent)
        first = start if previous is None else jnp.clip(previous, start, end)
        previous = end
        firsts.append(first)
        lasts.append(end)
        optical = placement_depth(origin, view, first, end, medium)
        opticals.append(optical)
        bounds = first[..., None] + (end - first)[..., None] * bound_fraction(fractions, optical[..., None])
        tau = optical_depth(
            origin[..., None, :], view[..., None, :], start[..., None], bounds, **medium.density
        )
        all_bounds.append(bounds)
        attenuated.append(jnp.exp(-tau[..., :-1]) - jnp.exp(-tau[..., 1:]))
    lower, upper = (jnp.concatenate(parts, axis=-1) for parts in ([b[..., :-1] for b in all_bounds],
                                                                  [b[..., 1:] for b in all_bounds]))  # fmt: skip
    attenuated = jnp.concatenate(attenuated, axis=-1)
    along, miss = light_approach(view, toward, inverse)
    # What varies along a segment (the shadow, the light's way in; the sun's angle) is taken where its light comes
    # from: near a point light that is the ray's closest approach, not the segment's middle. A point light's angle
    # sweeps too far across a segment for one reading: its phase is the segment's mean (`segment_phase`).
    middles = irradiance_median(lower, upper, along[..., None], miss[..., None], inverse)
    points = view[..., None, :] * middles[..., None]
    dimmed = light_transmittance(points, toward, light_depth=light_depth, **medium.density, **medium.extent)
    to_light, _ = toward_light(points, toward, inverse)
    phase = henyey_greenstein(dot(view[..., None, :], to_light), anisotropy=medium.anisotropy)
    if not is_static_sun(light_depth):  # the sun's angle is the same all along a ray: a sun traced skips the mean
        phase = jax.lax.cond(
            inverse > 0, lambda: segment_phase(lower, upper, along[..., None], miss[..., None], inverse, medium),
            lambda: phase,
        )  # fmt: skip
    irradiance = segment_irradiance(view, lower, upper, toward, inverse)
    visible = visibility(pixel_xy, lower, upper, middles)
    lit = attenuated * visible * dimmed * phase * irradiance
    pieces = jnp.moveaxis(lit.reshape(*lit.shape[:-1], len(ray_ends), num_view_steps), -2, 0)
    light_bounds = irradiance_coordinate(jnp.stack(all_bounds), along[..., None], miss[..., None], inverse)
    return MarchedPieces(
        pieces, jnp.cumsum(pieces, axis=-1) - pieces, jnp.stack(firsts), jnp.stack(lasts), jnp.stack(opticals),
        light_bounds, along, miss, inverse,
    )  # fmt: skip
