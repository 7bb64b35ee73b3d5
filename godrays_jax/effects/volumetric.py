"""`VolumetricFog`: a bounded medium lit segment by segment, its shadows read from the depth buffer."""

import dataclasses
import math
from collections.abc import Collection, Sequence
from typing import ClassVar, Literal

import numpy as np
from jaxtyping import Array, Float

from godrays_jax.effects.base import Effect, frame_ray_depth
from godrays_jax.effects.fields import param, part, static
from godrays_jax.effects.medium import FLAT_NAMES, Medium
from godrays_jax.kernels.bounded_medium import BoundedMedium
from godrays_jax.kernels.light_view_shadows import covers_view
from godrays_jax.kernels.shadow_lines import REFERENCE_SIDE
from godrays_jax.kernels.shadow_reading import (
    ShadowLines,
    ShadowReading,
    ShadowSamples,
    Slabs,
)
from godrays_jax.kernels.silhouettes import silhouette_mix
from godrays_jax.kernels.volumetric import (
    composite_fog,
    fog_light,
    scattered_again,
    scattered_aside,
    volumetric_fog_terms,
)
from godrays_jax.primitives.buffers import Buffers, Silhouettes
from godrays_jax.primitives.camera import focal_length_px
from godrays_jax.primitives.checks import check_light

# On frames larger than `REFERENCE_SIDE` the march rays keep their fraction of the frame, so a preset looks and costs
# the same, up to this many times farther apart: a 1920-pixel frame samples as a 320-pixel one, a larger one finer.
_MAX_SPACING_SCALE = 6.0
SURFACE_BLUR_SIGMA = 0.08
"""The spread of the frame's light the medium scatters aside (`surface_blur`), a Gaussian's standard deviation in
the frame's larger side: how far the haze of the rooms of the path-traced references, lit by a sunbeam's patch on
the floor, spreads its halo around the patch (benchmarks/README.md, "A sunbeam through a window behind the
camera")."""
LIGHT_VIEW_COVER_MULTIPLE = 2.0
"""How far a depth map seen from the light must cover a frame's view for a fit to shade it by the map alone
(`VolumetricFog.same_on`), in multiples of the frame's farthest surface: beyond the surfaces no pixel sees, and
only a march ray's segment that reaches past its surface, or open sky, reads points there."""
SCATTERED_BLUR_SIGMA = 0.05
"""The spread of the light scattered again on its way to the camera (`scattered_blur`), a Gaussian's standard
deviation in the frame's larger side: a glow beside the beams of the path-traced references, narrower than the
surfaces' halo (benchmarks/README.md, "Light scattered again, and a race that waits for the room")."""
# The march rays' spacing (`resolution_factor`) of the stand-in `fit` fits in place of shadows read along lines, and
# the share of the lines it reads (all the bins: with half, thin slats' shadows fit worse).
_STAND_IN_FACTOR = 4
_STAND_IN_LINE_SHARE = 2


def march_factor(height: int, width: int, resolution_factor: int) -> float:
    """The march rays' spacing in pixels on a `height x width` frame (`kernels.volumetric`'s `resolution_factor`).

    `resolution_factor` pixels on a frame up to 320 pixels on its larger side; on a larger frame the same
    fraction of that side, at most 6 x `resolution_factor` pixels. 1 is no exception: every pixel's own ray up
    to 320 pixels, as far apart as a pixel of such a frame beyond (`volumetric_haze`'s shadows read along
    lines need rays that close to hold still, and look the same at any size).
    """
    scale = min(max(max(height, width) / REFERENCE_SIDE, 1.0), _MAX_SPACING_SCALE)
    return resolution_factor * scale


class VolumetricFog(Effect):
    """A medium around the camera, each view ray lit only where the depth buffer lets the light through.

    The fogged frame is `color * surface + light_color * scattered +
    ambient_color * ambient` (`kernels.volumetric`): every view ray is marched
    in `num_view_steps` segments up to its depth (`buffers.ray_depth(fov_x_deg)`,
    scene units) or the medium's end; each segment's light is its share of the
    ray's extinction times its visibility of the light, read from the depth
    buffer (each surface a slab `thickness` times its depth deep, soft over
    `edge_softness` of its depth), times the light dimmed by the medium on its
    way in, times the Henyey-Greenstein phase of `anisotropy`. `shadows` says
    how the visibility is read: `"samples"`, at the segment's middle from
    `num_shadow_samples` points along the screen toward the light
    (`kernels.shadow_samples.segment_visibility`); `"lines"`, as the mean over the
    segment, from `num_shadow_lines` lines through the light with
    `num_shadow_bins` bins of the shadow rays' coordinate each
    (`kernels.shadow_lines`): no sampling that crawls with the pixel grid, so
    shafts hold still under a moving camera, at more cost (benchmarks/README.md,
    "VolumetricFog: speed and memory").

    The medium is the `medium` part (a `Medium`, its fields `medium.extinction`,
    ...): `extinction` per scene unit at the camera's height, falling
    off as `exp(-height_falloff * height)` (per scene unit, the height above
    the camera along its up axis), inside a ball of radius `max_distance`
    (scene units) around the camera and below `layer_top` (scene units above
    the camera). `light_color` is the RGB albedo times the light's irradiance
    (for a point light at `light_depth`, at the camera's distance from it),
    `ambient_color` the RGB albedo times the sky's radiance, which with the
    light scattered more than once grows with height above the ground:
    `ambient` is the ray's opacity plus `ambient_rise` (per scene unit) times
    the height above the camera of its scattering; `direct_fraction`
    of the frame's own surface light comes from the light and is dimmed like
    the medium's. Of the frame's own light that the medium takes out of each
    ray (`1 - surface`), `surface_blur` reaches the camera a little aside,
    spread by a Gaussian of `SURFACE_BLUR_SIGMA` of the frame's larger side
    (`kernels.volumetric.scattered_aside`: forward scattering, a halo around
    bright surfaces seen through haze; 0, the presets', leaves the frame as
    single scattering of the light and the sky alone draws it). Of the
    light scattered toward the camera, `scattered_blur` scatters again and
    reaches it beside its pixel, spread by a Gaussian of
    `SCATTERED_BLUR_SIGMA` of the frame's larger side
    (`kernels.volumetric.scattered_again`: a glow beside a beam; 0, the
    presets', draws none). `fov_x_deg` is the horizontal field of view in
    degrees.

    The march runs on rays `resolution_factor` pixels apart on a frame of up
    to 320 pixels (on larger frames the same fraction of the frame, at most
    four times as many pixels apart: `march_factor`; 1 too), anchored to the light
    (under a pan they ride with the scene), any factor at any frame size; each
    ray runs through to the medium's end and every pixel reads its four
    nearest rays up to its own depth; memory is O(march rays x
    `num_view_steps`) whatever `num_shadow_samples` is, and with `"lines"`
    also `num_shadow_lines x num_shadow_bins` times a frame's diagonal in
    cells (one pixel long on a 320-pixel frame, the same fraction beyond).

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
    ambient_rise: Float[Array, ""] = param(0.0, low=-1.0, high=2.0)
    surface_blur: Float[Array, ""] = param(0.0, low=0.0, high=1.0)
    scattered_blur: Float[Array, ""] = param(0.0, low=0.0, high=1.0)
    num_view_steps: int = static(16, low=1, high=256)
    num_shadow_samples: int = static(32, low=1, high=1024)
    shadows: Literal["samples", "lines"] = static("samples")
    num_shadow_lines: int = static(512, low=2, high=8192)
    num_shadow_bins: int = static(192, low=2, high=2048)
    resolution_factor: int = static(4, low=1, high=64)

    NEEDS_DEPTH: ClassVar[bool] = True
    CAMERA_FIELDS: ClassVar[tuple[str, ...]] = ("fov_x_deg",)
    # The colours and the terms' weights enter the final sum alone; the medium's ends only where each piece of a
    # ray stops; the slabs' fields reach the shadows, which the medium's own fields do not (read along lines, the
    # shadows' table is most of the work: its derivatives are taken for these two alone). The march's fields reach
    # everything else (benchmarks/README.md, "The fit's Jacobian by stages").
    FIELD_STAGES: ClassVar[dict[str, str]] = {
        "medium.light_color": "sum", "medium.ambient_color": "sum", "direct_fraction": "sum", "ambient_rise": "sum",
        "surface_blur": "sum", "scattered_blur": "sum",
        "medium.max_distance": "ends", "layer_top": "ends", "thickness": "shadows", "edge_softness": "shadows",
        "fov_x_deg": "camera",
    }  # fmt: skip
    # The field of view moves every shadow's line, as the slabs' fields do, and every ray of the march: in the march's
    # stage its lanes carried the lines' table, a copy per lane of the stage (a fit of frames without a camera in
    # its header), and in a stage of its own XLA mixed the march's lanes ("XLA and the vmapped forward-mode Jacobian",
    # docs/findings.md). Its column by differences costs two renders and a frame's memory.
    DIFFERENCED_STAGES: ClassVar[tuple[str, ...]] = ("camera",)
    SHARP_STAGES: ClassVar[tuple[str, ...]] = ("shadows",)  # the slabs' depth and faces: a shadow's edges
    # Fitted from the start, the light scattered aside traded against the medium's extinction and light, and a room's
    # descent ended in a thin medium reaching far, its beam gone (docs/findings.md, "The frame's light scattered
    # aside"); from where the descent stops, the polish can only lower the loss. The light scattered again likewise.
    POLISH_FIELDS: ClassVar[tuple[str, ...]] = ("surface_blur", "scattered_blur")
    LIGHT_TINT_STAGE: ClassVar[str] = "sum"  # a light's tint multiplies its in-scattering and its share of the surface

    def same_on(self, frames: Sequence[Buffers]) -> "VolumetricFog":
        """One sample a segment where the frames leave the screen's shadows nothing to shade: on frames with no finite
        depth above 0 (all sky; surfaces at the eye are slabs of no depth) nothing casts a shadow, and every reading
        sees the light everywhere; on frames whose depth map seen from the light covers every point their rays reach
        within `LIGHT_VIEW_COVER_MULTIPLE` times their farthest surface (`light_view_shadows.covers_view`), the map
        alone shades those points. Either way no shadows' table is built (benchmarks/README.md, "Several lights, light
        views and rooms at 480x270"); beyond that reach, where no pixel sees a surface, a light view's points off the
        map read the screen at one sample a segment."""
        if self.shadows == "samples" and self.num_shadow_samples == 1:
            return self  # already that effect: `fit` then sees no other one to polish with
        if any(frame.depth is None for frame in frames):
            return self  # which says that it needs depth when it draws them
        if not all(self._shaded_without_the_screen(frame) for frame in frames):
            return self
        return dataclasses.replace(self, shadows="samples", num_shadow_samples=1)

    def _shaded_without_the_screen(self, frame: Buffers) -> bool:
        """Whether no surface of `frame` casts a shadow, or its depth map seen from the light covers every point
        its fog reads within `LIGHT_VIEW_COVER_MULTIPLE` times its farthest surface, through the frame and its
        march rays' margin."""
        depth = np.asarray(frame_ray_depth(self, frame))
        surfaces = depth[np.isfinite(depth) & (depth > 0)]
        if surfaces.size == 0:
            return True
        if frame.light_view is None:
            return False
        spacing = march_factor(frame.height, frame.width, self.resolution_factor)
        focal = float(focal_length_px(frame.width, self.fov_x_deg))
        reach = LIGHT_VIEW_COVER_MULTIPLE * float(surfaces.max())
        return covers_view(
            frame.light_view, height=frame.height, width=frame.width, focal=focal, reach=reach, margin=2.0 * spacing
        )

    def frames_read_once(self, frames: Sequence[Buffers], *, fitted: Collection[str]) -> list[Buffers]:
        """`frames` with their silhouettes read (`kernels.silhouettes.silhouette_mix`), each frame that has depth,
        where `fitted` leaves its depth as it is (a planar depth's distance along the rays takes the field of
        view)."""
        return [
            frame if frame.depth is None or (frame.depth_kind == "planar" and "fov_x_deg" in fitted)
            else dataclasses.replace(frame, silhouettes=Silhouettes(
                *silhouette_mix(frame.coverage, frame_ray_depth(self, frame), frame.color)))
            for frame in frames
        ]  # fmt: skip

    def fit_stand_in(self) -> "VolumetricFog":
        """Read along lines, the shadows' table and every pixel's own ray are most of a fit's work, and a fit
        matches single frames, where holding still under a moving camera does not count: `fit` fits the same
        fields read along lines more coarsely (march rays 4 pixels apart at 320 wide, half the lines;
        benchmarks/README.md, "The fit as users run it"), several times cheaper, polishes them with this effect's
        own residuals and returns them with this effect's counts."""
        if self.shadows != "lines":
            return self
        lines = max(self.num_shadow_lines // _STAND_IN_LINE_SHARE, 2)
        return dataclasses.replace(self, resolution_factor=_STAND_IN_FACTOR, num_shadow_lines=lines)

    def terms(self, buffers, light_xy, *, light_in_front=True, light_depth=math.inf):
        """`(surface, scattered, ambient)`, each `(H, W)` (`kernels.volumetric.volumetric_fog_terms`), `scattered`
        with its share `scattered_blur` scattered again (`kernels.volumetric.scattered_again`)."""
        light_xy = check_light(light_xy)
        depth = frame_ray_depth(self, buffers)
        factor = march_factor(buffers.height, buffers.width, self.resolution_factor)
        silhouettes = buffers.silhouettes
        if silhouettes is None:
            silhouettes = Silhouettes(*silhouette_mix(buffers.coverage, depth, buffers.color))
        surface, scattered, ambient = volumetric_fog_terms(
            depth, light_xy, fov_x_deg=self.fov_x_deg, light_depth=light_depth, light_in_front=light_in_front,
            medium=BoundedMedium(
                extinction=self.medium.extinction, max_distance=self.medium.max_distance,
                anisotropy=self.medium.anisotropy, height_falloff=self.height_falloff, layer_top=self.layer_top,
            ),
            slabs=Slabs(thickness=self.thickness, edge_softness=self.edge_softness), shadows=self.shadow_reading,
            direct_fraction=self.direct_fraction, ambient_rise=self.ambient_rise, num_view_steps=self.num_view_steps,
            resolution_factor=factor, coverage=silhouettes.coverage, uncovered_depth=silhouettes.uncovered_depth,
            light_view=buffers.light_view,
        )  # fmt: skip
        sigma = SCATTERED_BLUR_SIGMA * max(buffers.height, buffers.width)
        return surface, scattered_again(scattered, scattered_blur=self.scattered_blur, sigma=sigma), ambient

    @property
    def shadow_reading(self) -> ShadowReading:
        """How the kernel reads each segment's shadow (`kernels.shadow_reading`), from `shadows` and its counts."""
        if self.shadows == "lines":
            return ShadowLines(num_lines=self.num_shadow_lines, num_bins=self.num_shadow_bins)
        return ShadowSamples(count=self.num_shadow_samples)

    def _light(self, scattered, ambient):
        return fog_light(scattered, ambient, light_color=self.medium.light_color, ambient_color=self.medium.ambient_color)

    def surface_light_aside(self, color: Float[Array, "H W C"], surface: Float[Array, "H W"]) -> Float[Array, "H W 3"]:
        """The frame's own light `color` that the medium scatters a little aside, RGB (`surface_blur`; `surface`
        as `terms` gives it): part of the light the medium adds (`layer`)."""
        sigma = SURFACE_BLUR_SIGMA * max(color.shape[0], color.shape[1])
        return scattered_aside(color, surface, surface_blur=self.surface_blur, sigma=sigma)

    def layer(self, buffers, light_xy, *, light_in_front=True, light_depth=math.inf):
        """The light the medium adds, `(H, W, 3)`: the light's and the sky's scattered toward the camera, and the
        frame's own scattered aside (`surface_light_aside`)."""
        surface, scattered, ambient = self.terms(buffers, light_xy, light_in_front=light_in_front, light_depth=light_depth)
        added = self._light(scattered, ambient) + self.surface_light_aside(buffers.color, surface)
        return added.astype(buffers.color.dtype)

    def __call__(self, buffers, light_xy, *, light_in_front=True, light_depth=math.inf):
        """The fogged frame: `color * surface + layer` on the colour channels, alpha unchanged."""
        surface, scattered, ambient = self.terms(buffers, light_xy, light_in_front=light_in_front, light_depth=light_depth)
        added = self._light(scattered, ambient) + self.surface_light_aside(buffers.color, surface)
        return composite_fog(buffers.color, surface, added)
