"""Scattering from the depth buffer: view rays marched in segments, each segment's shadow read along the screen.

Pixel `p` sees along the unit view ray `t * d_p` (`lens.view_directions`, from
the horizontal field of view) up to its depth `D_p` (distance along the ray,
scene units, `+inf` on sky). The light is the point `S = light_depth * d_L`
(`d_L` = `lens.light_direction`) or, for `light_depth = inf`, the sun in
direction `d_L`. The medium fills a sphere of radius `max_distance` around the
camera; its extinction is `extinction * exp(-height_falloff * y)` (`y` the
height above the camera along its up axis, scene units: engines' height fog)
below `layer_top` (scene units above the camera, `inf`: no top). The fogged
frame is

    L = C * T(D) * (1 - direct_fraction + direct_fraction * T_L(P))
        + light_color * sum_j V_j * T_L(X_j) * E_j * p(theta_j) * (T(t_j) - T(t_j+1))
        + ambient_color * max(1 - T(D) + ambient_rise * Y(D), 0),

single scattering in closed form per segment: `T` the transmittance from the
camera, `T_L` from a point toward the light (the light dimmed on its way in,
through the same bounded medium), `E_j` the irradiance relative to the
light's at the camera's distance (1 for the sun; the mean of
`(light_depth / |S - X|)^2` over the segment for a point light), `p` the
Henyey-Greenstein phase function, `V_j` the segment's visibility of the light
(`segment_visibility`), `P` the surface seen. The sky's light and the light
scattered more than once, which `ambient_color` stands for, grow with height
above the ground, which hides the lower half of the sky near it:
`ambient_rise` (per scene unit) raises the ambient in proportion to the
height above the camera of the ray's scattering, `Y(D)` (`scattering_height`:
`integral sigma T y dt` up to `D`, in closed form as in the homogeneous
medium of the same optical depth).

A segment's visibility is read from the depth buffer (`shadow_samples.segment_visibility`, or along lines through
the light, `shadow_lines`) along the screen segment
from `p` toward the light's position (away from the light's true projection
when it is behind the camera), clipped to the screen: at each of
`num_shadow_samples` samples `q`, the shadow ray from the segment's midpoint
crosses `q`'s camera ray at a distance `mu` (closed form in the plane of the
camera, the point and the light); a surface near `q` blocks it when the depths
`[mu_prev, mu]` the ray runs through since the previous sample (the first:
since the point itself) meet its slab `[D_q, D_q * (1 + thickness)]` (a depth
buffer is a height field of unknown thickness; near the light's screen
position one step covers a long stretch in depth), with linear ramps `edge_softness * D_q` wide at
both faces so that the thickness, the light and the field of view have
gradients; the slab test is made at the four texels around `q` and blended
with bilinear weights, so shadows move smoothly as `q` moves under the pixel
grid. A last sample sits at the segment's end: on screen, the light's
own pixel, where every shadow ray reaches the light's distance (the sun's:
beyond every slab), so an object that hides the light shades the whole view
ray in front of it. Surfaces whose slab reaches the light (the emitter) and
sky block nothing; off screen nothing is known and nothing blocks. The samples are
shared by every segment. The march runs on rays `resolution_factor` pixels
apart, anchored to the light (its position plus multiples of the spacing: under
a pan they ride with the scene), each marched through to the medium's end in
two pieces, split at the depth of the texel it lies in (sky: halfway), so that
its segments are fine up to its own surface. A piece's segments are even in
transmittance rather than in distance (in dense haze most of the light reaching
the camera comes from its first stretch). Every pixel reads its four nearest
rays' in-scattering up to its own depth (the segment holding it taken in
proportion) and takes them by bilinear weights at their true positions. A
ray's split only places its segments' bounds: when a surface's edge slides
under it (a pan), what it reads at a depth changes by the sampling alone.
"""

import functools
import math
import numbers
from typing import Literal

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from godrays_jax.kernels.bounded_medium import (
    dot,
    irradiance_coordinate,
    irradiance_median,
    light_approach,
    light_geometry,
    light_transmittance,
    medium_interval,
    optical_depth,
    scattering_height,
    segment_irradiance,
    toward_light,
)
from godrays_jax.kernels.lens import rays_through, view_directions
from godrays_jax.kernels.media import henyey_greenstein
from godrays_jax.kernels.shadow_lines import segment_visibility_by_lines
from godrays_jax.kernels.shadow_samples import segment_visibility
from godrays_jax.primitives.camera import focal_length_px
from godrays_jax.primitives.checks import check_image, check_light, check_plane, check_scalar, is_static_int
from godrays_jax.primitives.sampling import bilinear_corners

# The nearest a point light is taken to the camera, as a fraction of the medium's radius (`volumetric_fog_terms`).
_NEAREST_LIGHT = 1e-3

# The pixels' reads of the march rays are made this many pixels (whole rows) at a time on larger frames: memory
# O(band x lanes) in a fit's Jacobian instead of O(frame x lanes), the same values.
_BAND_PIXELS = 1 << 16

# A piece's segments are even in the transmittance of a homogeneous medium of the piece's optical depth, taken
# at most this deep: beyond it the first segments are short enough, and float32 would lose the last bound's place.
_DEEPEST_PLACEMENT = 12.0


def _bound_fraction(fraction, optical):
    """Where a piece's segment bound lies, as a fraction of the piece's length, for the bound at `fraction` of the
    segments (`k / num_view_steps`): even in `1 - T` through a homogeneous medium of optical depth `optical`
    over the piece, so that each segment holds an equal share of the light a lit piece scatters toward the
    camera (even in distance, dense haze spent most segments where its light no longer reaches the camera);
    even in distance as `optical` goes to 0. `fraction` in [0, 1], 1 on the piece's end exactly."""
    small = optical < 1e-4
    x = jnp.where(small, 1.0, jnp.minimum(optical, _DEEPEST_PLACEMENT))
    placed = -jnp.log1p(jnp.minimum(fraction, 1.0 - 1e-6) * jnp.expm1(-x)) / x
    return jnp.where(small, fraction, jnp.where(fraction >= 1.0, 1.0, placed))


def _placement_depth(origin, view, first, end, *, extinction, height_falloff):
    """The optical depth of each piece from `first` to `end` that places its segments (`_bound_fraction`), held
    under differentiation. Where the segments lie is a sampling choice: its derivative is the sampling error's
    (large where a shadow's edge crosses a segment's middle), not the medium's, and in the fit's Jacobian it made
    every Levenberg-Marquardt step fail from a fog layer's start (benchmarks/README.md, "Segments even in
    transmittance"). The bounds still move with the piece's ends, as before."""
    return jax.lax.stop_gradient(
        optical_depth(origin, view, first, end, extinction=extinction, height_falloff=height_falloff)
    )


def _segment_fraction(fraction, optical):
    """`_bound_fraction`'s inverse: for a point at `fraction` of a piece's length, the fraction of the segments
    before it (not floored)."""
    small = optical < 1e-4
    x = jnp.where(small, 1.0, jnp.minimum(optical, _DEEPEST_PLACEMENT))
    return jnp.where(small, fraction, jnp.expm1(-x * fraction) / jnp.expm1(-x))


def _march_grid(light_xy, height, width, spacing, dtype):
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


def _in_scattered(view, ray_ends, depth, light_xy, pixel_xy, options):
    """Single scattering of the light along the rays `view` (unit, `(h, w, 3)`) in consecutive pieces, the
    first from the medium's start up to `ray_ends[0]`, each next one from where the previous ended up to its own
    end (`ray_ends`: a sequence of `(h, w)`, each clamped to the medium), each in `num_view_steps` segments
    even in transmittance (`_bound_fraction`): `(L, h, w, num_view_steps)`, each piece's first and last bound
    (scene units, two `(L, h, w)`), its optical depth (`(L, h, w)`, which places its bounds) and a function
    of a ray's distances that is even in the light's irradiance along it (`irradiance_coordinate` of the rays,
    each `(h, w)`, indexed by rows and columns). The pieces share each shadow sample's reads of the
    depth buffer."""
    (fov_x_deg, light_depth, light_in_front, extinction, max_distance, height_falloff, layer_top, anisotropy,
     thickness, edge_softness, num_view_steps, num_shadow_samples, shadows, num_shadow_lines,
     num_shadow_bins) = options  # fmt: skip
    height, width = depth.shape
    dtype = view.dtype
    toward, inverse = light_geometry(light_xy, height, width, fov_x_deg, light_depth, light_in_front, dtype)
    origin = jnp.zeros_like(view)
    fractions = jnp.arange(num_view_steps + 1, dtype=dtype) / num_view_steps
    lower, upper, attenuated, firsts, lasts, opticals = [], [], [], [], [], []
    previous = None
    for ray_end in ray_ends:
        start, end = medium_interval(origin, view, ray_end, max_distance=max_distance, layer_top=layer_top)
        first = start if previous is None else jnp.clip(previous, start, end)
        previous = end
        firsts.append(first)
        lasts.append(end)
        optical = _placement_depth(origin, view, first, end, extinction=extinction, height_falloff=height_falloff)
        opticals.append(optical)
        bounds = first[..., None] + (end - first)[..., None] * _bound_fraction(fractions, optical[..., None])
        tau = optical_depth(
            origin[..., None, :], view[..., None, :], start[..., None], bounds,
            extinction=extinction, height_falloff=height_falloff,
        )  # fmt: skip
        lower.append(bounds[..., :-1])
        upper.append(bounds[..., 1:])
        attenuated.append(jnp.exp(-tau[..., :-1]) - jnp.exp(-tau[..., 1:]))
    lower, upper, attenuated = (jnp.concatenate(parts, axis=-1) for parts in (lower, upper, attenuated))
    along, miss = light_approach(view, toward, inverse)
    # What varies along a segment (the angle to the light, the shadow, the light's way in) is taken where its
    # light comes from: near a point light that is the ray's closest approach, not the segment's middle.
    middles = irradiance_median(lower, upper, along[..., None], miss[..., None], inverse)
    points = view[..., None, :] * middles[..., None]
    dimmed = light_transmittance(
        points, toward, light_depth=light_depth, extinction=extinction, max_distance=max_distance,
        height_falloff=height_falloff, layer_top=layer_top,
    )  # fmt: skip
    to_light, _ = toward_light(points, toward, inverse)
    phase = henyey_greenstein(dot(view[..., None, :], to_light), anisotropy=anisotropy)
    irradiance = segment_irradiance(view, lower, upper, toward, inverse)
    if shadows == "lines":
        visible = segment_visibility_by_lines(
            depth, light_xy, pixel_xy, lower, upper, fov_x_deg=fov_x_deg, light_depth=light_depth,
            light_in_front=light_in_front, thickness=thickness, edge_softness=edge_softness,
            max_distance=max_distance, num_lines=num_shadow_lines, num_bins=num_shadow_bins,
        )  # fmt: skip
    else:
        visible = segment_visibility(
            depth, light_xy, pixel_xy, middles, fov_x_deg=fov_x_deg, light_depth=light_depth,
            light_in_front=light_in_front, thickness=thickness, edge_softness=edge_softness,
            num_shadow_samples=num_shadow_samples,
        )  # fmt: skip
    lit = attenuated * visible * dimmed * phase * irradiance
    pieces = jnp.moveaxis(lit.reshape(*lit.shape[:-1], len(ray_ends), num_view_steps), -2, 0)

    def even_in_light(distance, row, col):
        return irradiance_coordinate(distance, along[row, col], miss[row, col], inverse)

    return pieces, jnp.stack(firsts), jnp.stack(lasts), jnp.stack(opticals), even_in_light


def _read_at_depth(lit, first, last, optical, even_in_light, row, col, ray_end):
    """The in-scattering along the march rays `(row, col)` up to `ray_end` (clamped to the piece's bounds) from
    one piece's segments' light `lit` (`(h, w, M)`, segments from `first` to `last`, each `(h, w)`, placed by
    the piece's optical depth `optical` as `_bound_fraction` places them), the
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
    segments_before = jax.lax.stop_gradient(_segment_fraction((distance - first) / length, optical) * count)
    index = jnp.clip(jnp.floor(segments_before), 0, count - 1)
    lower, upper = (first + length * _bound_fraction((index + offset) / count, optical) for offset in (0.0, 1.0))
    start, reached, end = (even_in_light(u, row, col) for u in (lower, distance, upper))
    share = jnp.clip((reached - start) / jnp.where(end > start, end - start, 1.0), 0.0, 1.0)
    index = index.astype(jnp.int32)
    before = jnp.cumsum(lit, axis=-1) - lit
    return before[row, col, index] + lit[row, col, index] * share


def _upsample_by_depth(lit, firsts, lasts, opticals, even_in_light, ray_end, xs, ys, spacing, first_row=0):
    """The in-scattering of the march rays at `(xs, ys)` (`spacing` pixels apart; their pieces' segments' light
    `lit`, `(L, h, w, M)`, from `firsts` to `lasts`, placed by `opticals`, each `(L, h, w)`; `even_in_light` as
    `_read_at_depth`'s) at every pixel of the rows from `first_row` on: each of its four nearest rays read up
    to the pixel's own `ray_end` (`(rows, W)`, scene units, `inf` on sky: read as it is, so that a read beyond a
    piece's end takes the piece whole with the piece's own derivatives), by bilinear weights at the rays' true
    positions."""
    height, width = ray_end.shape
    _, small_h, small_w, _ = lit.shape
    dtype = lit.dtype
    x = (jnp.arange(width, dtype=dtype) + 0.5 - xs[0]) / spacing
    y = (jnp.arange(height, dtype=dtype) + first_row + 0.5 - ys[0]) / spacing
    row, col, tent = bilinear_corners(x[None, :], y[:, None], small_h, small_w)
    read = sum(_read_at_depth(*piece, even_in_light, row, col, ray_end) for piece in zip(lit, firsts, lasts, opticals))
    return jnp.sum(tent * read, axis=0)


def _covering_depth(depth):
    """Each pixel's depth, or on sky the nearest depth among its eight neighbours (`inf` where they are all sky)."""
    padded = jnp.pad(depth, 1, constant_values=jnp.inf)
    height, width = depth.shape
    nearest = functools.reduce(
        jnp.minimum, [padded[dy : dy + height, dx : dx + width] for dy in range(3) for dx in range(3)]
    )  # fmt: skip
    return jnp.where(jnp.isfinite(depth), depth, nearest)


def volumetric_fog_terms(
    depth: Float[Array, "H W"],
    light_xy: Float[ArrayLike, "2"],
    *,
    fov_x_deg: Float[ArrayLike, ""],
    light_depth: Float[ArrayLike, ""] = math.inf,
    light_in_front: Bool[ArrayLike, ""] | bool = True,
    extinction: Float[ArrayLike, ""],
    max_distance: Float[ArrayLike, ""],
    height_falloff: Float[ArrayLike, ""] = 0.0,
    layer_top: Float[ArrayLike, ""] = math.inf,
    anisotropy: Float[ArrayLike, ""],
    direct_fraction: Float[ArrayLike, ""] = 0.0,
    thickness: Float[ArrayLike, ""] = 0.15,
    edge_softness: Float[ArrayLike, ""] = 0.05,
    num_view_steps: int = 16,
    num_shadow_samples: int = 32,
    shadows: Literal["samples", "lines"] = "samples",
    num_shadow_lines: int = 512,
    num_shadow_bins: int = 192,
    resolution_factor: int = 1,
    ambient_rise: Float[ArrayLike, ""] = 0.0,
    coverage: Float[Array, "H W"] | None = None,
    uncovered_depth: Float[Array, "H W"] | None = None,
) -> tuple[Float[Array, "H W"], Float[Array, "H W"], Float[Array, "H W"]]:
    """`(surface, scattered, ambient)`: the fogged frame is `C * surface + light_color * scattered + ambient_color * ambient`.

    `surface = T(D) * (1 - direct_fraction + direct_fraction * T_L(P))` (sky:
    `T(D)`), `scattered` the sum over segments of the module docstring
    (per steradian of the phase function), `ambient = max(1 - T(D) +
    ambient_rise * Y(D), 0)`: the opacity `1 - T(D)` where `ambient_rise` is 0.

    Args:
        depth: distance along each camera ray, scene units, `+inf` on sky.
        light_xy: the light's projected position in pixels, anywhere on or off
            screen (mirrored through the camera plane when behind it).
        fov_x_deg: horizontal field of view in degrees, in (0, 180).
        light_depth: the light's distance along its camera ray, scene units; `inf`: the sun.
        light_in_front: whether the light is in front of the camera.
        extinction: per scene unit at the camera's height, >= 0.
        max_distance: the radius of the medium around the camera, scene units.
        height_falloff: per scene unit, >= 0 (0: homogeneous in height).
        layer_top: the medium's top above the camera (scene units; negative: the
            camera above the layer; `inf`: no top).
        anisotropy: Henyey-Greenstein `g`, in (-1, 1).
        direct_fraction: the share of the frame's surface light that comes from
            the light (dimmed by the medium on its way in), in [0, 1].
        ambient_rise: the ambient's growth with the height of the ray's
            scattering above the camera, per scene unit (0: the same at every
            height; negative: it falls with height); the ambient weight is
            clipped at 0 where the ray runs down steeply enough.
        thickness, edge_softness: the depth buffer's slabs (`segment_visibility`).
        num_view_steps: segments per view ray (static int, >= 1).
        num_shadow_samples: depth samples per screen segment (static int, >= 1), with `shadows="samples"`.
        shadows: how each segment's shadow is read: `"samples"`, at its middle from
            `num_shadow_samples` samples along the screen toward the light
            (`segment_visibility`); `"lines"`, as the mean over the segment from
            `num_shadow_lines` lines through the light, `num_shadow_bins` bins
            of the shadow rays' coordinate each (`shadow_lines`): no sampling
            that crawls under a camera pan, at more cost.
        num_shadow_lines, num_shadow_bins: with `shadows="lines"` (static ints, >= 2).
        resolution_factor: the march rays' spacing in pixels (a static Python
            number >= 1, any frame size): 1, every pixel's own ray; more, rays
            at the light's position plus `resolution_factor` times integers
            (`_march_grid`), each read by its nearest pixels up to their own
            depths (the module's docstring).
        coverage: the fraction of each pixel covered by its surface, in [0, 1]
            (`Buffers.coverage`); each term is then `coverage` times the term
            of the surface (on a sky pixel, of its nearest neighbour's) plus
            the rest times the term of what the uncovered part sees, as a
            renderer's pixel filter blends a silhouette. None: the depth alone
            says (finite: covered).
        uncovered_depth: the distance (scene units) that the uncovered part of
            each pixel sees, along the pixel's ray: a surface behind or in
            front of its own at a silhouette between two surfaces; `inf`, the
            sky (None: the sky everywhere). Used with `coverage`.
    """
    if jnp.ndim(depth) != 2:
        raise ValueError(f"depth must have shape (H, W), got shape {jnp.shape(depth)}")
    light_xy = check_light(light_xy)
    if not is_static_int(num_view_steps) or num_view_steps < 1:
        raise ValueError(f"num_view_steps must be a Python int >= 1, got {num_view_steps!r}")
    if shadows not in ("samples", "lines"):
        raise ValueError(f"shadows must be 'samples' or 'lines', got {shadows!r}")
    if not isinstance(resolution_factor, numbers.Real) or isinstance(resolution_factor, bool) or not resolution_factor >= 1:
        raise ValueError(f"resolution_factor must be a Python number >= 1, got {resolution_factor!r}")
    height, width = depth.shape
    for name, value in (("extinction", extinction), ("max_distance", max_distance), ("height_falloff", height_falloff),
                        ("layer_top", layer_top), ("anisotropy", anisotropy), ("direct_fraction", direct_fraction),
                        ("ambient_rise", ambient_rise)):  # fmt: skip
        check_scalar(value, name)
    if coverage is not None:
        check_plane(coverage, "coverage", height, width)
    if uncovered_depth is not None:
        if coverage is None:
            raise ValueError("uncovered_depth needs coverage (the share of each pixel its own surface covers)")
        check_plane(uncovered_depth, "uncovered_depth", height, width)
    dtype = jnp.result_type(depth, jnp.float32)
    depth = jnp.asarray(depth, dtype)
    # A point light within a thousandth of the medium's reach of the camera is taken at that distance: nearer, its
    # inverse distance overflows float32 in the irradiance around it and its shadows read along lines lose their angles.
    # The floor is a guard, not a model: no gradient reaches `max_distance` through it (one would carry the medium's
    # reach through every use of the light's distance, the shadows' table among them, in a fit's Jacobian).
    nearest = jax.lax.stop_gradient(_NEAREST_LIGHT * jnp.asarray(max_distance, dtype))
    light_depth = jnp.maximum(jnp.asarray(light_depth, dtype), nearest)
    medium = dict(extinction=extinction, height_falloff=height_falloff)
    bounds = dict(max_distance=max_distance, layer_top=layer_top)
    view = view_directions(height, width, fov_x_deg=fov_x_deg, dtype=dtype)
    toward, _ = light_geometry(light_xy, height, width, fov_x_deg, light_depth, light_in_front, dtype)
    share = jnp.asarray(direct_fraction, dtype)
    rise = jnp.asarray(ambient_rise, dtype)

    def surface_and_ambient(view, ray_end):
        origin = jnp.zeros_like(view)
        start, end = medium_interval(origin, view, jnp.where(jnp.isfinite(ray_end), ray_end, jnp.inf), **bounds)
        tau = optical_depth(origin, view, start, end, **medium)
        opacity = -jnp.expm1(-tau)
        finite = jnp.isfinite(ray_end)
        surface_points = view * jnp.where(finite, ray_end, 0.0)[..., None]
        dimmed = light_transmittance(surface_points, toward, light_depth=light_depth, **medium, **bounds)
        ambient = jnp.maximum(opacity + rise * scattering_height(view, start, end, tau), 0.0)
        return (1.0 - opacity) * jnp.where(finite, 1.0 - share + share * dimmed, 1.0), ambient

    options = (fov_x_deg, light_depth, light_in_front, extinction, max_distance, height_falloff, layer_top, anisotropy,
               thickness, edge_softness, num_view_steps, num_shadow_samples, shadows, num_shadow_lines,
               num_shadow_bins)  # fmt: skip
    spacing = resolution_factor
    if spacing == 1:
        x, y = jnp.meshgrid(jnp.arange(width, dtype=dtype) + 0.5, jnp.arange(height, dtype=dtype) + 0.5)

        def march(ray_end, first_row):  # the whole frame: every pixel's own ray
            return jnp.sum(_in_scattered(view, (ray_end,), depth, light_xy, jnp.stack([x, y], axis=-1), options)[0][0], axis=-1)

    else:
        xs, ys = _march_grid(light_xy, height, width, spacing, dtype)
        x, y = jnp.meshgrid(xs, ys)
        # Each march ray's own depth: the texel it lies in (clamped to the frame: the margin's rays).
        rows = jnp.clip(jnp.floor(y), 0, height - 1).astype(jnp.int32)
        cols = jnp.clip(jnp.floor(x), 0, width - 1).astype(jnp.int32)
        coarse_depth = depth[rows, cols]
        rays = rays_through(x, y, height, width, focal_length_px(width, fov_x_deg, dtype))
        rays = rays / jnp.linalg.norm(rays, axis=-1, keepdims=True)
        # Each ray through to the medium's end in two pieces split at its own surface, so its segments are fine
        # up to there; a pixel reads every nearby ray up to its own depth, whatever surface the ray met (sky in a
        # gap narrower than the spacing, a trunk's edge sliding under the ray). A sky ray's split, halfway, moves with the
        # medium's extent as every segment bound does, so derivatives agree with the frame's change.
        sky = jnp.full_like(coarse_depth, jnp.inf)
        start, end = medium_interval(jnp.zeros_like(rays), rays, sky, **bounds)
        split = jnp.where(coarse_depth < end, coarse_depth, 0.5 * (start + end))
        pieces = _in_scattered(rays, (split, sky), depth, light_xy, jnp.stack([x, y], axis=-1), options)

        def march(ray_end, first_row):
            return _upsample_by_depth(*pieces, ray_end, xs, ys, spacing, first_row)

    def pixel_terms(view, first_row, surface_depth, covered, uncovered):
        """The three terms at the rows of `view` from `first_row` on."""
        surface, ambient = surface_and_ambient(view, surface_depth)
        on_surface = (surface, march(surface_depth, first_row), ambient)
        if covered is None:
            return on_surface
        # A silhouette's pixel is partly the surface (on sky: its nearest neighbour's) and partly what lies beside it.
        surface, ambient = surface_and_ambient(view, uncovered)
        on_sky = (surface, march(uncovered, first_row), ambient)
        return tuple(covered * one + (1.0 - covered) * other for one, other in zip(on_surface, on_sky))

    if coverage is None:
        planes = (depth, None, None)
    else:
        uncovered = jnp.full_like(depth, jnp.inf) if uncovered_depth is None else jnp.asarray(uncovered_depth, dtype)
        planes = (_covering_depth(depth), jnp.asarray(coverage, dtype), uncovered)
    band = max(_BAND_PIXELS // width, 1)
    if spacing == 1 or band >= height:
        return pixel_terms(view, 0, *planes)
    # Band by band: every pixel's reads of its rays (in a fit's Jacobian, in every lane) held for a band of rows at
    # a time instead of the frame. The rows that fill the last band repeat the frame's last (pixels like its own,
    # whose derivatives are finite: reverse mode multiplies theirs by zero) and are cut off again.
    bands = -(-height // band)

    def in_bands(plane):
        padded = jnp.pad(plane, [(0, bands * band - height)] + [(0, 0)] * (plane.ndim - 1), mode="edge")
        return padded.reshape(bands, band, *plane.shape[1:])

    inputs = [in_bands(view), jnp.arange(bands) * band, *[None if plane is None else in_bands(plane) for plane in planes]]
    terms = jax.lax.map(lambda rows: pixel_terms(*rows), inputs)
    return tuple(term.reshape(bands * band, width)[:height] for term in terms)


def apply_volumetric_fog(
    image: Float[Array, "H W C"],
    depth: Float[Array, "H W"],
    light_xy: Float[ArrayLike, "2"],
    *,
    light_color: Float[ArrayLike, "3"],
    ambient_color: Float[ArrayLike, "3"],
    **options,
) -> Float[Array, "H W C"]:
    """The fogged frame `image * surface + light_color * scattered + ambient_color * ambient`; alpha passes through.

    `image` is the clean linear frame, `depth` its distance along each camera ray (scene units,
    `+inf` on sky), `light_xy` the light's position in pixels; `light_color` the RGB albedo times the
    light's irradiance (at the camera's distance from a point light),
    `ambient_color` the RGB albedo times the sky's radiance; `options` are
    `volumetric_fog_terms`'. A 1-channel image receives the mean of the RGB light.
    """
    check_image(image)
    check_plane(depth, "depth", image.shape[0], image.shape[1])
    dtype = image.dtype
    surface, scattered, ambient = volumetric_fog_terms(depth, light_xy, **options)
    light = scattered[..., None] * jnp.asarray(light_color, dtype) + ambient[..., None] * jnp.asarray(ambient_color, dtype)
    channels = min(image.shape[-1], 3)
    if channels == 1:
        light = jnp.mean(light, axis=-1, keepdims=True)
    colour = image[..., :channels] * surface[..., None].astype(dtype) + light[..., :channels].astype(dtype)
    return jnp.concatenate([colour, image[..., channels:]], axis=-1)
