"""Light-shaft effects: radial rays (`GodRays`, GPU Gems 3 ch. 13) and kbEngine's flare-outs (`FlareOuts`)."""

import dataclasses
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
    flare_size_px,
    pixels_per_unit,
    planar_light_depth,
    reach_taps,
)
from godrays_jax.effects.fields import count_param, param, size_param, size_reach, static, texture_field
from godrays_jax.kernels.blur import bloom_level_shape, draw_at_uv, gaussian_blur
from godrays_jax.kernels.composite import BlendMode
from godrays_jax.kernels.fast import fast_radial_rays, radial_rays_multipass
from godrays_jax.kernels.masks import bright_pass, clip_space_depth
from godrays_jax.kernels.rays import flare_outs_into, radial_rays_of, scale_iterated_flares_of
from godrays_jax.primitives.checks import check_light

RayMethod = Literal["exact", "multipass", "fast"]


RAY_METHODS: tuple[str, ...] = ("exact", "multipass", "fast")
"""`GodRays.method`: the exact loop, or the fast variants of `godrays_jax.kernels.fast` (errors in benchmarks/README.md)."""

MULTIPASS_PASSES, MULTIPASS_TAPS = 2, 16
"""`method="multipass"`'s comb: 2 passes x 16 taps (256 samples). Each pass resamples the previous one
bilinearly, with a blur that follows the light's sub-pixel position; two passes instead of the engines'
three hold the shafts stiller in a moving camera (benchmarks/bench_shimmer.py)."""

STEP_CLAMP_LIMIT = 0.5
"""The XNA crepuscular-rays article's `clamp(ScreenPosition.w * ScreenPosition.z, 0, .5)` upper limit."""

FlareSizing = Literal["clip_depth", "fixed"]
FLARE_SIZINGS: tuple[str, ...] = ("clip_depth", "fixed")
"""`GodRays.flare_sizing`: the XNA article's half-extent `sun_size / z` (UV, `z` the light's clip-space z), or a
fixed `flare_size` whatever the light's distance (ours)."""

XNA_NEAR_PLANE = 0.5
"""The near clip plane `GodRays` assumes unless given the frame's: the XNA article author's sample camera's
(`Base3DCamera(game, .5f, 20000)`); the article itself prints none. `render` writes a frame's own
(`godrays:clip_planes`)."""

XNA_FAR_PLANE = 5000.0
"""The far clip plane `GodRays` assumes unless given the frame's (ours): a light at infinity is drawn on it, so the
article's SunSize 1500 gives it a flare of .3 UV, the article's sun as if 5000 units away."""


def step_clamp(light_clip_depth) -> Float[Array, ""] | float:
    """The XNA article's step factor `clamp(ScreenPosition.w * ScreenPosition.z, 0, .5)`.

    `w * z` after the perspective divide is the light's clip-space z
    (`masks.clip_space_depth`, scene units): 0 for a light on the near plane,
    0.5 once it is half a unit (times `far / (far - near)`) beyond it. A
    concrete value gives a Python float (so the rays' window around the light
    stays known at trace time).
    """
    if isinstance(light_clip_depth, jax.core.Tracer):
        return jnp.clip(light_clip_depth, 0.0, STEP_CLAMP_LIMIT)
    return float(np.clip(float(np.asarray(light_clip_depth)), 0.0, STEP_CLAMP_LIMIT))


def _flare_reach_px(effect, height: int, width: int, light_xy, light_depth) -> float | None:
    """How far from the light the default flare can be non-zero, in pixels, when known at trace time.

    The procedural flare and the cone are black outside their inscribed ellipse; a user's
    texture may not be (clamp addressing repeats its border), so no promise.
    """
    if effect.source != "disc" or effect.flare_texture is not None:
        return None
    inputs = (effect.flare_size, effect.sun_size, effect.fov_x_deg, light_xy, light_depth)
    if any(isinstance(value, jax.core.Tracer) for value in jax.tree_util.tree_leaves(inputs)):
        return None
    with jax.ensure_compile_time_eval():
        radius = effect.flare_size_in_px(height, width, jnp.asarray(light_xy), light_depth, jnp.float32)
        return float(jnp.max(radius))


def _check_clip_planes(owner: str, near_plane, far_plane) -> None:
    if not all(isinstance(value, (int, float)) and not isinstance(value, bool) for value in (near_plane, far_plane)):
        raise ValueError(f"{owner}.near_plane and far_plane must be numbers, got {near_plane!r}, {far_plane!r}")
    if not 0 < near_plane < far_plane < math.inf:
        raise ValueError(f"{owner}.near_plane and far_plane must satisfy 0 < near_plane < far_plane, got {near_plane}, {far_plane}")


class Emitter(eqx.Module):
    """The emitter fields `GodRays` and `FlareOuts` share, declared once: what shines before the rays or the copies
    spread it, with the camera the XNA depth test reads and the off-screen fade.

    `source`: `"disc"` (a flare of half-extent `flare_size` at the light:
    `flare_texture`, else by `flare_shape` the procedural glow or the cone),
    `"sky"` (the frame's own colour) or `"light_pass"`; `scene_mask` lets it
    through (`SCENE_MASKS`, not for `"light_pass"`; `"depth"` the XNA
    article's hardware-depth test with `depth_bias`, `near_plane`,
    `far_plane` and `fov_x_deg`). The fields are the effect's own, under their
    own names; `emitter_inputs` draws the emitter.
    """

    flare_size: Float[Array, ""] = size_param(0.1, low=1e-3, high=4.0, px_high=8192.0)
    offscreen_fade: Float[Array, ""] = param(0.5, low=0.01, high=10.0)
    flare_texture: Float[Array, "h w C"] | None = texture_field()
    fov_x_deg: Float[Array, ""] = param(50.0, low=1.0, high=170.0)
    flare_shape: FlareShape = static("glow")
    depth_bias: float = static(0.00025)
    near_plane: float = static(XNA_NEAR_PLANE)
    far_plane: float = static(XNA_FAR_PLANE)
    source: Source = static("disc")
    scene_mask: SceneMask = static("coverage")

    def __check_init__(self):
        owner = type(self).__name__
        _check_clip_planes(owner, self.near_plane, self.far_plane)
        bias = self.depth_bias
        if not (isinstance(bias, (int, float)) and not isinstance(bias, bool) and 0.0 <= bias < 1.0):
            raise ValueError(f"{owner}.depth_bias must be a number in [0, 1), got {bias!r}")

    @property
    def reads_light_pass(self) -> bool:
        """Whether the emitter is the frame's rendered light pass (`source="light_pass"`)."""
        return self.source == "light_pass"

    def for_buffers(self, buffers):
        """On a frame without a light pass, the emitter that reads one becomes the disc at the light, the nearest
        stand-in (a renderer's frame seldom has one; `godrays-jax render` writes it)."""
        if not self.reads_light_pass or buffers.light_pass is not None:
            return self, None
        why = "has no light pass (light.Y): using the disc emitter at the light instead (source='disc')"
        return dataclasses.replace(self, source="disc"), why

    def with_flare_texture(self, texture):
        """This effect drawing `texture` as its flare (checked as the `flare_texture` field checks it)."""
        return dataclasses.replace(self, flare_texture=texture)


class GodRays(Effect, Emitter):
    """Radial light shafts, the XNA crepuscular-rays and galaxy-engine VLS articles (GPU Gems 3 ch. 13).

    Passes, as the XNA article's five shaders:

    1. the emitter (`source`): `"disc"`, the XNA article's light-source mask,
       `2 * pow(tex, 2)` of a flare texture centred on the light with
       half-extent (UV units, stretched with the frame's aspect ratio as on
       the GPU) by `flare_sizing`: `"clip_depth"` (the XNA preset's), the
       article's `SunSize / z` (`sun_size` over the light's clip-space z,
       `masks.clip_space_depth` of `near_plane` and `far_plane`: small for a
       far light, large for a near one, a light at infinity on the far
       plane), or `"fixed"` (ours, the class default so that a given
       `flare_size` is what is drawn), `flare_size` whatever the light's
       distance (pixels under `units="px"`); the texture is `flare_texture`,
       else by `flare_shape` the procedural glow (`masks.procedural_flare()`)
       or the analytic cone; `"sky"`, the frame's own colour;
       `"light_pass"`, the galaxy-engine VLS article's white-light/black-occluder pass;
    2. the scene mask (`scene_mask`, not for `"light_pass"`): `"depth"`, the
       XNA article's hardware-depth compare (pixels whose z/w is below the
       light's less `depth_bias`, the article's .00025, blanked; `base.scene_mask_of`),
       `"sky"` (hard, depth `+inf`) or `"coverage"` (antialiased open sky);
    3. `radial_rays` with `density` times, if `step_clamp`, the XNA
       article's `clamp(z, 0, .5)` of the light's clip-space z;
    4. the XNA article's `bright_pass` (`threshold`) if `use_bright_pass`,
       times `tint` (neither article has a tint: 1 is the article);
    5. the blend.

    `light_depth` (a call argument, scene units along the light's ray, `+inf`
    by default) is what the flare's size, the depth test and the step clamp
    read. Clip-space z and hardware depth are planar: `fov_x_deg` (the
    frame's horizontal field of view) converts ray distances; `near_plane`
    and `far_plane` are the frame's camera's (default `XNA_NEAR_PLANE`,
    `XNA_FAR_PLANE`; `render` writes its camera's with the frame).

    `num_samples` is fittable through `radial_rays`'s relaxation (loop length
    `max_samples`); at an integer value it is the exact loop.
    `method` picks the rays kernel: `"exact"` (`radial_rays`), `"multipass"`
    (`fast.radial_rays_multipass`, `MULTIPASS_PASSES` x `MULTIPASS_TAPS`) or `"fast"`
    (`fast.fast_radial_rays`: multi-pass at `1 / resolution_factor` resolution).
    With the default flare and the fields known at trace time (the effect
    closed over by `jax.jit`, as `batch` does) the exact loop runs only on
    the window around the light that can hold rays
    (`radial_rays(source_radius=...)`): the same image, faster at high
    resolution.
    """

    CAMERA_FIELDS: ClassVar[tuple[str, ...]] = ("fov_x_deg", "near_plane", "far_plane")
    FLARE_SQUARED: ClassVar[bool] = True
    # The emitter's own, over `Effect`'s defaults (`Effect` comes first among the bases).
    reads_light_pass = Emitter.reads_light_pass
    for_buffers = Emitter.for_buffers
    with_flare_texture = Emitter.with_flare_texture

    density: Float[Array, ""] = param(0.5, low=0.0, high=2.0)
    decay: Float[Array, ""] = param(0.95, low=0.5, high=1.0)
    weight: Float[Array, ""] = param(1.0, low=0.0, high=10.0)
    exposure: Float[Array, ""] = param(0.15, low=0.0, high=5.0)
    sun_size: Float[Array, ""] = param(1500.0, low=1e-3, high=1e7)
    threshold: Float[Array, ""] = param(0.25, low=0.0, high=0.99)
    tint: Float[Array, "3"] = param((1.0, 1.0, 1.0), low=0.0, high=10.0)
    num_samples: Float[Array, ""] = count_param(128.0, low=1.0, high=4096.0, cap="max_samples")
    flare_sizing: FlareSizing = static("fixed")
    max_samples: int = static(128, low=1, high=4096)
    step_clamp: bool = static(False)
    use_bright_pass: bool = static(False)
    blend_mode: BlendMode = static("add")
    method: RayMethod = static("exact")
    resolution_factor: int = static(2, low=1, high=64)
    units: Units = static("frame")

    def light_clip_depth(self, height: int, width: int, light_xy, light_depth, dtype) -> Float[Array, ""]:
        """The light's clip-space z (scene units; `masks.clip_space_depth`) from its distance along its ray."""
        planar = planar_light_depth(light_depth, light_xy, height, width, self.fov_x_deg, dtype)
        return clip_space_depth(planar, near_plane=self.near_plane, far_plane=self.far_plane)

    def flare_size_in_px(self, height: int, width: int, light_xy, light_depth, dtype) -> Float[Array, "2"]:
        """The flare's half-extent `(rx, ry)` in pixels, by `flare_sizing` (the class docstring)."""
        if self.flare_sizing == "fixed":
            return flare_size_px(self.flare_size, self.units, height, width, dtype)
        # The article's size = SunSize / scale; a light on or before the near plane gets the largest flare.
        clip_z = jnp.maximum(self.light_clip_depth(height, width, light_xy, light_depth, dtype), 1e-6)
        return flare_size_px(jnp.asarray(self.sun_size, dtype) / clip_z, "frame", height, width, dtype)

    def layer(self, buffers, light_xy, *, light_in_front=True, light_depth=math.inf):
        """The rays alone, `(H, W, 3)` (or 1 channel for a 1-channel flare texture or `sky` source)."""
        light_xy = check_light(light_xy)
        # The exact loop takes the emitter as a function of its inputs, so that
        # it differentiates the few numbers it is drawn from (flare_size) in
        # forward mode: their reverse-mode gradient then needs no image adjoint.
        emitter_fn, emitter_args = emitter_inputs(self, buffers, light_xy, light_in_front, light_depth)
        density = self.density
        if self.step_clamp:
            with jax.ensure_compile_time_eval():  # a known light gives a known step: the rays' window stays known
                clip_z = self.light_clip_depth(buffers.height, buffers.width, light_xy, light_depth, buffers.color.dtype)
            density = density * step_clamp(clip_z)
        fields = dict(
            num_samples=self.num_samples,
            density=density,
            decay=self.decay,
            weight=self.weight,
            exposure=self.exposure,
        )
        if self.method == "exact":
            reach = _flare_reach_px(self, buffers.height, buffers.width, light_xy, light_depth)
            rays = radial_rays_of(
                emitter_fn, emitter_args, light_xy, max_samples=self.max_samples, source_radius=reach, **fields
            )
        elif self.method == "multipass":
            rays = radial_rays_multipass(
                emitter_fn(*emitter_args), light_xy, num_passes=MULTIPASS_PASSES, num_taps=MULTIPASS_TAPS, **fields
            )
        else:
            rays = fast_radial_rays(
                emitter_fn(*emitter_args), light_xy, resolution_factor=self.resolution_factor, **fields
            )
        if self.use_bright_pass:
            rays = bright_pass(rays, threshold=self.threshold)
        return rays * self.tint.astype(rays.dtype)


class FlareOuts(Effect, Emitter):
    """kbEngine's screen-space god rays.

    1. The masked flare: a flare texture as sampled (`masks.flare_image`:
       `flare_texture`, else the `flare_shape` of `GodRays`) centred on the
       light as in `GodRays` (half-extent `flare_size`, UV units; the article
       does not say where its base texture lies), times the scene mask
       (`scene_mask`; kbEngine's `1 - sign(depth)` is `"sky"`; `"depth"` is
       the XNA article's test, with `near_plane`, `far_plane`, `depth_bias`
       and `fov_x_deg` as in `GodRays`);
    2. the flare-outs: the full-resolution masked texture scaled about the
       light `num_iters` times by `scale_step` each, drawn into a target of
       `Fullsize / resolution_factor` whole pixels (`rays.flare_outs_into`:
       the article draws them into a low-resolution target; 1 draws at full
       resolution, `scale_iterated_flares`);
    3. times `intensity`, a Gaussian blur of `blur_sigma` against banding
       (frame units, taps to `blur_reach`), on the low-resolution target;
    4. the target drawn back over the frame by UV, bilinearly, times `tint`, added.

    `num_iters` is fittable (loop length `max_iters`).
    """

    CAMERA_FIELDS: ClassVar[tuple[str, ...]] = ("fov_x_deg", "near_plane", "far_plane")
    FLARE_SQUARED: ClassVar[bool] = False
    # The emitter's own, over `Effect`'s defaults (`Effect` comes first among the bases).
    reads_light_pass = Emitter.reads_light_pass
    for_buffers = Emitter.for_buffers
    with_flare_texture = Emitter.with_flare_texture

    scale_step: Float[Array, ""] = param(1.03, low=0.8, high=1.5)
    intensity: Float[Array, ""] = param(0.1, low=0.0, high=10.0)
    copy_decay: Float[Array, ""] = param(1.0, low=0.5, high=1.0)
    blur_sigma: Float[Array, ""] = size_param(0.00625, low=0.0, high=0.2, px_high=200.0)
    tint: Float[Array, "3"] = param((1.0, 1.0, 1.0), low=0.0, high=10.0)
    num_iters: Float[Array, ""] = count_param(20.0, low=1.0, high=64.0, cap="max_iters")
    max_iters: int = static(20, low=1, high=64)
    blur_reach: float = size_reach(0.01875)
    resolution_factor: int = static(1, low=1, high=64, formerly=("target_factor",))
    blend_mode: BlendMode = static("add")
    units: Units = static("frame")

    def flare_size_in_px(self, height: int, width: int, light_xy, light_depth, dtype) -> Float[Array, "2"]:
        """The flare's half-extent `(rx, ry)` in pixels: `flare_size` (the article does not size its base texture)."""
        return flare_size_px(self.flare_size, self.units, height, width, dtype)

    def layer(self, buffers, light_xy, *, light_in_front=True, light_depth=math.inf):
        """The flare-outs alone, `(H, W, C)` (C: the flare texture's channels, or 3 for the `sky` source)."""
        light_xy = check_light(light_xy)
        height, width, factor = buffers.height, buffers.width, self.resolution_factor
        emitter_fn, emitter_args = emitter_inputs(self, buffers, light_xy, light_in_front, light_depth)
        copies = dict(num_iters=self.num_iters, max_iters=self.max_iters, scale_step=self.scale_step, decay=self.copy_decay)
        if factor == 1:
            flares = scale_iterated_flares_of(emitter_fn, emitter_args, jnp.asarray(light_xy, buffers.color.dtype), **copies)
        else:
            target = bloom_level_shape(height, width, factor)
            flares = flare_outs_into(emitter_fn(*emitter_args), light_xy, target_shape=target, **copies)
        sigma = self.blur_sigma * pixels_per_unit(self.units, height, width) / factor
        taps = reach_taps(self.blur_reach, self.units, height, width, level=factor)
        flares = gaussian_blur(flares * self.intensity, sigma=sigma, reach=taps)
        if factor > 1:
            flares = draw_at_uv(flares, height, width)
        return flares * self.tint.astype(flares.dtype)
