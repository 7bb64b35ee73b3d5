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

Beyond the frame's edges the buffer knows nothing. Under open sky a shadow ray
that leaves the screen meets nothing; in a room it meets the ceiling or a wall
out of view, and the light enters only through the openings the frame shows.
`enclosure` tells the two apart by the frame's sky, and both readings shade a
ray that leaves a closed frame in front of the surface seen where it leaves.
"""

import math
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from godrays_jax.kernels.shadow_lines import default_cell_px, lines_reader
from godrays_jax.kernels.shadow_samples import segment_visibility
from godrays_jax.primitives.checks import check_scalar, is_static_int

ENCLOSED_SKY: tuple[float, float] = (0.05, 0.15)
"""The shares of a frame's pixels that are sky at and below which `enclosure` reads it as closed beyond its edges,
and at and above which as open (linear between): a room's windows against the sky of any outdoor frame
(benchmarks/README.md, "A sunbeam through a window in view")."""


def enclosure(depth: Float[Array, "H W"]) -> Float[Array, ""]:
    """How closed the frame of `depth` (scene units, `+inf` on sky) is beyond its edges, in [0, 1]: 1 where at most
    `ENCLOSED_SKY[0]` of its pixels are sky (a room, its windows), 0 from `ENCLOSED_SKY[1]` up (open air), linear
    between, so that a sequence whose sky grows fades from one reading to the other. No gradient: what the frame
    is, not a fitted value."""
    low, high = ENCLOSED_SKY
    sky = jnp.logical_not(jnp.isfinite(jax.lax.stop_gradient(depth)))
    sky = jnp.mean(sky.astype(jnp.result_type(depth, jnp.float32)))
    return jnp.clip((high - sky) / (high - low), 0.0, 1.0)


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
    """What the two readings share: how the fog asks for its segments' visibility."""

    def reader(
        self,
        depth: Float[Array, "H W"],
        light_xy: Float[Array, "2"],
        *,
        fov_x_deg: Float[ArrayLike, ""],
        light_depth: Float[ArrayLike, ""] = math.inf,
        light_in_front: Bool[ArrayLike, ""] | bool = True,
        slabs: Slabs,
        max_distance: Float[ArrayLike, ""],
        enclosed: Float[ArrayLike, ""] = 0.0,
    ) -> Callable[[Array, Array, Array, Array], Array]:
        """The function `visibility(pixel_xy, lower, upper, middles)`: how much of the light reaches each segment
        `[lower, upper]` (`(h, w, M)`, scene units) of the view rays through `pixel_xy` (`(h, w, 2)`, pixels), in
        [0, 1]. `ShadowSamples` reads it at `middles` (the distances where each segment's light comes from),
        `ShadowLines` over the whole segment, its bins reaching the largest shadow ray inside the medium's radius
        `max_distance`, from one table of the frame that every call reads (a march in bands builds it once).
        `depth` and `light_xy` in the caller's floating dtype, checked by the caller; `enclosed`, how closed the
        frame is beyond its edges (`enclosure`)."""
        light = dict(
            fov_x_deg=fov_x_deg, light_depth=light_depth, light_in_front=light_in_front, thickness=slabs.thickness,
            edge_softness=slabs.edge_softness, enclosed=enclosed,
        )  # fmt: skip
        return self._reader(depth, light_xy, max_distance, light)


class ShadowSamples(_Reading):
    """Each segment's shadow read at its middle, from `count` samples (a static int >= 1) along the screen
    segment toward the light (`shadow_samples.segment_visibility`)."""

    count: int = eqx.field(static=True, default=32)

    def __check_init__(self):
        _check_count(self.count, "the shadow samples' count", 1)

    def _reader(self, depth, light_xy, max_distance, light):
        def visibility(pixel_xy, lower, upper, middles):
            return segment_visibility(depth, light_xy, pixel_xy, middles, num_shadow_samples=self.count, **light)

        return visibility


class ShadowLines(_Reading):
    """Each segment's shadow as the mean over the segment, read from `num_lines` lines through the light's
    position, each in `num_bins` bins of the shadow rays' coordinate (static ints >= 2;
    `shadow_lines.segment_visibility_by_lines`)."""

    num_lines: int = eqx.field(static=True, default=512)
    num_bins: int = eqx.field(static=True, default=192)

    def __check_init__(self):
        _check_count(self.num_lines, "num_lines", 2)
        _check_count(self.num_bins, "num_bins", 2)

    def _reader(self, depth, light_xy, max_distance, light):
        read = lines_reader(
            depth, light_xy, max_distance=max_distance, num_lines=self.num_lines, num_bins=self.num_bins,
            cell_px=default_cell_px(*depth.shape), **light,
        )  # fmt: skip

        def visibility(pixel_xy, lower, upper, middles):
            return read(pixel_xy, lower, upper)

        return visibility


ShadowReading = ShadowSamples | ShadowLines
"""A segment's shadow read by samples at its middle or along lines through the light."""
