"""Participating media: `ScatteringFog`, a homogeneous medium in closed form with screen-space shaft shadowing."""

import functools
import math
from typing import ClassVar

import jax.numpy as jnp
from jaxtyping import Array, Float

from godrays_jax.effects.base import Effect, frame_ray_depth, light_visibility
from godrays_jax.effects.fields import count_param, param, part, static
from godrays_jax.effects.medium import FLAT_NAMES, Medium
from godrays_jax.kernels.masks import coverage_mask
from godrays_jax.kernels.media import apply_fog, in_scattering
from godrays_jax.kernels.rays import radial_rays
from godrays_jax.primitives.buffers import Buffers
from godrays_jax.primitives.checks import check_light


class ScatteringFog(Effect):
    """A homogeneous participating medium: extinction of the frame plus in-scattered sky and sun light.

    The frame becomes `color * T + (1 - T) * (ambient_color + light_color * p(theta) * lit)`
    (`media.apply_fog`, single scattering in closed form) with the fields of
    its `medium` (a `Medium`: `medium.extinction`, `medium.max_distance`,
    `medium.anisotropy`, `medium.light_color`, `medium.ambient_color`):
    `T = exp(-extinction * min(depth, max_distance))` with `depth` the distance
    along the camera ray in scene units (`buffers.ray_depth(fov_x_deg)`: planar
    depth converted with the effect's field of view; sky: `max_distance`), `p`
    the Henyey-Greenstein phase function (per steradian) of `anisotropy` at the
    angle between each pixel's view ray and the sun (from `fov_x_deg`, the
    horizontal field of view in degrees).
    `ScatteringFog(medium=Medium(extinction=0.02), shadow_strength=0.5)`.

    `lit` is the screen-space estimate of how much of each ray the sun
    reaches, so occluders cast shafts of shadow into the medium:
    `lit = 1 - shadow_strength * v * (1 - rays)`, `rays` the GPU Gems radial
    blur (`radial_rays`, `num_samples` up to `max_samples`, `density`,
    `decay`) of the open-sky mask toward the sun, normalised so open sky gives
    1, and `v` the off-screen fade (`light_visibility`): far off-screen or
    behind-camera suns cast no screen-space shafts, while the extinction, the
    ambient light and the (backward, behind the camera) sun lobe stay.

    Unlike the additive effects the medium also removes light: `effect(...)` is
    the fogged frame, `effect.layer(...)` the in-scattered light alone (the
    frame is `color * media.transmittance(...) + layer`).
    """

    medium: Medium = part(Medium, formerly=FLAT_NAMES | {"ambient": "ambient_color", "sun_irradiance": "light_color"})
    fov_x_deg: Float[Array, ""] = param(50.0, low=1.0, high=170.0)
    shadow_strength: Float[Array, ""] = param(1.0, low=0.0, high=1.0, formerly=("shaft_strength",))
    density: Float[Array, ""] = param(1.0, low=0.0, high=2.0)
    decay: Float[Array, ""] = param(0.97, low=0.5, high=1.0)
    num_samples: Float[Array, ""] = count_param(32.0, low=1.0, high=512.0, cap="max_samples")
    offscreen_fade: Float[Array, ""] = param(0.5, low=0.01, high=10.0)
    max_samples: int = static(32, low=1, high=4096)

    NEEDS_DEPTH: ClassVar[bool] = True
    CAMERA_FIELDS: ClassVar[tuple[str, ...]] = ("fov_x_deg",)

    def lit(self, buffers: Buffers, light_xy, *, light_in_front=True) -> Float[Array, "H W"]:
        """The fraction of each camera ray the sun reaches, in [0, 1] (1 without occluders)."""
        light_xy = check_light(light_xy)
        dtype = buffers.color.dtype
        open_sky = coverage_mask(buffers.coverage.astype(dtype))[..., None]
        shafts = functools.partial(
            radial_rays, light_xy=light_xy, num_samples=self.num_samples, max_samples=self.max_samples,
            density=self.density, decay=self.decay, weight=1.0, exposure=1.0,
        )  # fmt: skip
        # Clamp addressing makes a 1x1 image of ones read 1 everywhere: its rays are the
        # weight sum, which normalises open sky to exactly 1 at any (relaxed) sample count.
        normalised = shafts(open_sky)[..., 0] / shafts(jnp.ones((1, 1, 1), dtype))[0, 0, 0]
        visible = light_visibility(
            light_xy, buffers.height, buffers.width, fade=self.offscreen_fade, light_in_front=light_in_front, dtype=dtype
        )
        return 1.0 - self.shadow_strength.astype(dtype) * visible * (1.0 - normalised)

    def _fog_options(self, buffers, light_xy, light_in_front):
        return dict(
            fov_x_deg=self.fov_x_deg, extinction=self.medium.extinction, max_distance=self.medium.max_distance,
            ambient_color=self.medium.ambient_color, light_color=self.medium.light_color,
            anisotropy=self.medium.anisotropy,
            light_in_front=light_in_front,
            lit=self.lit(buffers, light_xy, light_in_front=light_in_front),
        )  # fmt: skip

    def layer(self, buffers, light_xy, *, light_in_front=True, light_depth=math.inf):
        """The in-scattered light alone, `(H, W, 3)`."""
        options = self._fog_options(buffers, light_xy, light_in_front)
        return in_scattering(frame_ray_depth(self, buffers), light_xy, **options).astype(buffers.color.dtype)

    def __call__(self, buffers, light_xy, *, light_in_front=True, light_depth=math.inf):
        """The fogged frame: `color * T + layer` on the colour channels, alpha unchanged."""
        options = self._fog_options(buffers, light_xy, light_in_front)
        return apply_fog(buffers.color, frame_ray_depth(self, buffers), light_xy, **options)


