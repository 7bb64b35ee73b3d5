"""What every effect shares: fittable fields, the `Effect` base class, the off-screen rule and the emitters.

An effect is called as `effect(buffers, light_xy, *, light_in_front=True)` and
returns the composited frame; `effect.layer(...)` returns the effect alone,
before blending. Every array field is fittable (a JAX scalar or vector);
static fields (`eqx.field(static=True)`) are Python values that select the
algorithm. Sizes are in pixels, except `blur_power`, which is in UV units as
in the sun-overcasting article.

Off-screen and behind-camera lights, the same rule for every effect that a
light drives: the layer is multiplied by `light_visibility(light_xy, ...,
fade=offscreen_fade)`, 1 while the light is on screen, fading smoothly to 0
once the light is `offscreen_fade` frame-widths beyond the edge, and 0 when
the light is behind the camera (`light_in_front` false: the frame comes back
unchanged). `Bloom` does not depend on the light and ignores both.
"""

import dataclasses
import functools
import reprlib
import typing
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike
from jaxtyping import Array, ArrayLike, Bool, Float

from godrays_jax.kernels.composite import BLEND_MODES, blend
from godrays_jax.kernels.masks import coverage_mask, light_source_mask
from godrays_jax.primitives.buffers import Buffers
from godrays_jax.primitives.checks import check_light, is_static_int

Source = Literal["disc", "sky", "light_pass"]


SOURCES: tuple[str, ...] = ("disc", "sky", "light_pass")


STATIC_RANGES: dict[str, tuple[int, int]] = {
    "max_samples": (1, 4096),
    "max_iters": (1, 64),
    "max_passes": (0, 8),
    "max_morphology": (0, 64),
    "blur_radius": (0, 1024),
    "glow_radius": (0, 1024),
    "radius": (0, 1024),
    "gaussian_radius": (0, 1024),
    "resolution_factor": (1, 64),
    "dirt_seed": (0, 2**63 - 1),
}
"""Inclusive ranges of the integer static fields, checked by every effect's constructor (so also for params files).

Loop lengths stop at the top of the fittable count they bound (`num_samples`
<= 4096, `num_iters` <= 64, `passes` <= 8, `source_grow` / `occluder_shrink`
<= 64 px): a longer loop renders the same image more slowly, and a huge one
(`max_samples: 1e8`) hangs a render. Blur half-widths stop at 1024 px, three
standard deviations of the widest Gaussian (`gaussian_sigma` <= 100 px) with
room to spare; `resolution_factor` at 64 (a 4K frame is then 60 px wide);
`dirt_seed` is any non-negative 64-bit seed.
"""


def _is_numbers(value) -> bool:
    if isinstance(value, jax.core.Tracer):
        return True
    if isinstance(value, (jax.Array, np.ndarray, np.generic)):
        return value.dtype.kind in "fiu"
    if isinstance(value, bool) or not isinstance(value, (int, float, list, tuple)):
        return False
    try:
        return np.asarray(value).dtype.kind in "fiu"  # ragged or too deep lists raise; huge ints are objects
    except (ValueError, TypeError, OverflowError, RecursionError):
        return False


def _array(value) -> Array:
    # Anything but numbers is kept as given, so that `__check_init__` names the field:
    # a JSON "0.5" or true is not a number.
    return jnp.asarray(value, dtype=jnp.result_type(float)) if _is_numbers(value) else value


_SHOWN = reprlib.Repr()
_SHOWN.maxlevel, _SHOWN.maxstring, _SHOWN.maxother = 3, 40, 40


def _check_static(owner: str, name: str, annotation, value) -> None:
    """A static field's value against its annotation (`bool`, `int` with `STATIC_RANGES`, `Literal`, `str`)."""
    shown = _SHOWN.repr(value)
    if annotation is bool:
        if not isinstance(value, (bool, np.bool_)):
            raise ValueError(f"{owner}.{name} must be true or false (a boolean), got {shown}")
    elif annotation is int:
        if not is_static_int(value):
            raise ValueError(f"{owner}.{name} must be an integer, got {shown}")
        low, high = STATIC_RANGES.get(name, (0, 2**63 - 1))
        if not low <= value <= high:
            raise ValueError(f"{owner}.{name} must lie in [{low}, {high}] (STATIC_RANGES), got {value}")
    elif typing.get_origin(annotation) is Literal:
        if not isinstance(value, str) or value not in typing.get_args(annotation):
            raise ValueError(f"{owner}.{name} must be one of {', '.join(typing.get_args(annotation))}; got {shown}")
    elif annotation is str and not isinstance(value, str):
        raise ValueError(f"{owner}.{name} must be a string, got {shown}")


@functools.cache
def _static_annotations(cls) -> dict[str, object]:
    hints = typing.get_type_hints(cls)
    return {field.name: hints[field.name] for field in dataclasses.fields(cls) if field.metadata.get("static")}


def param(default, *, low: float, high: float):
    """A fittable field, stored as a floating JAX array whatever number or list is given.

    `[low, high]` is its valid range (every element, for a vector): fitting keeps
    the value inside it and the tuner's sliders span it.
    """
    return eqx.field(converter=_array, default=default, metadata={"bounds": (low, high)})


def plain_value(value):
    """A field's value as plain Python (float, nested lists of floats, or the static value itself).

    Floating arrays become the shortest decimals that read back to the same
    numbers in their own precision: a float32 0.95 is `0.95`, not
    `0.949999988079071`.
    """
    if not isinstance(value, (jax.Array, np.ndarray, np.generic)) or isinstance(value, jax.core.Tracer):
        return value
    array = np.asarray(value)
    if not np.issubdtype(array.dtype, np.floating):
        return array.tolist()
    # NumPy's str of a float32 scalar is the shortest decimal that round-trips; float() of it keeps that text.
    shortest = [float(str(number)) for number in array.ravel()]
    return np.array(shortest, dtype=object).reshape(array.shape).tolist()


def parameter_bounds(effect: "Effect | type[Effect]") -> dict[str, tuple[float, float]]:
    """`{field name: (low, high)}` for every fittable field of an effect (instance or class)."""
    cls = effect if isinstance(effect, type) else type(effect)
    return {field.name: field.metadata["bounds"] for field in dataclasses.fields(cls) if "bounds" in field.metadata}


class Effect(eqx.Module):
    """Base class: subclasses define `layer` and a static `blend_mode` field."""

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        _EFFECT_CLASSES[cls.__name__] = cls

    def __check_init__(self):
        owner = type(self).__name__
        for name, annotation in _static_annotations(type(self)).items():
            _check_static(owner, name, annotation, getattr(self, name))
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
            if not isinstance(value, jax.Array):
                shown = _SHOWN.repr(value)
                raise ValueError(f"{owner}.{name} must be a number (a list of numbers for a vector), got {shown}")
            values = np.asarray(value)
            if not (np.all(np.isfinite(values)) and np.all(values >= low) and np.all(values <= high)):
                raise ValueError(f"{owner}.{name} must lie in [{low:g}, {high:g}], got {values.tolist()}")

    def __repr__(self) -> str:
        """`GodRays(density=0.5, ...)`: every field with its value (equinox shows `f32[]` placeholders)."""
        fields = ", ".join(f"{field.name}={plain_value(getattr(self, field.name))!r}" for field in dataclasses.fields(self))
        return f"{type(self).__name__}({fields})"

    def layer(
        self, buffers: Buffers, light_xy: Float[ArrayLike, "2"], *, light_in_front: Bool[ArrayLike, ""] | bool = True
    ) -> Float[Array, "H W L"]:
        raise NotImplementedError

    def __call__(
        self, buffers: Buffers, light_xy: Float[ArrayLike, "2"], *, light_in_front: Bool[ArrayLike, ""] | bool = True
    ) -> Float[Array, "H W C"]:
        """The frame with the effect blended on: `blend(buffers.color, layer, mode=blend_mode)`."""
        return blend(buffers.color, self.layer(buffers, light_xy, light_in_front=light_in_front), mode=self.blend_mode)


_EFFECT_CLASSES: dict[str, type[Effect]] = {}


def effect_class(name: str) -> type[Effect]:
    """The effect class of that name (every subclass of `Effect` registers itself); `ValueError` if none."""
    if name not in _EFFECT_CLASSES:
        raise ValueError(f"unknown effect {name!r}; known effects: {', '.join(sorted(_EFFECT_CLASSES))}")
    return _EFFECT_CLASSES[name]


def light_visibility(
    light_xy: Float[ArrayLike, "2"],
    height: int,
    width: int,
    *,
    fade: Float[ArrayLike, ""],
    light_in_front: Bool[ArrayLike, ""] | bool = True,
    dtype: DTypeLike = jnp.float32,
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
    reach = jnp.maximum(jnp.asarray(fade, dtype), 1e-6) * max(height, width)
    # Clipped to the reach, then in units of it, before squaring: squares of far lights' pixel distances
    # overflow float32 (beyond ~2e19 px), and a distance of 1 reach or more is t = 1 whatever the rest.
    outside_x = jnp.minimum(jnp.maximum(jnp.maximum(-light_xy[0], light_xy[0] - width), 0.0), reach) / reach
    outside_y = jnp.minimum(jnp.maximum(jnp.maximum(-light_xy[1], light_xy[1] - height), 0.0), reach) / reach
    squared = outside_x**2 + outside_y**2
    distance = jnp.where(squared > 0, jnp.sqrt(jnp.where(squared > 0, squared, 1.0)), 0.0)
    t = jnp.minimum(distance, 1.0)
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


def emitter_inputs(effect, buffers: Buffers, light_xy, light_in_front):
    """`(function, arguments)` drawing the effect's emitter; the arguments hold only what that source depends on.

    The loops differentiate an emitter's few-number arguments in forward mode,
    one sampled derivative image each, so an unused one (a sky's disc radius)
    would cost a derivative image of zeros.
    """
    radius = effect.light_radius if effect.source == "disc" else None
    arguments = (buffers, light_xy, radius, light_in_front, effect.offscreen_fade)
    return functools.partial(_emitter, effect.source), arguments


