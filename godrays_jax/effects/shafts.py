"""Light-shaft effects: radial rays (`GodRays`, GPU Gems 3 ch. 13) and kbEngine's flare-outs (`FlareOuts`)."""

import math
from typing import ClassVar, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from godrays_jax.effects.base import (
    Effect,
    FlareShape,
    SceneMask,
    Source,
    Units,
    emitter_inputs,
    param,
    pixels_per_unit,
    reach_taps,
    size_param,
    size_reach,
    texture_field,
)
from godrays_jax.kernels.blur import gaussian_blur
from godrays_jax.kernels.fast import fast_radial_rays, radial_rays_multipass
from godrays_jax.kernels.masks import bright_pass
from godrays_jax.kernels.rays import radial_rays_of, scale_iterated_flares_of
from godrays_jax.primitives.checks import check_light, is_static_int
from godrays_jax.primitives.resample import downsample_box, upsample_bilinear

RayMethod = Literal["exact", "multipass", "fast"]


RAY_METHODS: tuple[str, ...] = ("exact", "multipass", "fast")
"""`GodRays.method`: the exact loop, or the fast variants of `godrays_jax.kernels.fast` (errors in benchmarks/README.md)."""

STEP_CLAMP_LIMIT = 0.5
"""The XNA crepuscular-rays article's `clamp(ScreenPosition.w * ScreenPosition.z, 0, .5)` upper limit."""


def step_clamp(light_depth) -> Float[Array, ""] | float:
    """The XNA article's step factor `clamp(w * z, 0, .5)` from the light's distance (scene units).

    `w * z` after the perspective divide is the light's clip-space z, which
    is its view depth less the near plane (scaled by `far / (far - near)`):
    the light's depth for a near plane much closer than the light. So any
    light more than half a unit in front halves the step, and a light at
    infinity (`+inf`) gives 0.5. A concrete depth gives a Python float (so
    the rays' window around the light stays known at trace time).
    """
    if isinstance(light_depth, jax.core.Tracer):
        return jnp.clip(light_depth, 0.0, STEP_CLAMP_LIMIT)
    return float(np.clip(float(np.asarray(light_depth)), 0.0, STEP_CLAMP_LIMIT))


def _flare_reach_px(effect, height: int, width: int) -> float | None:
    """How far from the light the default flare can be non-zero, in pixels, when known at trace time.

    The procedural flare and the cone are black outside their inscribed ellipse; a user's
    texture may not be (clamp addressing repeats its border), so no promise.
    """
    size = effect.flare_size
    if effect.source != "disc" or effect.flare_texture is not None or isinstance(size, jax.core.Tracer):
        return None
    return float(size) * (max(height, width) if effect.units == "frame" else 1.0)


class GodRays(Effect):
    """Radial light shafts, the XNA crepuscular-rays and galaxy-engine VLS articles (GPU Gems 3 ch. 13).

    Passes, as the XNA article's five shaders:

    1. the emitter (`source`): `"disc"`, the XNA article's light-source mask,
       `2 * pow(tex, 2)` of a flare texture centred on the light with
       half-extent `flare_size` (UV units, the article's `SunSize / z`: it
       stretches with the frame's aspect ratio as on the GPU; pixels under
       `units="px"`): `flare_texture`, else by `flare_shape` the procedural
       glow (`masks.procedural_flare()`) or the analytic cone; `"sky"`,
       the frame's own colour; `"light_pass"`, the galaxy-engine VLS article's
       white-light/black-occluder pass;
    2. the scene mask (`scene_mask`, not for `"light_pass"`): `"depth"`, the
       XNA article's depth test (pixels nearer than the light blanked,
       `depth_bias` a fraction of the light's distance), `"sky"` (hard,
       depth `+inf`) or `"coverage"` (antialiased open sky);
    3. `radial_rays` with `density` times, if `step_clamp`, the XNA
       article's `clamp(clip-space z, 0, .5)` of the light's depth
       (`step_clamp`: 0.5 for any light beyond half a unit);
    4. the XNA article's `bright_pass` (`threshold`) if `use_bright_pass`,
       times `tint` (neither article has a tint: 1 is the article);
    5. the blend.

    `light_depth` (a call argument, scene units, `+inf` by default) is what
    the depth test and the step clamp read.

    `num_samples` is fittable through `radial_rays`'s relaxation (loop length
    `max_samples`); at an integer value it is the exact loop.
    `method` picks the rays kernel: `"exact"` (`radial_rays`), `"multipass"`
    (`fast.radial_rays_multipass`, 3 passes x 8 taps) or `"fast"`
    (`fast.fast_radial_rays`: multi-pass at `1 / resolution_factor` resolution).
    With the default flare and the fields known at trace time (the effect
    closed over by `jax.jit`, as `batch` does) the exact loop runs only on
    the window around the light that can hold rays
    (`radial_rays(source_radius=...)`): the same image, faster at high
    resolution.
    """

    FLARE_SQUARED: ClassVar[bool] = True

    density: Float[Array, ""] = param(0.5, low=0.0, high=2.0)
    decay: Float[Array, ""] = param(0.95, low=0.5, high=1.0)
    weight: Float[Array, ""] = param(1.0, low=0.0, high=10.0)
    exposure: Float[Array, ""] = param(0.15, low=0.0, high=5.0)
    flare_size: Float[Array, ""] = size_param(0.1, low=1e-3, high=4.0, px_high=8192.0)
    threshold: Float[Array, ""] = param(0.25, low=0.0, high=0.99)
    tint: Float[Array, "3"] = param((1.0, 1.0, 1.0), low=0.0, high=10.0)
    num_samples: Float[Array, ""] = param(128.0, low=1.0, high=4096.0)
    offscreen_fade: Float[Array, ""] = param(0.5, low=0.01, high=10.0)
    flare_texture: Float[Array, "h w C"] | None = texture_field()
    flare_shape: FlareShape = eqx.field(static=True, default="glow")
    depth_bias: float = eqx.field(static=True, default=0.1)
    max_samples: int = eqx.field(static=True, default=128)
    source: Source = eqx.field(static=True, default="disc")
    scene_mask: SceneMask = eqx.field(static=True, default="coverage")
    step_clamp: bool = eqx.field(static=True, default=False)
    use_bright_pass: bool = eqx.field(static=True, default=False)
    blend_mode: str = eqx.field(static=True, default="add")
    method: RayMethod = eqx.field(static=True, default="exact")
    resolution_factor: int = eqx.field(static=True, default=2)
    units: Units = eqx.field(static=True, default="frame")

    def __check_init__(self):
        if self.method not in RAY_METHODS:
            raise ValueError(f"method must be one of {', '.join(RAY_METHODS)}; got {self.method!r}")

    def layer(self, buffers, light_xy, *, light_in_front=True, light_depth=math.inf):
        """The rays alone, `(H, W, 3)` (or 1 channel for a 1-channel flare texture or `sky` source)."""
        check_light(light_xy)
        # The exact loop takes the emitter as a function of its inputs, so that
        # it differentiates the few numbers it is drawn from (flare_size) in
        # forward mode: their reverse-mode gradient then needs no image adjoint.
        emitter_fn, emitter_args = emitter_inputs(self, buffers, light_xy, light_in_front, light_depth)
        density = self.density * step_clamp(light_depth) if self.step_clamp else self.density
        fields = dict(
            num_samples=self.num_samples,
            density=density,
            decay=self.decay,
            weight=self.weight,
            exposure=self.exposure,
        )
        if self.method == "exact":
            reach = _flare_reach_px(self, buffers.height, buffers.width)
            rays = radial_rays_of(
                emitter_fn, emitter_args, light_xy, max_samples=self.max_samples, source_radius=reach, **fields
            )
        elif self.method == "multipass":
            rays = radial_rays_multipass(emitter_fn(*emitter_args), light_xy, **fields)
        else:
            rays = fast_radial_rays(
                emitter_fn(*emitter_args), light_xy, resolution_factor=self.resolution_factor, **fields
            )
        if self.use_bright_pass:
            rays = bright_pass(rays, threshold=self.threshold)
        return rays * self.tint.astype(rays.dtype)


class FlareOuts(Effect):
    """kbEngine's screen-space god rays.

    1. The masked flare: a flare texture as sampled (`masks.flare_image`:
       `flare_texture`, else the `flare_shape` of `GodRays`) centred on the
       light as in `GodRays` (half-extent `flare_size`, UV units; the article
       does not say where its base texture lies), times the scene mask
       (`scene_mask`; kbEngine's `1 - sign(depth)` is `"sky"`);
    2. the flare-outs: the masked texture scaled about the light `num_iters`
       times by `scale_step` each (`scale_iterated_flares`), added into a
       target at `1 / resolution_factor` of the frame's resolution (the article
       draws them into a low-resolution target; 1 draws at full resolution);
    3. times `intensity`, a Gaussian blur of `blur_sigma` against banding
       (frame units, taps to `blur_reach`), on the low-resolution target;
    4. the target read back bilinearly at full resolution, times `tint`, added.

    `num_iters` is fittable (loop length `max_iters`).
    """

    FLARE_SQUARED: ClassVar[bool] = False

    scale_step: Float[Array, ""] = param(1.03, low=0.8, high=1.5)
    intensity: Float[Array, ""] = param(0.1, low=0.0, high=10.0)
    copy_decay: Float[Array, ""] = param(1.0, low=0.5, high=1.0)
    flare_size: Float[Array, ""] = size_param(0.1, low=1e-3, high=4.0, px_high=8192.0)
    blur_sigma: Float[Array, ""] = size_param(0.00625, low=0.0, high=0.2, px_high=200.0)
    tint: Float[Array, "3"] = param((1.0, 1.0, 1.0), low=0.0, high=10.0)
    num_iters: Float[Array, ""] = param(20.0, low=1.0, high=64.0)
    offscreen_fade: Float[Array, ""] = param(0.5, low=0.01, high=10.0)
    flare_texture: Float[Array, "h w C"] | None = texture_field()
    flare_shape: FlareShape = eqx.field(static=True, default="glow")
    depth_bias: float = eqx.field(static=True, default=0.1)
    max_iters: int = eqx.field(static=True, default=20)
    blur_reach: float = size_reach(0.01875)
    resolution_factor: int = eqx.field(static=True, default=1, metadata={"formerly": ("target_factor",)})
    source: Source = eqx.field(static=True, default="disc")
    scene_mask: SceneMask = eqx.field(static=True, default="coverage")
    blend_mode: str = eqx.field(static=True, default="add")
    units: Units = eqx.field(static=True, default="frame")

    def __check_init__(self):
        if not is_static_int(self.resolution_factor) or self.resolution_factor < 1:
            raise ValueError(f"resolution_factor must be a Python int >= 1, got {self.resolution_factor!r}")

    def layer(self, buffers, light_xy, *, light_in_front=True, light_depth=math.inf):
        """The flare-outs alone, `(H, W, C)` (C: the flare texture's channels, or 3 for the `sky` source)."""
        check_light(light_xy)
        height, width, factor = buffers.height, buffers.width, self.resolution_factor
        emitter_fn, emitter_args = emitter_inputs(self, buffers, light_xy, light_in_front, light_depth)
        target_fn = emitter_fn if factor == 1 else lambda *args: downsample_box(emitter_fn(*args), factor)
        flares = scale_iterated_flares_of(
            target_fn,
            emitter_args,
            jnp.asarray(light_xy, buffers.color.dtype) / factor,
            num_iters=self.num_iters,
            max_iters=self.max_iters,
            scale_step=self.scale_step,
            decay=self.copy_decay,
        )
        sigma = self.blur_sigma * pixels_per_unit(self.units, height, width) / factor
        taps = reach_taps(self.blur_reach, self.units, height, width, level=factor)
        flares = gaussian_blur(flares * self.intensity, sigma=sigma, reach=taps)
        if factor > 1:
            flares = upsample_bilinear(flares, factor, height, width)
        return flares * self.tint.astype(flares.dtype)
