"""Whole effects as parameter sets (`equinox.Module`s) and a preset for each source article.

An effect is called as `effect(buffers, light_xy, *, light_in_front=True)` and
returns the composited frame; `effect.layer(...)` returns the effect alone,
before blending. Every array field is fittable (a JAX scalar or vector);
static fields (`eqx.field(static=True)`) are Python values that select the
algorithm. Sizes are in pixels, except `blur_power`, which is in UV units as
in seed 000. Presets are tuned for frames around 320 to 1920 pixels wide.

Off-screen and behind-camera lights, the same rule for every effect that a
light drives: the layer is multiplied by `light_visibility(light_xy, ...,
fade=offscreen_fade)`, 1 while the light is on screen, fading smoothly to 0
once the light is `offscreen_fade` frame-widths beyond the edge, and 0 when
the light is behind the camera (`light_in_front` false: the frame comes back
unchanged). `Bloom` does not depend on the light and ignores both.
"""

import dataclasses
import functools
import json
import os
import tempfile
from typing import Any, ClassVar, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from godrays_jax.primitives.checks import check_light
from godrays_jax.kernels.blur import bloom, gaussian_blur, poisson_blur
from godrays_jax.primitives.buffers import Buffers
from godrays_jax.kernels.composite import BLEND_MODES, blend
from godrays_jax.kernels.lens import LENS_DIRT_ABERRATION, ViewMode, dirt_texture, lens_dirt, sun_spot
from godrays_jax.kernels.media import apply_fog, in_scattering
from godrays_jax.kernels.masks import bright_pass, coverage_mask, dilate, erode, light_source_mask
from godrays_jax.kernels.fast import fast_radial_rays, radial_rays_multipass
from godrays_jax.kernels.rays import radial_rays, radial_rays_of, scale_iterated_flares_of
from godrays_jax.primitives.sampling import pixel_centres

Source = Literal["disc", "sky", "light_pass"]
SOURCES: tuple[str, ...] = ("disc", "sky", "light_pass")


def _array(value) -> Array:
    return jnp.asarray(value, dtype=jnp.result_type(float))


def param(default, *, low: float, high: float):
    """A fittable field, stored as a floating JAX array whatever number or list is given.

    `[low, high]` is its valid range (every element, for a vector): fitting keeps
    the value inside it and the tuner's sliders span it.
    """
    return eqx.field(converter=_array, default=default, metadata={"bounds": (low, high)})


def parameter_bounds(effect: "Effect | type[Effect]") -> dict[str, tuple[float, float]]:
    """`{field name: (low, high)}` for every fittable field of an effect (instance or class)."""
    cls = effect if isinstance(effect, type) else type(effect)
    return {field.name: field.metadata["bounds"] for field in dataclasses.fields(cls) if "bounds" in field.metadata}


class Effect(eqx.Module):
    """Base class: subclasses define `layer` and a static `blend_mode` field."""

    _registry: ClassVar[dict[str, type["Effect"]]] = {}

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        Effect._registry[cls.__name__] = cls

    def __check_init__(self):
        mode = getattr(self, "blend_mode", "add")
        if mode not in BLEND_MODES:
            raise ValueError(f"blend_mode must be one of {', '.join(BLEND_MODES)}; got {mode!r}")
        source = getattr(self, "source", "disc")
        if source not in SOURCES:
            raise ValueError(f"source must be one of {', '.join(SOURCES)}; got {source!r}")
        for name, (low, high) in parameter_bounds(self).items():
            value = getattr(self, name)
            if isinstance(value, jax.core.Tracer):
                continue  # built inside a traced function: the kernels check what they must at run time
            values = np.asarray(value)
            if not (np.all(np.isfinite(values)) and np.all(values >= low) and np.all(values <= high)):
                raise ValueError(f"{type(self).__name__}.{name} must lie in [{low:g}, {high:g}], got {values.tolist()}")

    def layer(
        self, buffers: Buffers, light_xy: Float[ArrayLike, "2"], *, light_in_front: Bool[ArrayLike, ""] | bool = True
    ) -> Float[Array, "H W L"]:
        raise NotImplementedError

    def __call__(
        self, buffers: Buffers, light_xy: Float[ArrayLike, "2"], *, light_in_front: Bool[ArrayLike, ""] | bool = True
    ) -> Float[Array, "H W C"]:
        """The frame with the effect blended on: `blend(buffers.color, layer, mode=blend_mode)`."""
        return blend(buffers.color, self.layer(buffers, light_xy, light_in_front=light_in_front), mode=self.blend_mode)


def light_visibility(
    light_xy: Float[ArrayLike, "2"],
    height: int,
    width: int,
    *,
    fade: Float[ArrayLike, ""],
    light_in_front: Bool[ArrayLike, ""] | bool = True,
    dtype=jnp.float32,
) -> Float[Array, ""]:
    """How much of a light-driven effect to draw: the off-screen fade and behind-camera rule of every effect.

    1 while the light is on screen (`0 <= x <= W`, `0 <= y <= H`); outside, it
    falls smoothly (`1 - smoothstep(t)`, `t` = the light's distance to the
    screen rectangle divided by `fade * max(W, H)`) to 0 once the light is
    `fade` frame-widths (of the larger side) beyond the edge, so shafts and
    glows neither vanish abruptly nor stretch across the frame from a far-away
    light. 0 when the light is behind the camera (`light_in_front` false).
    Differentiable in `light_xy` and `fade` (gradients finite everywhere).
    """
    check_light(light_xy)
    light_xy = jnp.asarray(light_xy, dtype)
    outside_x = jnp.maximum(jnp.maximum(-light_xy[0], light_xy[0] - width), 0.0)
    outside_y = jnp.maximum(jnp.maximum(-light_xy[1], light_xy[1] - height), 0.0)
    squared = outside_x**2 + outside_y**2
    distance = jnp.where(squared > 0, jnp.sqrt(jnp.where(squared > 0, squared, 1.0)), 0.0)
    reach = jnp.maximum(jnp.asarray(fade, dtype), 1e-6) * max(height, width)
    t = jnp.clip(distance / reach, 0.0, 1.0)
    return (1.0 - t * t * (3.0 - 2.0 * t)) * jnp.asarray(light_in_front, dtype)


def _emitter(
    source: str,
    buffers: Buffers,
    light_xy,
    radius,
    light_in_front,
    fade,
) -> Float[Array, "H W C"]:
    """What shines: a disc at the light seen through the sky, the sky's own colour, or the light pass."""
    dtype = buffers.color.dtype
    visible = light_visibility(
        light_xy, buffers.height, buffers.width, fade=fade, light_in_front=light_in_front, dtype=dtype
    )
    open_sky = coverage_mask(buffers.coverage)[..., None]
    if source == "disc":
        disc = light_source_mask(buffers.height, buffers.width, light_xy, radius=radius, dtype=dtype)
        return disc * open_sky * visible
    if source == "sky":
        colour = buffers.color[..., :3] if buffers.color.shape[-1] >= 3 else buffers.color[..., :1]
        return colour * open_sky * visible
    if buffers.light_pass is None:
        raise ValueError("source='light_pass' needs buffers.light_pass (render it, or use source='disc')")
    return buffers.light_pass[..., None].astype(dtype) * visible


def _emitter_inputs(effect, buffers: Buffers, light_xy, light_in_front):
    """`(function, arguments)` drawing the effect's emitter; the arguments hold only what that source depends on.

    The loops differentiate an emitter's few-number arguments in forward mode,
    one sampled derivative image each, so an unused one (a sky's disc radius)
    would cost a derivative image of zeros.
    """
    radius = effect.light_radius if effect.source == "disc" else None
    arguments = (buffers, light_xy, radius, light_in_front, effect.offscreen_fade)
    return functools.partial(_emitter, effect.source), arguments


RayMethod = Literal["exact", "multipass", "fast"]


def _disc_radius(effect) -> float | None:
    """The disc emitter's radius in pixels when it is known at trace time (the exact loop then runs near the light)."""
    radius = effect.light_radius
    if effect.source != "disc" or isinstance(radius, jax.core.Tracer):
        return None
    return float(radius)


RAY_METHODS: tuple[str, ...] = ("exact", "multipass", "fast")
"""`GodRays.method`: the exact loop, or the fast variants of `godrays_jax.kernels.fast` (errors in benchmarks/README.md)."""


class GodRays(Effect):
    """Radial light shafts, seeds 003 and 004 (GPU Gems 3 ch. 13).

    Passes: the emitter (`source`: `"disc"`, seed 003's light-source mask
    `2 * saturate(1 - d / light_radius)**2` through the sky; `"sky"`, the frame's
    own colour on sky pixels; `"light_pass"`, seed 004's white-light/black-occluder
    pass), then `radial_rays`, then seed 003's `bright_pass` if `use_bright_pass`,
    times `tint`, then the blend.

    `num_samples` is fittable through `radial_rays`'s relaxation (loop length
    `max_samples`); at an integer value it is the exact loop.
    `method` picks the rays kernel: `"exact"` (`radial_rays`), `"multipass"`
    (`fast.radial_rays_multipass`, 3 passes x 8 taps) or `"fast"`
    (`fast.fast_radial_rays`: multi-pass at `1 / resolution_factor` resolution).
    With the disc source and the fields known at trace time (the effect closed
    over by `jax.jit`, as `batch` does) the exact loop runs only on the window
    around the light that can hold rays (`radial_rays(source_radius=...)`):
    the same image, several times faster at high resolution.
    """

    density: Float[Array, ""] = param(0.5, low=0.0, high=2.0)
    decay: Float[Array, ""] = param(0.95, low=0.5, high=1.0)
    weight: Float[Array, ""] = param(1.0, low=0.0, high=10.0)
    exposure: Float[Array, ""] = param(0.15, low=0.0, high=5.0)
    light_radius: Float[Array, ""] = param(40.0, low=0.5, high=500.0)
    threshold: Float[Array, ""] = param(0.25, low=0.0, high=0.99)
    tint: Float[Array, "3"] = param((1.0, 1.0, 1.0), low=0.0, high=10.0)
    num_samples: Float[Array, ""] = param(128.0, low=1.0, high=4096.0)
    offscreen_fade: Float[Array, ""] = param(0.5, low=0.01, high=10.0)
    max_samples: int = eqx.field(static=True, default=128)
    source: Source = eqx.field(static=True, default="disc")
    use_bright_pass: bool = eqx.field(static=True, default=False)
    blend_mode: str = eqx.field(static=True, default="add")
    method: RayMethod = eqx.field(static=True, default="exact")
    resolution_factor: int = eqx.field(static=True, default=2)

    def __check_init__(self):
        if self.method not in RAY_METHODS:
            raise ValueError(f"method must be one of {', '.join(RAY_METHODS)}; got {self.method!r}")

    def layer(self, buffers, light_xy, *, light_in_front=True):
        """The rays alone, `(H, W, 3)` (or 1 channel for a 1-channel `sky` source)."""
        check_light(light_xy)
        # The exact loop takes the emitter as a function of its inputs, so that
        # it differentiates the few numbers it is drawn from (light_radius) in
        # forward mode: their reverse-mode gradient then needs no image adjoint.
        emitter_fn, emitter_args = _emitter_inputs(self, buffers, light_xy, light_in_front)
        fields = dict(
            num_samples=self.num_samples,
            density=self.density,
            decay=self.decay,
            weight=self.weight,
            exposure=self.exposure,
        )
        if self.method == "exact":
            rays = radial_rays_of(
                emitter_fn, emitter_args, light_xy, max_samples=self.max_samples, source_radius=_disc_radius(self),
                **fields,
            )  # fmt: skip
        elif self.method == "multipass":
            rays = radial_rays_multipass(emitter_fn(*emitter_args), light_xy, **fields)
        else:
            rays = fast_radial_rays(emitter_fn(*emitter_args), light_xy, factor=self.resolution_factor, **fields)
        if self.use_bright_pass:
            rays = bright_pass(rays, self.threshold)
        return rays * self.tint.astype(rays.dtype)


class FlareOuts(Effect):
    """kbEngine's screen-space god rays, seed 002.

    The emitter (as in `GodRays`: a disc through the sky by default, kbEngine's
    "base flare texture x (1 - sign(depth))"), scaled about the light
    `num_iters` times by `scale_step` each (`scale_iterated_flares`), times
    `intensity * tint`, a Gaussian blur of `blur_sigma` pixels against banding,
    then added. `num_iters` is fittable (loop length `max_iters`).
    """

    scale_step: Float[Array, ""] = param(1.03, low=0.8, high=1.5)
    intensity: Float[Array, ""] = param(0.1, low=0.0, high=10.0)
    copy_decay: Float[Array, ""] = param(1.0, low=0.5, high=1.0)
    light_radius: Float[Array, ""] = param(40.0, low=0.5, high=500.0)
    blur_sigma: Float[Array, ""] = param(2.0, low=0.0, high=50.0)
    tint: Float[Array, "3"] = param((1.0, 1.0, 1.0), low=0.0, high=10.0)
    num_iters: Float[Array, ""] = param(20.0, low=1.0, high=64.0)
    offscreen_fade: Float[Array, ""] = param(0.5, low=0.01, high=10.0)
    max_iters: int = eqx.field(static=True, default=20)
    blur_radius: int = eqx.field(static=True, default=6)
    source: Source = eqx.field(static=True, default="disc")
    blend_mode: str = eqx.field(static=True, default="add")

    def layer(self, buffers, light_xy, *, light_in_front=True):
        """The flare-outs alone, `(H, W, 3)`."""
        check_light(light_xy)
        emitter_fn, emitter_args = _emitter_inputs(self, buffers, light_xy, light_in_front)
        flares = scale_iterated_flares_of(
            emitter_fn,
            emitter_args,
            light_xy,
            num_iters=self.num_iters,
            max_iters=self.max_iters,
            scale_step=self.scale_step,
            decay=self.copy_decay,
        )
        flares = gaussian_blur(flares * self.intensity, self.blur_sigma, radius=self.blur_radius)
        return flares * self.tint.astype(flares.dtype)


class SunOvercast(Effect):
    """Seed 000's sun overcasting: a glow pass blurred twice with the Poisson blur, then added.

    The glow pass is `buffers.glow_pass` when the rasterizer rendered it (the
    source enlarged x1.3 in `glow_color`, occluders shrunk x0.8 in transparent
    black). For other buffers it is drawn in image space, seed 000's two
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
            source = dilate(buffers.light_pass.astype(dtype), self.source_grow, max_radius=self.max_morphology)
        else:
            x, y = pixel_centres(buffers.height, buffers.width, dtype)
            light_xy = jnp.asarray(light_xy, dtype)
            distance = jnp.sqrt((x - light_xy[0]) ** 2 + (y - light_xy[1]) ** 2 + 1e-12)
            source = jnp.clip(self.source_radius + self.source_grow - distance + 0.5, 0.0, 1.0)
        occluders = erode(jnp.clip(buffers.coverage, 0.0, 1.0), self.occluder_shrink, max_radius=self.max_morphology)
        inside = (source * (1.0 - occluders) * visible)[..., None]
        return inside * self.glow_color.astype(dtype)

    def layer(self, buffers, light_xy, *, light_in_front=True):
        """The blurred glow as added: `(H, W, 3)` = blurred rgb times blurred alpha."""
        glow = poisson_blur(
            self.glow(buffers, light_xy, light_in_front=light_in_front),
            self.blur_power,
            passes=self.passes,
            max_passes=self.max_passes,
        )
        return glow[..., :3] * glow[..., 3:]


class LensDirt(Effect):
    """Seed 001's lens dirt: a dirt texture lit by the sun, `lens.lens_dirt`, added.

    The texture is `lens.dirt_texture(H, W, seed=dirt_seed)`, generated at the
    frame's size on first use and cached (pass your own texture to
    `lens.lens_dirt`). Directions come from `fov_x_deg` (horizontal field of
    view, degrees); `far` (scene units) normalises depth to seed 001's
    `LDepth`; `power` and `scale` are seed 001's 20 and 2; `aberration` is the
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
            power=self.power, scale=self.scale, aberration=self.aberration, in_front=light_in_front, view=self.view,
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
    """Seed 001's sky sun spot, `lens.sun_spot` on the sky in `sun_color`, plus its glow.

    As in seed 001 the spot is also written to a glow target (`glow`), which
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
        """The glow target: the coloured spot on sky pixels (seed 001's `Out.glow`), unblurred."""
        check_light(light_xy)
        dtype = buffers.color.dtype
        spot = sun_spot(
            buffers.height, buffers.width, light_xy, fov_x_deg=self.fov_x_deg, sun_distance=self.sun_distance,
            sun_sharpness=self.sun_sharpness, in_front=light_in_front, dtype=dtype,
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
    """Seed 001's bright glow (`blur.bloom`): bright pass, blurs at 1/2 .. 1/16 resolution, summed, added.

    `method="gaussian"` is the single large Gaussian seed 001 compares it with:
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
            glow = gaussian_blur(bright, self.gaussian_sigma, radius=self.gaussian_radius)
        return glow * self.intensity.astype(colour.dtype)


class ScatteringFog(Effect):
    """A homogeneous participating medium: extinction of the frame plus in-scattered sky and sun light.

    The frame becomes `color * T + (1 - T) * (ambient + sun_irradiance * p(theta) * lit)`
    (`media.apply_fog`, single scattering in closed form): `T = exp(-extinction *
    min(depth, max_distance))` with `depth` the distance along the camera ray in
    scene units (sky: `max_distance`), `extinction` per scene unit, `p` the
    Henyey-Greenstein phase function (per steradian) of `anisotropy` at the
    angle between each pixel's view ray and the sun (from `fov_x_deg`, the
    horizontal field of view in degrees), `ambient` and `sun_irradiance` RGB
    (albedo times sky radiance and times sun irradiance).

    `lit` is the screen-space estimate of how much of each ray the sun
    reaches, so occluders cast shafts of shadow into the medium:
    `lit = 1 - shaft_strength * v * (1 - rays)`, `rays` the GPU Gems radial
    blur (`radial_rays`, `num_samples` up to `max_samples`, `density`,
    `decay`) of the open-sky mask toward the sun, normalised so open sky gives
    1, and `v` the off-screen fade (`light_visibility`): far off-screen or
    behind-camera suns cast no screen-space shafts, while the extinction, the
    ambient light and the (backward, behind the camera) sun lobe stay.

    Unlike the additive effects the medium also removes light: `effect(...)` is
    the fogged frame, `effect.layer(...)` the in-scattered light alone (the
    frame is `color * media.transmittance(...) + layer`).
    """

    extinction: Float[Array, ""] = param(0.01, low=0.0, high=1.0)
    max_distance: Float[Array, ""] = param(100.0, low=0.0, high=1e4)
    anisotropy: Float[Array, ""] = param(0.76, low=-0.95, high=0.95)
    ambient: Float[Array, "3"] = param((0.05, 0.06, 0.08), low=0.0, high=10.0)
    sun_irradiance: Float[Array, "3"] = param((1.0, 0.9, 0.75), low=0.0, high=100.0)
    fov_x_deg: Float[Array, ""] = param(50.0, low=1.0, high=170.0)
    shaft_strength: Float[Array, ""] = param(1.0, low=0.0, high=1.0)
    density: Float[Array, ""] = param(1.0, low=0.0, high=2.0)
    decay: Float[Array, ""] = param(0.97, low=0.5, high=1.0)
    num_samples: Float[Array, ""] = param(32.0, low=1.0, high=512.0)
    offscreen_fade: Float[Array, ""] = param(0.5, low=0.01, high=10.0)
    max_samples: int = eqx.field(static=True, default=32)

    def lit(self, buffers: Buffers, light_xy, *, light_in_front=True) -> Float[Array, "H W"]:
        """The fraction of each camera ray the sun reaches, in [0, 1] (1 without occluders)."""
        check_light(light_xy)
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
        return 1.0 - self.shaft_strength.astype(dtype) * visible * (1.0 - normalised)

    def _fog_options(self, buffers, light_xy, light_in_front):
        return dict(
            fov_x_deg=self.fov_x_deg, extinction=self.extinction, max_distance=self.max_distance, ambient=self.ambient,
            sun_irradiance=self.sun_irradiance, anisotropy=self.anisotropy, light_in_front=light_in_front,
            lit=self.lit(buffers, light_xy, light_in_front=light_in_front),
        )  # fmt: skip

    def layer(self, buffers, light_xy, *, light_in_front=True):
        """The in-scattered light alone, `(H, W, 3)`."""
        options = self._fog_options(buffers, light_xy, light_in_front)
        return in_scattering(buffers.depth, light_xy, **options).astype(buffers.color.dtype)

    def __call__(self, buffers, light_xy, *, light_in_front=True):
        """The fogged frame: `color * T + layer` on the colour channels, alpha unchanged."""
        options = self._fog_options(buffers, light_xy, light_in_front)
        return apply_fog(buffers.color, buffers.depth, light_xy, **options)


def _xna_crepuscular() -> GodRays:
    """Seed 003: 128 samples, density .5, decay .95, weight 1, exposure .15, bright pass, additive."""
    # Seed 003 leaves the flare size (SunSize / z), the bright-pass threshold and
    # the colour open: with decay .95 the shafts reach only ~8 % of the way to the
    # light, so the disc must reach the occluders (120 px on a 320 px frame), and
    # a warm tint below 1 keeps the saturated core from washing the silhouettes out.
    return GodRays(
        density=0.5, decay=0.95, weight=1.0, exposure=0.15, threshold=0.25, num_samples=128.0,
        max_samples=128, light_radius=120.0, tint=(0.8, 0.7, 0.5), source="disc", use_bright_pass=True,
        blend_mode="add",
    )  # fmt: skip


def _galaxy_vls() -> GodRays:
    """Seed 004: light white and occluders black, 200 samples, density 1, decay .98, exposure .05, additive."""
    return GodRays(
        density=1.0, decay=0.98, weight=1.0, exposure=0.05, num_samples=200.0, max_samples=200,
        source="light_pass", use_bright_pass=False, blend_mode="add",
    )  # fmt: skip


def _kbengine_flares() -> FlareOuts:
    """Seed 002: kbEngine3's 20 flare-outs scaled x1.03 each, blurred against banding, added."""
    return FlareOuts(scale_step=1.03, num_iters=20.0, max_iters=20, intensity=0.1, blur_sigma=2.0)


def _sun_overcast() -> SunOvercast:
    """Seed 000: orange (0.8, 0.5, 0, 0.65) glow, two Poisson-blur passes, additive."""
    # The halo size and the occluders' shrink (x1.3 / x0.8 of objects in the seed) are
    # open in image space: a 45 px halo and 2 px of seeping read as the seed's picture.
    return SunOvercast(
        blur_power=0.015, glow_color=(0.8, 0.5, 0.0, 0.65), passes=2.0, max_passes=2, source_radius=45.0,
        occluder_shrink=2.0,
    )  # fmt: skip


def _vbex_lens_dirt() -> LensDirt:
    """Seed 001: power 20, scale 2, chromatic offset 0.002, warm sun colour, added."""
    return LensDirt(power=20.0, scale=2.0, aberration=LENS_DIRT_ABERRATION, sun_color=(1.0, 0.8, 0.55))


def _vbex_sun_spot() -> SunSpot:
    """Seed 001: `pow(dot, SunDistance * 2000) * SunSharpness * 30` on the sky, bloomed through the glow target."""
    return SunSpot(sun_distance=1.0, sun_sharpness=1.0, sun_color=(1.0, 0.85, 0.6), glow_intensity=0.5)


def _vbex_bloom() -> Bloom:
    """Seed 001: bright pass, blurs at 1/2, 1/4, 1/8, 1/16 resolution added with equal weights."""
    return Bloom(threshold=1.0, weights=(1.0, 1.0, 1.0, 1.0), intensity=0.25, method="pyramid")


def _gaussian_bloom() -> Bloom:
    """The single large Gaussian that seed 001's pyramid replaces, for comparison."""
    return Bloom(threshold=1.0, gaussian_sigma=12.0, gaussian_radius=36, intensity=1.0, method="gaussian")


def _participating_media() -> ScatteringFog:
    """A light haze: no seed; physically motivated defaults, not tuned to any reference frame."""
    # Mie haze has g ~ 0.76; extinction 0.01 per unit leaves 37 % of the light after
    # 100 units; a bluish ambient (sky light) and a warm sun; the medium ends at 100 units.
    return ScatteringFog(
        extinction=0.01, max_distance=100.0, anisotropy=0.76, ambient=(0.05, 0.06, 0.08),
        sun_irradiance=(1.0, 0.9, 0.75), fov_x_deg=50.0, shaft_strength=1.0, density=1.0, decay=0.97,
        num_samples=32.0, max_samples=32,
    )  # fmt: skip


PRESETS: dict[str, Any] = {
    "xna_crepuscular": _xna_crepuscular,
    "galaxy_vls": _galaxy_vls,
    "kbengine_flares": _kbengine_flares,
    "sun_overcast": _sun_overcast,
    "vbex_lens_dirt": _vbex_lens_dirt,
    "vbex_sun_spot": _vbex_sun_spot,
    "vbex_bloom": _vbex_bloom,
    "gaussian_bloom": _gaussian_bloom,
    "participating_media": _participating_media,
}
"""Preset name -> a function making that effect with the source article's constants."""


def preset(name: str) -> Effect:
    """A fresh effect with the constants of the named source article (see `PRESETS`)."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of: {', '.join(sorted(PRESETS))}")
    return PRESETS[name]()


def _field_names(cls) -> list[str]:
    return [field.name for field in dataclasses.fields(cls)]


def effect_to_dict(effect: Effect) -> dict:
    """A JSON-ready description: `{"effect": class name, field: value, ...}`."""
    fields = {"effect": type(effect).__name__}
    for name in _field_names(type(effect)):
        value = getattr(effect, name)
        fields[name] = np.asarray(value).tolist() if isinstance(value, (jnp.ndarray, np.ndarray)) else value
    return fields


def effect_from_dict(fields: dict) -> Effect:
    """Rebuild an effect from `effect_to_dict`'s output; unknown keys or effects raise `ValueError`."""
    fields = dict(fields)
    kind = fields.pop("effect", None)
    if kind not in Effect._registry:
        raise ValueError(f"unknown effect {kind!r}; known effects: {', '.join(sorted(Effect._registry))}")
    cls = Effect._registry[kind]
    unknown = sorted(set(fields) - set(_field_names(cls)))
    if unknown:
        raise ValueError(f"unknown parameter(s) for {kind}: {', '.join(unknown)}")
    return cls(**fields)


def save_effect(path: str | os.PathLike, effect: Effect) -> None:
    """Write the effect's parameters as JSON, atomically (a temporary file renamed into place)."""
    path = os.fspath(path)
    text = json.dumps(effect_to_dict(effect), indent=2) + "\n"
    handle, temporary = tempfile.mkstemp(dir=os.path.dirname(os.path.abspath(path)), suffix=".tmp")
    try:
        with os.fdopen(handle, "w") as stream:
            stream.write(text)
        os.replace(temporary, path)
    except BaseException:
        os.unlink(temporary)
        raise


def load_effect(path: str | os.PathLike) -> Effect:
    """Read parameters written by `save_effect` (or by `godrays-jax fit`)."""
    with open(path) as stream:
        try:
            fields = json.load(stream)
        except json.JSONDecodeError as error:
            raise ValueError(f"{os.fspath(path)} is not valid JSON: {error}") from None
    if not isinstance(fields, dict):
        raise ValueError(f"{os.fspath(path)} must hold a JSON object")
    return effect_from_dict(fields)
