"""Light-shaft effects: radial rays (`GodRays`, GPU Gems 3 ch. 13) and kbEngine's flare-outs (`FlareOuts`)."""

from typing import Literal

import equinox as eqx
import jax
from jaxtyping import Array, Float

from godrays_jax.effects.base import Effect, Source, emitter_inputs, param
from godrays_jax.kernels.blur import gaussian_blur
from godrays_jax.kernels.fast import fast_radial_rays, radial_rays_multipass
from godrays_jax.kernels.masks import bright_pass
from godrays_jax.kernels.rays import radial_rays_of, scale_iterated_flares_of
from godrays_jax.primitives.checks import check_light

RayMethod = Literal["exact", "multipass", "fast"]


RAY_METHODS: tuple[str, ...] = ("exact", "multipass", "fast")
"""`GodRays.method`: the exact loop, or the fast variants of `godrays_jax.kernels.fast` (errors in benchmarks/README.md)."""


def _disc_radius(effect) -> float | None:
    """The disc emitter's radius in pixels when it is known at trace time (the exact loop then runs near the light)."""
    radius = effect.light_radius
    if effect.source != "disc" or isinstance(radius, jax.core.Tracer):
        return None
    return float(radius)


class GodRays(Effect):
    """Radial light shafts, the XNA crepuscular-rays and galaxy-engine VLS articles (GPU Gems 3 ch. 13).

    Passes: the emitter (`source`: `"disc"`, the XNA crepuscular-rays article's light-source mask
    `2 * saturate(1 - d / light_radius)**2` through the sky; `"sky"`, the frame's
    own colour on sky pixels; `"light_pass"`, the galaxy-engine VLS article's white-light/black-occluder
    pass), then `radial_rays`, then the XNA crepuscular-rays article's `bright_pass` if `use_bright_pass`,
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
        emitter_fn, emitter_args = emitter_inputs(self, buffers, light_xy, light_in_front)
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
            rays = bright_pass(rays, threshold=self.threshold)
        return rays * self.tint.astype(rays.dtype)


class FlareOuts(Effect):
    """kbEngine's screen-space god rays, kbEngine's article.

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
        emitter_fn, emitter_args = emitter_inputs(self, buffers, light_xy, light_in_front)
        flares = scale_iterated_flares_of(
            emitter_fn,
            emitter_args,
            light_xy,
            num_iters=self.num_iters,
            max_iters=self.max_iters,
            scale_step=self.scale_step,
            decay=self.copy_decay,
        )
        flares = gaussian_blur(flares * self.intensity, sigma=self.blur_sigma, radius=self.blur_radius)
        return flares * self.tint.astype(flares.dtype)


