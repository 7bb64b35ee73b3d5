"""Glow effects: sun overcasting (`SunOvercast`) and the VBex engine's lens dirt, sun spot and bloom."""

import functools
import math
from typing import ClassVar, Literal

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from godrays_jax.effects.base import Effect, Units, frame_ray_depth, light_visibility, pixels_per_unit, reach_taps
from godrays_jax.effects.fields import MAX_SEED, Part, count_param, param, part, size_param, size_reach, static
from godrays_jax.kernels.blur import bloom, gaussian_blur, poisson_blur
from godrays_jax.kernels.composite import BlendMode
from godrays_jax.kernels.lens import (
    LENS_DIRT_ABERRATION,
    ViewMode,
    dirt_texture,
    lens_dirt,
    sun_spot,
)
from godrays_jax.kernels.masks import coverage_mask, dilate, erode
from godrays_jax.primitives.buffers import Buffers
from godrays_jax.primitives.checks import check_light
from godrays_jax.primitives.sampling import pixel_centres


class SunOvercast(Effect):
    """The sun-overcasting article's sun overcasting: a glow pass blurred twice with the Poisson blur, then added.

    The glow pass is `buffers.glow_pass` when the rasterizer rendered it (the
    source enlarged x1.3 in the article's orange, occluders shrunk x0.8 in transparent
    black). For other buffers it is drawn in image space, the sun-overcasting article's two
    object scalings becoming fittable sizes (frame units: fractions of the
    larger side; pixels under `units="px"`): the light source's coverage
    (`buffers.light_pass` if present, else a disc of radius `source_radius` at
    the light) dilated by `source_grow`, in `tint` (RGBA: the article's colour, alpha included), with the frame's
    geometry (its coverage) eroded by `occluder_shrink` cut out in transparent
    black, so the glow seeps into the occluders' outlines (`masks.dilate` /
    `masks.erode`, reach `morphology_reach`; the disc is grown analytically).
    `blur_power` is in UV units in either unit system, as the article writes it. The blurred RGBA is added as `rgb * alpha`, as XNA's
    additive sprite blend does.
    `num_passes` is fittable (relaxation of `poisson_blur`, loop length `max_passes`).
    """

    blur_power: Float[Array, ""] = param(0.015, low=0.0, high=0.2)
    tint: Float[Array, "4"] = param((0.8, 0.5, 0.0, 0.65), low=0.0, high=10.0, formerly=("glow_color",))
    source_radius: Float[Array, ""] = size_param(0.1, low=0.0, high=2.0, px_high=4096.0)
    num_passes: Float[Array, ""] = count_param(2.0, low=0.0, high=8.0, cap="max_passes", formerly=("passes",))
    offscreen_fade: Float[Array, ""] = param(0.5, low=0.01, high=10.0)
    source_grow: Float[Array, ""] = size_param(0.0, low=0.0, high=0.1, px_high=64.0, cap="morphology_reach")
    occluder_shrink: Float[Array, ""] = size_param(0.0, low=0.0, high=0.1, px_high=64.0, cap="morphology_reach")
    max_passes: int = static(2, low=0, high=8)
    morphology_reach: float = size_reach(0.0125)
    blend_mode: BlendMode = static("add")
    units: Units = static("frame")

    def glow(self, buffers: Buffers, light_xy, *, light_in_front=True) -> Float[Array, "H W 4"]:
        """The unblurred glow pass (RGBA), rendered or drawn in image space."""
        light_xy = check_light(light_xy)
        dtype = buffers.color.dtype
        visible = light_visibility(
            light_xy, buffers.height, buffers.width, fade=self.offscreen_fade, light_in_front=light_in_front, dtype=dtype
        )
        if buffers.glow_pass is not None:
            return buffers.glow_pass.astype(dtype) * visible
        scale = pixels_per_unit(self.units, buffers.height, buffers.width)
        reach = reach_taps(self.morphology_reach, self.units, buffers.height, buffers.width)
        grow, shrink = self.source_grow * scale, self.occluder_shrink * scale
        if buffers.light_pass is not None:
            source = dilate(buffers.light_pass.astype(dtype), radius=grow, max_radius=reach)
        else:
            x, y = pixel_centres(buffers.height, buffers.width, dtype)
            light_xy = jnp.asarray(light_xy, dtype)
            distance = jnp.sqrt((x - light_xy[0]) ** 2 + (y - light_xy[1]) ** 2 + 1e-12)
            source = jnp.clip(self.source_radius * scale + grow - distance + 0.5, 0.0, 1.0)
        occluders = erode(jnp.clip(buffers.coverage, 0.0, 1.0), radius=shrink, max_radius=reach)
        inside = (source * (1.0 - occluders) * visible)[..., None]
        return inside * self.tint.astype(dtype)

    def layer(self, buffers, light_xy, *, light_in_front=True, light_depth=math.inf):
        """The blurred glow as added: `(H, W, 3)` = blurred rgb times blurred alpha."""
        glow = poisson_blur(
            self.glow(buffers, light_xy, light_in_front=light_in_front),
            blur_power=self.blur_power,
            num_passes=self.num_passes,
            max_passes=self.max_passes,
        )
        return glow[..., :3] * glow[..., 3:]


class LensDirt(Effect):
    """The VBex article's lens dirt: a dirt texture lit by the sun, `lens.lens_dirt`, added.

    The texture is `lens.dirt_texture(H, W, seed=dirt_seed)`, generated at the
    frame's size on first use and cached (pass your own texture to
    `lens.lens_dirt`). Directions come from `fov_x_deg`, the frame's
    horizontal field of view in degrees (`render` writes it with the frame);
    `far_plane` (scene units) normalises depth to the VBex article's `LDepth`;
    `power` and `scale` are the VBex article's 20 and 2; `aberration` is the
    per-channel UV offset (0.002); `tint` (the article's SunColor) colours the dirt. `depth_floor`
    is the article's `.8` in `max(LDepth, .8)`. With `depth_in_power` true
    (the default) the formula is the article's as printed,
    `pow(saturate(dot * max(LDepth, .8)), 20) * 2`: geometry nearer than
    `depth_floor * far_plane` dims the dirt by `0.8 ** 20`, the article's
    "reduce intensity on occluder by LinearDepth", with a hard edge along
    every silhouette; `depth_in_power` false (ours) scales the intensity
    after the power instead, dimming near geometry only to `depth_floor`
    of the sky's (`lens.lens_dirt_intensity`).
    """

    power: Float[Array, ""] = param(20.0, low=1.0, high=200.0)
    scale: Float[Array, ""] = param(2.0, low=0.0, high=20.0)
    aberration: Float[Array, ""] = param(LENS_DIRT_ABERRATION, low=-0.05, high=0.05)
    tint: Float[Array, "3"] = param((1.0, 1.0, 1.0), low=0.0, high=10.0, formerly=("sun_color",))
    fov_x_deg: Float[Array, ""] = param(50.0, low=1.0, high=170.0)
    far_plane: Float[Array, ""] = param(100.0, low=1e-3, high=1e6, formerly=("far",))
    offscreen_fade: Float[Array, ""] = param(0.5, low=0.01, high=10.0)
    depth_floor: Float[Array, ""] = param(0.8, low=0.0, high=1.0)
    dirt_seed: int = static(0, low=0, high=MAX_SEED)
    view: ViewMode = static("pixel")
    depth_in_power: bool = static(True)
    blend_mode: BlendMode = static("add")

    NEEDS_DEPTH: ClassVar[bool] = True
    # Its `far_plane` is where its dirt stops catching light, a parameter of its own, not the camera's clip plane.
    CAMERA_FIELDS: ClassVar[tuple[str, ...]] = ("fov_x_deg",)

    def layer(self, buffers, light_xy, *, light_in_front=True, light_depth=math.inf):
        """The lit dirt alone, `(H, W, 3)`."""
        light_xy = check_light(light_xy)
        dtype = buffers.color.dtype
        dirt = jnp.asarray(_cached_dirt(buffers.height, buffers.width, self.dirt_seed), dtype)
        lit = lens_dirt(
            dirt, frame_ray_depth(self, buffers), light_xy, fov_x_deg=self.fov_x_deg, far_plane=self.far_plane,
            tint=self.tint, power=self.power, scale=self.scale, aberration=self.aberration, light_in_front=light_in_front,
            view=self.view, depth_floor=self.depth_floor, depth_in_power=self.depth_in_power,
        )  # fmt: skip
        visible = light_visibility(
            light_xy, buffers.height, buffers.width, fade=self.offscreen_fade, light_in_front=light_in_front, dtype=dtype
        )
        return lit.astype(dtype) * visible


@functools.lru_cache(maxsize=8)
def _cached_dirt(height: int, width: int, seed: int) -> np.ndarray:
    # Made once per size and seed, also when first asked for inside a jit trace.
    with jax.ensure_compile_time_eval():
        return np.asarray(dirt_texture(height, width, seed=seed))


class SunSpot(Effect):
    """The VBex article's sky sun spot, `lens.sun_spot` on the sky in `tint` (the article's SunColor), plus its glow.

    As in the VBex article the spot is also written to a glow target (`glow`), which
    its `bloom` (a `BloomBlur`, its fields `bloom.intensity`, `bloom.blur_sigma`, ...)
    spreads: the layer is `spot + bloom.blurred(spot)`, the spot blurred as
    `Bloom` blurs its glow target (no threshold), and the article adds the
    glow at full strength (`bloom.intensity = 1`).
    """

    CAMERA_FIELDS: ClassVar[tuple[str, ...]] = ("fov_x_deg",)

    sun_distance: Float[Array, ""] = param(1.0, low=0.01, high=100.0)
    sun_sharpness: Float[Array, ""] = param(1.0, low=0.0, high=100.0)
    tint: Float[Array, "3"] = param((1.0, 1.0, 1.0), low=0.0, high=10.0, formerly=("sun_color",))
    fov_x_deg: Float[Array, ""] = param(50.0, low=1.0, high=170.0)
    offscreen_fade: Float[Array, ""] = param(0.5, low=0.01, high=10.0)
    bloom: "BloomBlur" = part(
        lambda: BloomBlur(intensity=1.0, blur_sigma=0.0125, blur_reach=0.0375),
        formerly={
            "glow_intensity": "intensity", "bloom_intensity": "intensity", "glow_weights": "weights",
            "bloom_weights": "weights", "glow_sigma": "blur_sigma", "bloom_blur_sigma": "blur_sigma",
            "glow_reach": "blur_reach", "bloom_blur_reach": "blur_reach", "units": "units",
        },
    )  # fmt: skip
    blend_mode: BlendMode = static("add")

    def glow(self, buffers: Buffers, light_xy, *, light_in_front=True) -> Float[Array, "H W 3"]:
        """The glow target: the coloured spot on sky pixels (the VBex article's `Out.glow`), unblurred."""
        light_xy = check_light(light_xy)
        dtype = buffers.color.dtype
        spot = sun_spot(
            buffers.height, buffers.width, light_xy, fov_x_deg=self.fov_x_deg, sun_distance=self.sun_distance,
            sun_sharpness=self.sun_sharpness, light_in_front=light_in_front, dtype=dtype,
        )  # fmt: skip
        visible = light_visibility(
            light_xy, buffers.height, buffers.width, fade=self.offscreen_fade, light_in_front=light_in_front, dtype=dtype
        )
        sky = coverage_mask(buffers.coverage.astype(dtype))[..., None]
        return spot * sky * self.tint.astype(dtype) * visible

    def layer(self, buffers, light_xy, *, light_in_front=True, light_depth=math.inf):
        """The spot and its bloom, `(H, W, 3)`."""
        spot = self.glow(buffers, light_xy, light_in_front=light_in_front)
        return spot + self.bloom.blurred(spot)


def _pyramid(image, sigma, reach, weights, units):
    """`blur.bloom` (no threshold) with a frame-unit `sigma` and `reach`: the same texels' blur at every level.

    `sigma` and `reach` are those of the finest (1/2) level in frame units (or
    full-resolution pixels under `units="px"`), that is `sigma * max(W, H) / 2`
    texels of every level, as the article blurs each of its four targets with
    one kernel.
    """
    height, width = image.shape[0], image.shape[1]
    level_sigma = sigma * pixels_per_unit(units, height, width) / 2
    taps = reach_taps(reach, units, height, width, level=2)
    return bloom(image, threshold=0.0, weights=weights, sigma=level_sigma, reach=taps)


LUMINANCE = (0.2126, 0.7152, 0.0722)
"""Rec. 709 luminance weights: the frame's bright pass keeps a pixel's hue."""


def bright_part(colour: Float[Array, "H W C"], threshold) -> Float[Array, "H W C"]:
    """What of a frame blooms: `colour * max(Y - threshold, 0) / Y`, `Y` its luminance (the value of a 1-channel image).

    Thresholding luminance, not each channel, keeps the colour: a pixel of
    `(1.57, 0.98, 0.40)` over a threshold of 1 blooms orange, not red.
    """
    dtype = colour.dtype
    luminance = (
        colour[..., 0]
        if colour.shape[-1] == 1
        else jnp.tensordot(colour[..., :3], jnp.asarray(LUMINANCE, dtype), 1, precision="highest")
    )
    luminance = luminance[..., None]
    positive = luminance > 0
    excess = jnp.maximum(luminance - jnp.asarray(threshold, dtype), 0.0)
    return jnp.where(positive, colour * excess / jnp.where(positive, luminance, 1.0), 0.0)


BloomMethod = Literal["pyramid", "gaussian"]
BloomSource = Literal["glow_target", "frame"]


class BloomBlur(Part):
    """How a bloom spreads what glows (the VBex article's four targets, or one wide Gaussian), and how much of it.

    `method="pyramid"` is the article's four targets (`blur.bloom`: box-reduced
    to 1/2, 1/4, 1/8 and 1/16, each blurred by the same Gaussian of `blur_sigma`
    at the finest level, frame units, taps to `blur_reach`; see `_pyramid`),
    weighted by `weights` and summed; `method="gaussian"` is the single large
    Gaussian the article compares it with, `wide_blur_sigma` at full
    resolution (taps to `wide_blur_reach`). Sizes are fractions of the frame's
    larger side (pixels under `units="px"`). `blurred` is `intensity` times
    either. `Bloom` has these fields; `SunSpot` holds them as its `bloom` part.
    """

    intensity: Float[Array, ""] = param(0.25, low=0.0, high=10.0)
    weights: Float[Array, "4"] = param((1.0, 1.0, 1.0, 1.0), low=0.0, high=10.0)
    blur_sigma: Float[Array, ""] = size_param(0.0125, low=1e-4, high=0.2, px_high=100.0, formerly=("sigma",))
    wide_blur_sigma: Float[Array, ""] = size_param(
        0.0375, low=1e-4, high=0.5, px_high=500.0, formerly=("gaussian_sigma",)
    )
    blur_reach: float = size_reach(0.0375, formerly=("reach",))
    wide_blur_reach: float = size_reach(0.1125, formerly=("gaussian_reach",))
    method: BloomMethod = static("pyramid")
    units: Units = static("frame")

    def blurred(self, glowing: Float[Array, "H W C"]) -> Float[Array, "H W C"]:
        """What glows, blurred by `method` and times `intensity`."""
        if self.method == "pyramid":
            glow = _pyramid(glowing, self.blur_sigma, self.blur_reach, self.weights, self.units)
        else:
            height, width = glowing.shape[0], glowing.shape[1]
            scale = pixels_per_unit(self.units, height, width)
            taps = reach_taps(self.wide_blur_reach, self.units, height, width)
            glow = gaussian_blur(glowing, sigma=self.wide_blur_sigma * scale, reach=taps)
        return glow * self.intensity.astype(glow.dtype)


class Bloom(Effect, BloomBlur):
    """The VBex article's bright glow: what glows, blurred at 1/2 .. 1/16 resolution, summed, added.

    What glows (`bloom_source`): `"glow_target"`, the article's glow target
    (`buffers.glow_target`: the sky's sun spot, emissive surfaces and night
    lights, the atmosphere's shell, as the rasterizer renders them), or for buffers
    without one (and for `"frame"`) the frame's bright part
    (`bright_part(colour, threshold)`, luminance above `threshold`, hue kept).
    It is blurred as its `BloomBlur` fields say (`method`, `blur_sigma`, ...,
    `intensity`). Bloom does not depend on the light: `light_xy`,
    `light_in_front` and `light_depth` are accepted and ignored.
    """

    threshold: Float[Array, ""] = param(1.0, low=0.0, high=100.0)
    bloom_source: BloomSource = static("frame")
    blend_mode: BlendMode = static("add")

    def glowing(self, buffers: Buffers) -> Float[Array, "H W C"]:
        """What blooms, unblurred: the glow target, or the frame's bright part (see the class docstring)."""
        colour = buffers.color[..., :3] if buffers.color.shape[-1] >= 3 else buffers.color[..., :1]
        if self.bloom_source == "glow_target" and buffers.glow_target is not None:
            return buffers.glow_target.astype(colour.dtype)
        return bright_part(colour, self.threshold)

    def layer(self, buffers, light_xy, *, light_in_front=True, light_depth=math.inf):
        """The glow alone, `(H, W, 3)` (1 channel for a 1-channel frame without a glow target)."""
        check_light(light_xy)
        return self.blurred(self.glowing(buffers))
