"""Glow effects: sun overcasting (`SunOvercast`) and the VBex engine's lens dirt, sun spot and bloom."""

import functools
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from godrays_jax.effects.base import Effect, light_visibility, param
from godrays_jax.kernels.blur import bloom, gaussian_blur, poisson_blur
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
    source enlarged x1.3 in `glow_color`, occluders shrunk x0.8 in transparent
    black). For other buffers it is drawn in image space, the sun-overcasting article's two
    object scalings becoming a fittable number of pixels: the light source's
    coverage (`buffers.light_pass` if present, else a disc of `source_radius`
    pixels at the light) dilated by `source_grow` pixels, in `glow_color`, with
    the frame's geometry (its coverage) eroded by `occluder_shrink` pixels cut
    out in transparent black, so the glow seeps into the occluders' outlines
    (`masks.dilate` / `masks.erode`, reach `max_morphology` pixels; the disc is
    grown analytically). The blurred RGBA is added as `rgb * alpha`, as XNA's
    additive sprite blend does.
    `passes` is fittable (relaxation of `poisson_blur`, loop length `max_passes`).
    """

    blur_power: Float[Array, ""] = param(0.015, low=0.0, high=0.2)
    glow_color: Float[Array, "4"] = param((0.8, 0.5, 0.0, 0.65), low=0.0, high=10.0)
    source_radius: Float[Array, ""] = param(30.0, low=0.0, high=500.0)
    passes: Float[Array, ""] = param(2.0, low=0.0, high=8.0)
    offscreen_fade: Float[Array, ""] = param(0.5, low=0.01, high=10.0)
    source_grow: Float[Array, ""] = param(0.0, low=0.0, high=64.0)
    occluder_shrink: Float[Array, ""] = param(0.0, low=0.0, high=64.0)
    max_passes: int = eqx.field(static=True, default=2)
    max_morphology: int = eqx.field(static=True, default=4)
    blend_mode: str = eqx.field(static=True, default="add")

    def glow(self, buffers: Buffers, light_xy, *, light_in_front=True) -> Float[Array, "H W 4"]:
        """The unblurred glow pass (RGBA), rendered or drawn in image space."""
        check_light(light_xy)
        dtype = buffers.color.dtype
        visible = light_visibility(
            light_xy, buffers.height, buffers.width, fade=self.offscreen_fade, light_in_front=light_in_front, dtype=dtype
        )
        if buffers.glow_pass is not None:
            return buffers.glow_pass.astype(dtype) * visible
        if buffers.light_pass is not None:
            source = dilate(buffers.light_pass.astype(dtype), radius=self.source_grow, max_radius=self.max_morphology)
        else:
            x, y = pixel_centres(buffers.height, buffers.width, dtype)
            light_xy = jnp.asarray(light_xy, dtype)
            distance = jnp.sqrt((x - light_xy[0]) ** 2 + (y - light_xy[1]) ** 2 + 1e-12)
            source = jnp.clip(self.source_radius + self.source_grow - distance + 0.5, 0.0, 1.0)
        occluders = erode(jnp.clip(buffers.coverage, 0.0, 1.0), radius=self.occluder_shrink, max_radius=self.max_morphology)
        inside = (source * (1.0 - occluders) * visible)[..., None]
        return inside * self.glow_color.astype(dtype)

    def layer(self, buffers, light_xy, *, light_in_front=True):
        """The blurred glow as added: `(H, W, 3)` = blurred rgb times blurred alpha."""
        glow = poisson_blur(
            self.glow(buffers, light_xy, light_in_front=light_in_front),
            blur_power=self.blur_power,
            passes=self.passes,
            max_passes=self.max_passes,
        )
        return glow[..., :3] * glow[..., 3:]


class LensDirt(Effect):
    """The VBex article's lens dirt: a dirt texture lit by the sun, `lens.lens_dirt`, added.

    The texture is `lens.dirt_texture(H, W, seed=dirt_seed)`, generated at the
    frame's size on first use and cached (pass your own texture to
    `lens.lens_dirt`). Directions come from `fov_x_deg` (horizontal field of
    view, degrees); `far` (scene units) normalises depth to the VBex article's
    `LDepth`; `power` and `scale` are the VBex article's 20 and 2; `aberration` is the
    per-channel UV offset (0.002); `sun_color` tints the dirt.
    """

    power: Float[Array, ""] = param(20.0, low=1.0, high=200.0)
    scale: Float[Array, ""] = param(2.0, low=0.0, high=20.0)
    aberration: Float[Array, ""] = param(LENS_DIRT_ABERRATION, low=-0.05, high=0.05)
    sun_color: Float[Array, "3"] = param((1.0, 1.0, 1.0), low=0.0, high=10.0)
    fov_x_deg: Float[Array, ""] = param(50.0, low=1.0, high=170.0)
    far: Float[Array, ""] = param(100.0, low=1e-3, high=1e6)
    offscreen_fade: Float[Array, ""] = param(0.5, low=0.01, high=10.0)
    dirt_seed: int = eqx.field(static=True, default=0)
    view: ViewMode = eqx.field(static=True, default="pixel")
    blend_mode: str = eqx.field(static=True, default="add")

    def layer(self, buffers, light_xy, *, light_in_front=True):
        """The lit dirt alone, `(H, W, 3)`."""
        check_light(light_xy)
        dtype = buffers.color.dtype
        dirt = jnp.asarray(_cached_dirt(buffers.height, buffers.width, self.dirt_seed), dtype)
        lit = lens_dirt(
            dirt, buffers.depth, light_xy, fov_x_deg=self.fov_x_deg, far=self.far, sun_color=self.sun_color,
            power=self.power, scale=self.scale, aberration=self.aberration, light_in_front=light_in_front, view=self.view,
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
    """The VBex article's sky sun spot, `lens.sun_spot` on the sky in `sun_color`, plus its glow.

    As in the VBex article the spot is also written to a glow target (`glow`), which
    the bloom pyramid (`blur.bloom`, no threshold, `glow_weights`, `glow_sigma`
    level pixels) spreads; the layer is `spot + glow_intensity * bloom(spot)`.
    """

    sun_distance: Float[Array, ""] = param(1.0, low=0.01, high=100.0)
    sun_sharpness: Float[Array, ""] = param(1.0, low=0.0, high=100.0)
    sun_color: Float[Array, "3"] = param((1.0, 1.0, 1.0), low=0.0, high=10.0)
    fov_x_deg: Float[Array, ""] = param(50.0, low=1.0, high=170.0)
    glow_intensity: Float[Array, ""] = param(1.0, low=0.0, high=10.0)
    glow_weights: Float[Array, "4"] = param((1.0, 1.0, 1.0, 1.0), low=0.0, high=10.0)
    glow_sigma: Float[Array, ""] = param(2.0, low=0.1, high=10.0)
    offscreen_fade: Float[Array, ""] = param(0.5, low=0.01, high=10.0)
    glow_radius: int = eqx.field(static=True, default=6)
    blend_mode: str = eqx.field(static=True, default="add")

    def glow(self, buffers: Buffers, light_xy, *, light_in_front=True) -> Float[Array, "H W 3"]:
        """The glow target: the coloured spot on sky pixels (the VBex article's `Out.glow`), unblurred."""
        check_light(light_xy)
        dtype = buffers.color.dtype
        spot = sun_spot(
            buffers.height, buffers.width, light_xy, fov_x_deg=self.fov_x_deg, sun_distance=self.sun_distance,
            sun_sharpness=self.sun_sharpness, light_in_front=light_in_front, dtype=dtype,
        )  # fmt: skip
        visible = light_visibility(
            light_xy, buffers.height, buffers.width, fade=self.offscreen_fade, light_in_front=light_in_front, dtype=dtype
        )
        sky = coverage_mask(buffers.coverage.astype(dtype))[..., None]
        return spot * sky * self.sun_color.astype(dtype) * visible

    def layer(self, buffers, light_xy, *, light_in_front=True):
        """The spot and its bloom, `(H, W, 3)`."""
        spot = self.glow(buffers, light_xy, light_in_front=light_in_front)
        glow = bloom(spot, threshold=0.0, weights=self.glow_weights, sigma=self.glow_sigma, radius=self.glow_radius)
        return spot + self.glow_intensity * glow


BloomMethod = Literal["pyramid", "gaussian"]


class Bloom(Effect):
    """The VBex article's bright glow (`blur.bloom`): bright pass, blurs at 1/2 .. 1/16 resolution, summed, added.

    `method="gaussian"` is the single large Gaussian the VBex article compares it with:
    the same bright pass blurred once at full resolution with `gaussian_sigma`
    pixels (`gaussian_radius` taps each side). The layer is `intensity` times
    either. Bloom does not depend on the light: `light_xy` and
    `light_in_front` are accepted and ignored.
    """

    threshold: Float[Array, ""] = param(1.0, low=0.0, high=100.0)
    intensity: Float[Array, ""] = param(0.25, low=0.0, high=10.0)
    weights: Float[Array, "4"] = param((1.0, 1.0, 1.0, 1.0), low=0.0, high=10.0)
    sigma: Float[Array, ""] = param(2.0, low=0.1, high=10.0)
    gaussian_sigma: Float[Array, ""] = param(12.0, low=0.1, high=100.0)
    radius: int = eqx.field(static=True, default=6)
    gaussian_radius: int = eqx.field(static=True, default=36)
    method: BloomMethod = eqx.field(static=True, default="pyramid")
    blend_mode: str = eqx.field(static=True, default="add")

    def __check_init__(self):
        if self.method not in ("pyramid", "gaussian"):
            raise ValueError(f"method must be 'pyramid' or 'gaussian'; got {self.method!r}")

    def layer(self, buffers, light_xy, *, light_in_front=True):
        """The glow alone, same channels as `buffers.color` (an alpha channel is not bloomed)."""
        check_light(light_xy)
        colour = buffers.color[..., :3] if buffers.color.shape[-1] >= 3 else buffers.color[..., :1]
        if self.method == "pyramid":
            glow = bloom(colour, threshold=self.threshold, weights=self.weights, sigma=self.sigma, radius=self.radius)
        else:
            bright = jnp.maximum(colour - self.threshold.astype(colour.dtype), 0.0)
            glow = gaussian_blur(bright, sigma=self.gaussian_sigma, radius=self.gaussian_radius)
        return glow * self.intensity.astype(colour.dtype)


