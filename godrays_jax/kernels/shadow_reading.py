"""How a view segment's shadow is read from the depth buffer: the slabs that stand for the surfaces, and the reading.

The depth buffer is a height field of unknown thickness: a surface at depth
`D` is taken as the slab `[D, D * (1 + thickness)]` along its camera ray,
with soft faces `edge_softness` wide (`Slabs`). A segment's shadow is read
either at its middle from samples along the screen toward the light
(`ShadowSamples`, `shadow_samples.segment_visibility`) or as the mean over
the segment from lines through the light (`ShadowLines`,
`shadow_lines.segment_visibility_by_lines`): no sampling that crawls under a
camera pan, at more cost. `volumetric.volumetric_fog_terms` takes one of
each.
"""

import math

import equinox as eqx
from jaxtyping import Array, ArrayLike, Bool, Float

from godrays_jax.kernels.shadow_lines import segment_visibility_by_lines
from godrays_jax.kernels.shadow_samples import segment_visibility
from godrays_jax.primitives.checks import check_scalar, is_static_int


class Slabs(eqx.Module):
    """The surfaces' slabs: `thickness`, each slab's depth as a fraction of its own depth (>= 0), and
    `edge_softness`, the width of its soft faces as a fraction of its depth (> 0), so that the thickness, the
    light and the field of view have gradients."""

    thickness: Float[ArrayLike, ""] = 0.15
    edge_softness: Float[ArrayLike, ""] = 0.05

    def __check_init__(self):
        check_scalar(self.thickness, "thickness")
        check_scalar(self.edge_softness, "edge_softness")


def _check_count(value, name: str, smallest: int) -> None:
    if not is_static_int(value) or value < smallest:
        raise ValueError(f"{name} must be a Python int >= {smallest}, got {value!r}")


class _Reading(eqx.Module):
    """What the two readings share: how the fog asks for a segment's visibility."""

    def segment_visibility(
        self,
        depth: Float[Array, "H W"],
        light_xy: Float[ArrayLike, "2"],
        pixel_xy: Float[Array, "h w 2"],
        lower: Float[Array, "h w M"],
        upper: Float[Array, "h w M"],
        middles: Float[Array, "h w M"],
        *,
        fov_x_deg: Float[ArrayLike, ""],
        light_depth: Float[ArrayLike, ""] = math.inf,
        light_in_front: Bool[ArrayLike, ""] | bool = True,
        slabs: Slabs,
        max_distance: Float[ArrayLike, ""],
    ) -> Float[Array, "h w M"]:
        """How much of the light reaches each segment `[lower, upper]` (scene units) of the view rays through
        `pixel_xy` (pixels), in [0, 1]: `ShadowSamples` reads it at `middles` (the distances where each segment's
        light comes from), `ShadowLines` over the whole segment, its bins reaching the largest shadow ray inside
        the medium's radius `max_distance`."""
        light = dict(
            fov_x_deg=fov_x_deg, light_depth=light_depth, light_in_front=light_in_front, thickness=slabs.thickness,
            edge_softness=slabs.edge_softness,
        )  # fmt: skip
        return self._read(depth, light_xy, pixel_xy, (lower, upper, middles), max_distance, light)


class ShadowSamples(_Reading):
    """Each segment's shadow read at its middle, from `count` samples (a static int >= 1) along the screen
    segment toward the light (`shadow_samples.segment_visibility`)."""

    count: int = eqx.field(static=True, default=32)

    def __check_init__(self):
        _check_count(self.count, "the shadow samples' count", 1)

    def _read(self, depth, light_xy, pixel_xy, segments, max_distance, light):
        _, _, middles = segments
        return segment_visibility(depth, light_xy, pixel_xy, middles, num_shadow_samples=self.count, **light)


class ShadowLines(_Reading):
    """Each segment's shadow as the mean over the segment, read from `num_lines` lines through the light's
    position, each in `num_bins` bins of the shadow rays' coordinate (static ints >= 2;
    `shadow_lines.segment_visibility_by_lines`)."""

    num_lines: int = eqx.field(static=True, default=512)
    num_bins: int = eqx.field(static=True, default=192)

    def __check_init__(self):
        _check_count(self.num_lines, "num_lines", 2)
        _check_count(self.num_bins, "num_bins", 2)

    def _read(self, depth, light_xy, pixel_xy, segments, max_distance, light):
        lower, upper, _ = segments
        return segment_visibility_by_lines(
            depth, light_xy, pixel_xy, lower, upper, max_distance=max_distance, num_lines=self.num_lines,
            num_bins=self.num_bins, **light,
        )  # fmt: skip


ShadowReading = ShadowSamples | ShadowLines
"""A segment's shadow read by samples at its middle or along lines through the light."""
