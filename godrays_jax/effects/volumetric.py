"""`VolumetricFog`: a bounded medium lit segment by segment, its shadows read from the depth buffer."""

import math
from typing import ClassVar

import jax.numpy as jnp
from jaxtyping import Array, Float

from godrays_jax.effects.base import Effect, frame_ray_depth
from godrays_jax.effects.fields import param, part, static
from godrays_jax.effects.medium import FLAT_NAMES, Medium
from godrays_jax.kernels.volumetric import volumetric_fog_terms
from godrays_jax.primitives.checks import check_light


def march_factor(height: int, width: int, resolution_factor: int) -> int:
    """The largest divisor of both `height` and `width` that is at most `resolution_factor` (at least 1)."""
    return max(d for d in range(1, resolution_factor + 1) if height % d == 0 and width % d == 0)


# The share of a pixel's filter that falls on each neighbour in each direction (silhouette_coverage).
_FILTER_SPILL = 0.15
# How far apart (display space, x / (1 + x), mean over channels) a silhouette's surface and sky colours must be for
# the pixel's colour to say how much of it each covers: no trust below the first, full trust from their sum on.
_UNMIX_CONTRAST, _UNMIX_RAMP = 0.02, 0.03
# Neighbours within this fraction of the surface's depth belong to the same surface (silhouette_coverage).
_SAME_SURFACE = 0.05


def _neighbours(plane):
    """The eight neighbours of every pixel (edge pixels repeated at the border), stacked along a new first axis."""
    height, width = plane.shape[:2]
    pad = [(1, 1), (1, 1)] + [(0, 0)] * (plane.ndim - 2)
    padded = jnp.pad(plane, pad, mode="edge")
    return jnp.stack([padded[dy : dy + height, dx : dx + width] for dy in range(3) for dx in range(3) if (dy, dx) != (1, 1)])


def _unmixed_share(color, depth, surface_depth):
    """`(share, trust)`: how much of each pixel its surface covers, read from its colour, and how far to trust that.

    The pixel's colour is taken as a mix of its surface's colour (the median of
    the neighbours on the same surface, within `_SAME_SURFACE` of `surface_depth`)
    and the sky's (the median of its sky neighbours): the share is the
    projection of the colour on the segment between them, clipped to [0, 1].
    A pixel with no neighbour of its own kind is its own sample of it. Medians,
    so that a bright emitter beside the pixel does not stand for the sky.
    """
    color = color[..., :3]
    depths, colors = _neighbours(depth), _neighbours(color)
    finite = jnp.isfinite(depths)
    same_surface = finite & (jnp.abs(jnp.where(finite, depths, 0.0) - surface_depth) <= _SAME_SURFACE * surface_depth)
    on_surface = jnp.isfinite(depth)[..., None]

    def median_of(members, own):
        median = jnp.nanmedian(jnp.where(members[..., None], colors, jnp.nan), axis=0)
        return jnp.where(jnp.any(members, axis=0)[..., None], median, jnp.where(own, color, jnp.nan))

    surface_color, sky_color = median_of(same_surface, on_surface), median_of(~finite, ~on_surface)
    known = jnp.all(jnp.isfinite(surface_color) & jnp.isfinite(sky_color), axis=-1)
    surface_color, sky_color = jnp.nan_to_num(surface_color), jnp.nan_to_num(sky_color)
    apart = surface_color - sky_color
    share = jnp.sum((color - sky_color) * apart, axis=-1) / jnp.maximum(jnp.sum(apart * apart, axis=-1), 1e-20)
    contrast = jnp.mean(jnp.abs(surface_color / (1 + jnp.abs(surface_color)) - sky_color / (1 + jnp.abs(sky_color))), -1)
    trust = jnp.where(known, jnp.clip((contrast - _UNMIX_CONTRAST) / _UNMIX_RAMP, 0.0, 1.0), 0.0)
    return jnp.clip(share, 0.0, 1.0), trust


def silhouette_coverage(
    coverage: Float[Array, "H W"], depth: Float[Array, "H W"], color: Float[Array, "H W C"]
) -> Float[Array, "H W"]:
    """The frame's coverage, or where it only repeats the depth (1 on geometry, 0 on sky) an estimate of it.

    A frame without a coverage pass (Blender writes alpha 1 through an opaque
    film; `Buffers` then takes coverage from the depth) has hard silhouettes,
    while the renderer's pixel filter blends each silhouette pixel's colour
    from both sides (and Cycles' `Z` is one sample's, either side's). There
    the colour says how much of the pixel the surface covers, where the
    surface's and the sky's colours beside it differ enough to tell (ramping
    in over `_UNMIX_CONTRAST` .. `+ _UNMIX_RAMP` in display space); elsewhere
    the pixel filter's spread stands in: taps `[.15, .7, .15]` in each
    direction (`.15`: what Cycles' frames of `benchmarks/references/blender`
    blend across a silhouette, on average). `surface_depth` of a sky pixel is
    its nearest neighbour's (`kernels.volumetric`). A real coverage pass (any
    value strictly between 0 and 1, or a covered sky pixel) is used as it is.
    """
    hard = jnp.all(coverage == jnp.isfinite(depth).astype(coverage.dtype))
    height, width = coverage.shape
    padded = jnp.pad(coverage, 1, mode="edge")
    taps = (_FILTER_SPILL, 1.0 - 2.0 * _FILTER_SPILL, _FILTER_SPILL)
    spread = sum(
        wy * wx * padded[dy : dy + height, dx : dx + width] for dy, wy in enumerate(taps) for dx, wx in enumerate(taps)
    )  # fmt: skip
    surface_depth = jnp.where(jnp.isfinite(depth), depth, jnp.min(_neighbours(depth), axis=0))
    share, trust = _unmixed_share(color.astype(coverage.dtype), depth, surface_depth)
    # Only a silhouette's pixels (sky beside them, or they are sky beside a surface) are unmixed.
    silhouette = jnp.isfinite(surface_depth) & ~jnp.all(jnp.isfinite(_neighbours(depth)) & jnp.isfinite(depth), axis=0)
    estimate = jnp.where(silhouette, trust * share + (1.0 - trust) * spread, spread)
    return jnp.where(hard, estimate, coverage)


class VolumetricFog(Effect):
    """A medium around the camera, each view ray lit only where the depth buffer lets the light through.

    The fogged frame is `color * surface + light_color * scattered +
    ambient_color * opacity` (`kernels.volumetric`): every view ray is marched
    in `num_view_steps` segments up to its depth (`buffers.ray_depth(fov_x_deg)`,
    scene units) or the medium's end; each segment's light is its share of the
    ray's extinction times its visibility of the light, read from the depth
    buffer at `num_shadow_samples` points along the screen toward the light
    (each surface a slab `thickness` times its depth deep, soft over
    `edge_softness` of its depth), times the light dimmed by the medium on its
    way in, times the Henyey-Greenstein phase of `anisotropy`.

    The medium is the `medium` part (a `Medium`, its fields `medium.extinction`,
    ...): `extinction` per scene unit at the camera's height, falling
    off as `exp(-height_falloff * height)` (per scene unit, the height above
    the camera along its up axis), inside a ball of radius `max_distance`
    (scene units) around the camera and below `layer_top` (scene units above
    the camera). `light_color` is the RGB albedo times the light's irradiance
    (for a point light at `light_depth`, at the camera's distance from it),
    `ambient_color` the RGB albedo times the sky's radiance; `direct_fraction`
    of the frame's own surface light comes from the light and is dimmed like
    the medium's. `fov_x_deg` is the horizontal field of view in degrees.

    The march runs at `1 / resolution_factor` of the frame's size in each
    direction (the largest divisor of both sides up to it, `march_factor`)
    and is upsampled with depth-aware weights; memory is O(march pixels x
    `num_view_steps`) whatever `num_shadow_samples` is.

    `effect(...)` is the fogged frame, `effect.layer(...)` the scattered light alone. Built as
    `VolumetricFog(medium=Medium(extinction=0.02, anisotropy=0.8), thickness=0.2, num_view_steps=24)`.
    """

    medium: Medium = part(Medium, formerly=FLAT_NAMES)
    height_falloff: Float[Array, ""] = param(0.0, low=0.0, high=1.0)
    layer_top: Float[Array, ""] = param(1e4, low=-1e3, high=1e4)
    direct_fraction: Float[Array, ""] = param(0.5, low=0.0, high=1.0)
    thickness: Float[Array, ""] = param(0.15, low=0.0, high=4.0)
    edge_softness: Float[Array, ""] = param(0.05, low=0.005, high=1.0)
    fov_x_deg: Float[Array, ""] = param(50.0, low=1.0, high=170.0)
    num_view_steps: int = static(16, low=1, high=256)
    num_shadow_samples: int = static(32, low=1, high=1024)
    resolution_factor: int = static(4, low=1, high=64)

    NEEDS_DEPTH: ClassVar[bool] = True

    def terms(self, buffers, light_xy, *, light_in_front=True, light_depth=math.inf):
        """`(surface, scattered, opacity)`, each `(H, W)` (`kernels.volumetric.volumetric_fog_terms`)."""
        light_xy = check_light(light_xy)
        depth = frame_ray_depth(self, buffers)
        factor = march_factor(buffers.height, buffers.width, self.resolution_factor)
        return volumetric_fog_terms(
            depth, light_xy, fov_x_deg=self.fov_x_deg, light_depth=light_depth, light_in_front=light_in_front,
            extinction=self.medium.extinction, max_distance=self.medium.max_distance,
            height_falloff=self.height_falloff, layer_top=self.layer_top, anisotropy=self.medium.anisotropy,
            direct_fraction=self.direct_fraction, thickness=self.thickness, edge_softness=self.edge_softness,
            num_view_steps=self.num_view_steps, num_shadow_samples=self.num_shadow_samples, resolution_factor=factor,
            coverage=silhouette_coverage(buffers.coverage, depth, buffers.color),
        )  # fmt: skip

    def _light(self, scattered, opacity, dtype):
        medium = self.medium
        light = scattered[..., None] * medium.light_color.astype(dtype) + opacity[..., None] * medium.ambient_color.astype(dtype)
        return light.astype(dtype)

    def layer(self, buffers, light_xy, *, light_in_front=True, light_depth=math.inf):
        """The scattered light alone, `(H, W, 3)`."""
        _, scattered, opacity = self.terms(buffers, light_xy, light_in_front=light_in_front, light_depth=light_depth)
        return self._light(scattered, opacity, buffers.color.dtype)

    def __call__(self, buffers, light_xy, *, light_in_front=True, light_depth=math.inf):
        """The fogged frame: `color * surface + layer` on the colour channels, alpha unchanged."""
        surface, scattered, opacity = self.terms(buffers, light_xy, light_in_front=light_in_front, light_depth=light_depth)
        color = buffers.color
        dtype = color.dtype
        light = self._light(scattered, opacity, dtype)
        channels = min(color.shape[-1], 3)
        if channels == 1:
            light = jnp.mean(light, axis=-1, keepdims=True)
        fogged = color[..., :channels] * surface[..., None].astype(dtype) + light[..., :channels]
        return jnp.concatenate([fogged, color[..., channels:]], axis=-1)
