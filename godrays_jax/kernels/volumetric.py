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

The march is `fog_march`, the pixels' reading of it `fog_reading`, the
shadow's reading `shadow_reading`; here they are assembled into the three
terms, and the terms composited (`fog_light`, `composite_fog`).
"""

import functools
import math
import numbers

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from godrays_jax.kernels.blur import pooled_gaussian_matrices
from godrays_jax.kernels.bounded_medium import (
    BoundedMedium,
    is_static_sun,
    light_geometry,
    light_transmittance,
    medium_interval,
    optical_depth,
    scattering_height,
)
from godrays_jax.kernels.fog_march import MarchedPieces, march_grid, scattered_pieces
from godrays_jax.kernels.fog_reading import (
    blend_where_partly_covered,
    pack_pieces,
    read_by_depth,
    read_holding_piece,
    upsample_by_depth,
)
from godrays_jax.kernels.lens import rays_through, view_directions
from godrays_jax.kernels.light_view_shadows import light_view_visibility, on_light_view
from godrays_jax.kernels.shadow_reading import (
    ShadowReading,
    ShadowSamples,
    Slabs,
    enclosure,
)
from godrays_jax.primitives.camera import focal_length_px, unit_vectors
from godrays_jax.primitives.checks import (
    check_image,
    check_light,
    check_plane,
    check_scalar,
    is_static_int,
)
from godrays_jax.primitives.derivatives import values_are_only_needed
from godrays_jax.primitives.light_view import LightView

# The nearest a point light is taken to the camera, as a fraction of the medium's radius (`volumetric_fog_terms`).
_NEAREST_LIGHT = 1e-3

# Points a segment's shadow is read at from a depth map seen from the light (`_light_view_where_it_reaches`).
_LIGHT_VIEW_SAMPLES = 8
# The pixels' reads of the march rays are made this many pixels (whole rows) at a time on larger frames: memory
# O(band x lanes) in a fit's Jacobian instead of O(frame x lanes), the same values.
_BAND_PIXELS = 1 << 14
# The partly covered pixels whose own rays are marched at once, where every pixel has its own: a march costs far more
# than a read of the rays around a pixel, and a frame's silhouettes are a few thousand pixels.
_MARCHED_PIXELS = 1 << 10

def _covering_depth(depth):
    """Each pixel's depth, or on sky the nearest depth among its eight neighbours (`inf` where they are all sky)."""
    padded = jnp.pad(depth, 1, constant_values=jnp.inf)
    height, width = depth.shape
    nearest = functools.reduce(
        jnp.minimum, [padded[dy : dy + height, dx : dx + width] for dy in range(3) for dx in range(3)]
    )  # fmt: skip
    return jnp.where(jnp.isfinite(depth), depth, nearest)


def _march_in_bands(depth, xs, ys, spacing, focal, band, medium, march_options):
    """The march rays at `(xs, ys)` (`march_grid`), `band` rows of them at a time (their segments' arrays held for a
    band instead of the grid), each marched through to the medium's end in two pieces split at its own surface:
    `MarchedPieces` of the whole grid. The rows that fill the last band continue the grid and are cut off again."""
    height, width = depth.shape
    dtype = depth.dtype
    rows = ys.shape[0]
    band = min(band, rows)
    bands = -(-rows // band)

    def march_band(first):
        y = ys[0] + spacing * (first + jnp.arange(band)).astype(dtype)
        x, y = jnp.meshgrid(xs, y)
        # Each march ray's own depth: the texel it lies in (clamped to the frame: the margin's rays).
        texel_rows = jnp.clip(jnp.floor(y), 0, height - 1).astype(jnp.int32)
        texel_cols = jnp.clip(jnp.floor(x), 0, width - 1).astype(jnp.int32)
        ray_depth = depth[texel_rows, texel_cols]
        rays = unit_vectors(rays_through(x, y, height, width, focal))
        # Each ray through to the medium's end in two pieces split at its own surface, so its segments are fine
        # up to there; a pixel reads every nearby ray up to its own depth, whatever surface the ray met (sky in a
        # gap narrower than the spacing, a trunk's edge sliding under the ray). A sky ray's split, halfway, moves
        # with the medium's extent as every segment bound does, so derivatives agree with the frame's change.
        sky = jnp.full_like(ray_depth, jnp.inf)
        start, end = medium_interval(jnp.zeros_like(rays), rays, sky, **medium.extent)
        split = jnp.where(ray_depth < end, ray_depth, 0.5 * (start + end))
        return scattered_pieces(rays, (split, sky), jnp.stack([x, y], axis=-1), **march_options)

    # Every field but the light's inverse distance, which is the march's own: out of the loop a sun's Python 0 stays one.
    marched = jax.lax.map(lambda first: tuple(march_band(first))[:-1], jnp.arange(bands) * band)

    def whole(values, row_axis):  # (bands, ..., band, ...) -> (..., rows, ...)
        values = jnp.moveaxis(values, 0, row_axis - 1)
        values = values.reshape(*values.shape[: row_axis - 1], bands * band, *values.shape[row_axis + 1 :])
        return jax.lax.slice_in_dim(values, 0, rows, axis=row_axis - 1)

    *per_piece, along, miss = marched
    per_piece = [whole(values, 2) for values in per_piece]
    return MarchedPieces(*per_piece, whole(along, 1), whole(miss, 1), march_options["inverse"])


def volumetric_fog_terms(
    depth: Float[Array, "H W"],
    light_xy: Float[ArrayLike, "2"],
    *,
    fov_x_deg: Float[ArrayLike, ""],
    light_depth: Float[ArrayLike, ""] = math.inf,
    light_in_front: Bool[ArrayLike, ""] | bool = True,
    medium: BoundedMedium,
    slabs: Slabs = Slabs(),
    shadows: ShadowReading = ShadowSamples(),
    direct_fraction: Float[ArrayLike, ""] = 0.0,
    ambient_rise: Float[ArrayLike, ""] = 0.0,
    num_view_steps: int = 16,
    resolution_factor: int = 1,
    coverage: Float[Array, "H W"] | None = None,
    uncovered_depth: Float[Array, "H W"] | None = None,
    light_view: LightView | None = None,
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
        medium: the medium (`bounded_medium.BoundedMedium`: its extinction,
            reach, height profile and phase function).
        slabs: the depth buffer's surfaces as slabs (`shadow_reading.Slabs`).
        shadows: how each segment's shadow is read (`shadow_reading`):
            `ShadowSamples(count)` at its middle from samples along the screen
            toward the light; `ShadowLines(num_lines, num_bins)` as the mean
            over the segment from lines through the light: no sampling that
            crawls under a camera pan, at more cost.
        direct_fraction: the share of the frame's surface light that comes from
            the light (dimmed by the medium on its way in), in [0, 1].
        ambient_rise: the ambient's growth with the height of the ray's
            scattering above the camera, per scene unit (0: the same at every
            height; negative: it falls with height); the ambient weight is
            clipped at 0 where the ray runs down steeply enough.
        num_view_steps: segments per view ray (static int, >= 1).
        resolution_factor: the march rays' spacing in pixels (a static Python
            number >= 1, any frame size): 1, every pixel's own ray; more, rays
            at the light's position plus `resolution_factor` times integers
            (`march_grid`), each read by its nearest pixels up to their own
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
        light_view: a depth map seen from the light and its camera
            (`primitives.light_view.LightView`): each segment's visibility
            is then the mean, at points along the segment, of the map's test
            where a point falls on the map (`light_view_shadows`: the map
            holds what the frame shows too) and of the depth buffer's
            reading where it does not: a map that covers the medium casts
            all of its shadows, those of what lies outside the frame too.
            None: only the depth buffer casts shadows, and a frame that is
            nearly all surface (`shadow_reading.enclosure`: a room, its
            windows) is read as closed beyond its edges: a shadow ray toward
            a light in front that leaves the screen in front of the surface
            seen where it leaves is shaded, as by the ceiling and walls out
            of view, so the light enters through the openings the frame shows.
    """
    if jnp.ndim(depth) != 2:
        raise ValueError(f"depth must have shape (H, W), got shape {jnp.shape(depth)}")
    light_xy = check_light(light_xy)
    if not is_static_int(num_view_steps) or num_view_steps < 1:
        raise ValueError(f"num_view_steps must be a Python int >= 1, got {num_view_steps!r}")
    for name, value, kind in (("medium", medium, BoundedMedium), ("slabs", slabs, Slabs)):
        if not isinstance(value, kind):
            raise ValueError(f"{name} must be a {kind.__name__}, got {type(value).__name__}")
    if not isinstance(shadows, ShadowReading):
        raise ValueError(f"shadows must be a ShadowSamples or a ShadowLines, got {shadows!r}")
    if not isinstance(resolution_factor, numbers.Real) or isinstance(resolution_factor, bool) or not resolution_factor >= 1:
        raise ValueError(f"resolution_factor must be a Python number >= 1, got {resolution_factor!r}")
    height, width = depth.shape
    for name, value in (("direct_fraction", direct_fraction), ("ambient_rise", ambient_rise)):
        check_scalar(value, name)
    if coverage is not None:
        check_plane(coverage, "coverage", height, width)
    if uncovered_depth is not None:
        if coverage is None:
            raise ValueError("uncovered_depth needs coverage (the share of each pixel its own surface covers)")
        check_plane(uncovered_depth, "uncovered_depth", height, width)
    if light_view is not None and not isinstance(light_view, LightView):
        raise ValueError(f"light_view must be a LightView or None, got {type(light_view).__name__}")
    static_front = light_in_front if isinstance(light_in_front, bool) else None
    static_sun = is_static_sun(light_depth)
    arguments = (
        depth, light_xy, fov_x_deg, None if static_sun else light_depth,
        None if static_front is not None else jnp.asarray(light_in_front),
        medium, slabs, direct_fraction, ambient_rise, coverage, uncovered_depth, light_view,
    )  # fmt: skip
    # Called eagerly, the terms run compiled once per shape and count: their loops over functions defined in the call
    # would be traced and compiled again on every call. Traced (an effect, a fit), they are part of the caller's trace.
    traced = any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(arguments))
    terms = _fog_terms if traced else _compiled_fog_terms
    return terms(
        *arguments, shadows=shadows, num_view_steps=num_view_steps, resolution_factor=resolution_factor,
        static_front=static_front, static_sun=static_sun, values_only=values_are_only_needed(),
    )  # fmt: skip


def _fog_terms(depth, light_xy, fov_x_deg, light_depth, light_in_front, medium, slabs, direct_fraction, ambient_rise,
               coverage, uncovered_depth, light_view, *, shadows, num_view_steps, resolution_factor, static_front, static_sun,
               values_only):  # fmt: skip
    """`volumetric_fog_terms` after its checks; `static_front`: the light's side when the caller gave it as a
    Python bool, else None (`light_in_front` traced); `static_sun`: the caller gave the sun as a Python number
    (`light_depth` None), which drops the point light's branches (`light_geometry`); `values_only`: traced inside
    `derivatives.values_only()`."""
    if static_front is not None:
        light_in_front = static_front
    height, width = depth.shape
    dtype = jnp.result_type(depth, jnp.float32)
    depth = jnp.asarray(depth, dtype)
    # A point light within a thousandth of the medium's reach of the camera is taken at that distance: nearer, its
    # inverse distance overflows float32 in the irradiance around it and its shadows read along lines lose their angles.
    # The floor is a guard, not a model: no gradient reaches `max_distance` through it (one would carry the medium's
    # reach through every use of the light's distance, the shadows' table among them, in a fit's Jacobian).
    if static_sun:
        light_depth = math.inf
    else:
        nearest = jax.lax.stop_gradient(_NEAREST_LIGHT * jnp.asarray(medium.max_distance, dtype))
        light_depth = jnp.maximum(jnp.asarray(light_depth, dtype), nearest)
    toward, inverse = light_geometry(light_xy, height, width, fov_x_deg, light_depth, light_in_front, dtype)
    share = jnp.asarray(direct_fraction, dtype)
    rise = jnp.asarray(ambient_rise, dtype)

    def surface_and_ambient(view, ray_end):
        origin = jnp.zeros_like(view)
        start, end = medium_interval(origin, view, jnp.where(jnp.isfinite(ray_end), ray_end, jnp.inf), **medium.extent)
        tau = optical_depth(origin, view, start, end, **medium.density)
        opacity = -jnp.expm1(-tau)
        finite = jnp.isfinite(ray_end)
        surface_points = view * jnp.where(finite, ray_end, 0.0)[..., None]
        dimmed = light_transmittance(surface_points, toward, light_depth=light_depth, **medium.density, **medium.extent)
        ambient = jnp.maximum(opacity + rise * scattering_height(view, start, end, tau), 0.0)
        return (1.0 - opacity) * jnp.where(finite, 1.0 - share + share * dimmed, 1.0), ambient

    # A map seen from the light says what lies beyond the frame's edges; without one, the frame's sky says.
    visibility = shadows.reader(
        depth, jnp.asarray(light_xy, dtype), fov_x_deg=fov_x_deg, light_depth=light_depth,
        light_in_front=light_in_front, slabs=slabs, max_distance=medium.max_distance,
        enclosed=0.0 if light_view is not None else enclosure(depth),
    )  # fmt: skip
    focal = focal_length_px(width, fov_x_deg, dtype)
    if light_view is not None:
        visibility = _light_view_where_it_reaches(visibility, light_view, height, width, focal)
    march_options = dict(
        toward=toward, inverse=inverse, light_depth=light_depth, medium=medium, visibility=visibility,
        num_view_steps=num_view_steps,
    )  # fmt: skip
    spacing = resolution_factor
    band = max(_BAND_PIXELS // width, 1)
    if spacing == 1:
        x, y = jnp.meshgrid(jnp.arange(width, dtype=dtype) + 0.5, jnp.arange(height, dtype=dtype) + 0.5)

        def march(view, ray_end, first_row):  # the whole frame: every pixel's own ray
            marched = scattered_pieces(view, (ray_end,), jnp.stack([x, y], axis=-1), **march_options)
            return jnp.sum(marched.lit[0], axis=-1)

    else:
        xs, ys = march_grid(light_xy, height, width, spacing, dtype)
        marched = _march_in_bands(depth, xs, ys, spacing, focal, max(_BAND_PIXELS // xs.shape[0], 1), medium, march_options)

        def march(view, ray_end, first_row):
            return upsample_by_depth(marched, ray_end, xs, ys, spacing, first_row)

    def pixel_terms(view, first_row, surface_depth, covered, uncovered):
        """The three terms at the rows of `view` from `first_row` on."""
        surface, ambient = surface_and_ambient(view, surface_depth)
        on_surface = (surface, march(view, surface_depth, first_row), ambient)
        if covered is None:
            return on_surface
        # A silhouette's pixel is partly the surface (on sky: its nearest neighbour's) and partly what lies beside it.
        surface, ambient = surface_and_ambient(view, uncovered)
        on_sky = (surface, march(view, uncovered, first_row), ambient)
        return tuple(covered * one + (1.0 - covered) * other for one, other in zip(on_surface, on_sky))

    if coverage is None:
        planes = (depth, None, None)
    else:
        uncovered = jnp.full_like(depth, jnp.inf) if uncovered_depth is None else jnp.asarray(uncovered_depth, dtype)
        planes = (_covering_depth(depth), jnp.asarray(coverage, dtype), uncovered)
    whole_frame = spacing == 1 or band >= height
    bands = -(-height // band)

    def in_bands(function, planes):
        """`function(first_row, *band_planes)` (a tuple of planes of the band's rows) for each band of rows of the
        planes `(H, W)` (or None), put together. The rows that fill the last band repeat the frame's last planes on
        rays below it (pixels like its own, whose derivatives are finite: reverse mode multiplies theirs by zero)
        and are cut off."""

        def in_band(plane):
            padded = jnp.pad(plane, [(0, bands * band - height)] + [(0, 0)] * (plane.ndim - 1), mode="edge")
            return padded.reshape(bands, band, *plane.shape[1:])

        inputs = [jnp.arange(bands) * band, *[None if plane is None else in_band(plane) for plane in planes]]
        outputs = jax.lax.map(lambda inputs: function(*inputs), inputs)
        return tuple(output.reshape(bands * band, width)[:height] for output in outputs)

    def rows_view(first_row):  # the unit view rays through the pixels of a band's rows (of the frame, whole)
        if whole_frame:
            return view_directions(height, width, fov_x_deg=fov_x_deg, dtype=dtype)
        x, y = jnp.meshgrid(jnp.arange(width, dtype=dtype) + 0.5, (first_row + jnp.arange(band)).astype(dtype) + 0.5)
        return unit_vectors(rays_through(x, y, height, width, focal))

    def terms_of(planes):
        if whole_frame:
            return pixel_terms(rows_view(0), 0, *planes)
        # Band by band: every pixel's reads of its rays (in a fit's Jacobian, in every lane) held for a band of rows
        # at a time instead of the frame.
        return in_bands(lambda first_row, *rows: pixel_terms(rows_view(first_row), first_row, *rows), planes)

    if not values_only:
        return terms_of(planes)

    def one_side_then_silhouettes(planes):
        # Every pixel's one side (its surface where it has any, else what its uncovered part sees: the blend's
        # other weight is 0), then the other side at the few pixels partly covered (each its own ray, or each ray
        # read through the piece holding the depth alone): `terms_of`'s values to float rounding, for renders whose
        # derivatives nobody takes (`primitives.derivatives.values_only`): a compaction serves no derivative's
        # lanes, reverse mode cannot go through its while loop, and XLA compiled the fit's vectorised Jacobian
        # through it wrong.
        covering, covered, uncovered = planes
        if spacing == 1:
            seen_by_rays = march

            def seen_at(view, x, y, ray_end):  # pixels' own rays, `(n,)` of them
                pixels = jnp.stack([x, y], axis=-1)[None]
                return jnp.sum(scattered_pieces(view[None], (ray_end[None],), pixels, **march_options).lit[0], -1)[0]

        else:
            packed = pack_pieces(marched)

            def seen_by_rays(view, seen, first_row):
                return upsample_by_depth(packed, seen, xs, ys, spacing, first_row, pieces=read_holding_piece)

            def seen_at(view, x, y, ray_end):
                return read_by_depth(packed, ray_end, x, y, xs, ys, spacing, pieces=read_holding_piece)

        def one_side(first_row, seen):
            view = rows_view(first_row)
            surface, ambient = surface_and_ambient(view, seen)
            return surface, seen_by_rays(view, seen, first_row), ambient

        seen = covering if covered is None else jnp.where(covered > 0, covering, uncovered)
        terms = one_side(0, seen) if whole_frame else in_bands(one_side, [seen])
        if covered is None:
            return terms

        def other_side(x, y, ray_end):
            view = unit_vectors(rays_through(x, y, height, width, focal))
            surface, ambient = surface_and_ambient(view, ray_end)
            return surface, seen_at(view, x, y, ray_end), ambient

        chunk = _MARCHED_PIXELS if spacing == 1 else _BAND_PIXELS
        return blend_where_partly_covered(terms, covered, uncovered, other_side, chunk=chunk)

    return one_side_then_silhouettes(planes)


def _light_view_where_it_reaches(visibility, light_view, height, width, focal):
    """Each segment's visibility as the mean over `_LIGHT_VIEW_SAMPLES` points evenly along it, on the view ray
    through its pixel, of the light view's test where a point falls on the map and of `visibility` (a shadow
    reading's, the segment's) where it does not. A segment is often longer than a shaft through a gap is wide, and
    one point of it would read the shaft or miss it. The map alone on it: it holds the surfaces the frame shows as
    well, and a window's edge read twice, softly along the screen's lines and sharply on the map, would shade its
    beam twice (benchmarks/README.md, "A sunbeam through a window in view")."""
    fractions = (jnp.arange(_LIGHT_VIEW_SAMPLES) + 0.5) / _LIGHT_VIEW_SAMPLES

    def either(pixel_xy, lower, upper, middles):
        view = unit_vectors(rays_through(pixel_xy[..., 0], pixel_xy[..., 1], height, width, focal))
        distances = lower[..., None] + (upper - lower)[..., None] * fractions.astype(lower.dtype)
        points = view[..., None, None, :] * distances[..., None]
        seen = light_view_visibility(points, light_view=light_view)
        off_map = 1.0 - jnp.mean(on_light_view(points, light_view=light_view).astype(seen.dtype), axis=-1)
        # `seen` is 1 off the map: its mean there counts what the screen's reading then shades.
        return jnp.mean(seen, axis=-1) - off_map * (1.0 - visibility(pixel_xy, lower, upper, middles))

    return either


_compiled_fog_terms = jax.jit(
    _fog_terms,
    static_argnames=("shadows", "num_view_steps", "resolution_factor", "static_front", "static_sun", "values_only"),
)


def fog_light(
    scattered: Float[Array, "H W"],
    ambient: Float[Array, "H W"],
    *,
    light_color: Float[ArrayLike, "3"],
    ambient_color: Float[ArrayLike, "3"],
) -> Float[Array, "H W 3"]:
    """The light the medium adds, `light_color * scattered + ambient_color * ambient` (RGB, linear), in the terms'
    dtype; `volumetric_fog_terms` gives `scattered` and `ambient`."""
    dtype = scattered.dtype
    return (scattered[..., None] * jnp.asarray(light_color, dtype) + ambient[..., None] * jnp.asarray(ambient_color, dtype))


def composite_fog(
    image: Float[Array, "H W C"],
    surface: Float[Array, "H W"],
    light: Float[Array, "H W 3"],
) -> Float[Array, "H W C"]:
    """The fogged frame `image * surface + light` on the colour channels, alpha unchanged; a 1-channel image
    receives the mean of the RGB `light` (`fog_light`). In `image`'s dtype."""
    dtype = image.dtype
    channels = min(image.shape[-1], 3)
    if channels == 1:
        light = jnp.mean(light, axis=-1, keepdims=True)
    colour = image[..., :channels] * surface[..., None].astype(dtype) + light[..., :channels].astype(dtype)
    return jnp.concatenate([colour, image[..., channels:]], axis=-1)


def scattered_aside(
    image: Float[Array, "H W C"],
    surface: Float[Array, "H W"],
    *,
    surface_blur: Float[ArrayLike, ""],
    sigma: float,
) -> Float[Array, "H W 3"]:
    """The frame's own light that the medium scatters a little aside on its way to the camera (RGB, linear):
    `surface_blur * G * ((1 - surface) * image)`, `G` a Gaussian blur of `sigma` pixels (clamp-to-edge).

    `1 - surface` of each pixel's light is taken out of its view ray by the medium (`volumetric_fog_terms`'
    `surface`, in [0, 1]); a strongly forward phase function sends much of it on nearly the same way, so it reaches
    the camera beside the pixel: a halo around bright surfaces seen through haze, as around a sunbeam's patch on a
    room's floor. `surface_blur` in [0, 1] is that share. The blur runs on the image box-averaged by
    `floor(sigma / 2)` pixels and read back bilinearly, as products of constant matrices
    (`kernels.blur.pooled_gaussian_matrices`), so its cost does not grow with `sigma` and a blur that is a fixed
    fraction of the frame looks the same at any size. A 1-channel image's light is its one channel in each of R, G
    and B (`composite_fog` then takes their mean back). A `surface_blur` known to be 0 when traced (a Python or
    NumPy number, a constant) gives zeros without the blur; a traced one always runs it, so its derivative at 0
    is the blur.
    """
    check_image(image)
    check_plane(surface, "surface", image.shape[0], image.shape[1])
    check_scalar(surface_blur, "surface_blur")
    if not isinstance(sigma, numbers.Real) or isinstance(sigma, bool) or not sigma > 0:
        raise ValueError(f"sigma must be a Python number > 0 (pixels), got {sigma!r}")
    height, width = image.shape[:2]
    if not isinstance(surface_blur, jax.core.Tracer) and not np.any(np.asarray(surface_blur)):
        # Known to be 0 when traced (every preset's, a constant of `apply`'s program): no blur in the program.
        return jnp.zeros((height, width, 3), image.dtype)
    colour = image[..., : min(image.shape[-1], 3)]
    taken = (1.0 - jnp.asarray(surface, image.dtype))[..., None] * colour
    (pool_h, read_h), (pool_w, read_w) = (
        (jnp.asarray(matrix, taken.dtype) for matrix in pooled_gaussian_matrices(size, float(sigma)))
        for size in (height, width)
    )
    # Products with the full-size side of the frame go along its shorter side's few blocks: the cheaper order when
    # the frame is wider than tall.
    product = functools.partial(jnp.einsum, precision="highest")
    low = product("iw,jwc->jic", pool_w, product("jh,hwc->jwc", pool_h, taken))
    blurred = product("yj,jxc->yxc", read_h, product("xi,jic->jxc", read_w, low))
    return jnp.asarray(surface_blur, image.dtype) * jnp.broadcast_to(blurred, (height, width, 3))


def scattered_again(
    scattered: Float[Array, "H W"],
    *,
    scattered_blur: Float[ArrayLike, ""],
    sigma: float,
) -> Float[Array, "H W"]:
    """The light scattered toward the camera (`volumetric_fog_terms`' `scattered`) of which a share scatters once
    more on its way and reaches the camera beside its pixel: `scattered + scattered_blur * (G * scattered -
    scattered)`, `G` `scattered_aside`'s Gaussian blur of `sigma` pixels (pooled, clamp-to-edge, a cost that does
    not grow with `sigma`).

    The march scatters each ray's light once; in a haze thick enough to show a beam, some of the beam's light
    scatters again before it reaches the camera, a glow beside the beam that no single-scattering term draws.
    `scattered_blur` in [0, 1] is that share; it moves light, it adds none (the blur sums to 1 away from the frame's
    edges). A `scattered_blur` known to be 0 when traced (a Python or NumPy number, a constant) returns `scattered`
    itself, without the blur; a traced one always runs it, so its derivative at 0 is the blur's change.
    """
    if jnp.ndim(scattered) != 2:
        raise ValueError(f"scattered must be an (H, W) plane, got shape {jnp.shape(scattered)}")
    check_scalar(scattered_blur, "scattered_blur")
    if not isinstance(scattered_blur, jax.core.Tracer) and not np.any(np.asarray(scattered_blur)):
        return scattered  # every preset's: no blur in the program
    scattered = jnp.asarray(scattered)
    blurred = scattered_aside(scattered[..., None], jnp.zeros_like(scattered), surface_blur=1.0, sigma=sigma)[..., 0]
    return scattered + jnp.asarray(scattered_blur, scattered.dtype) * (blurred - scattered)


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
    surface, scattered, ambient = volumetric_fog_terms(depth, light_xy, **options)
    return composite_fog(image, surface, fog_light(scattered, ambient, light_color=light_color, ambient_color=ambient_color))
