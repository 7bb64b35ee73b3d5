"""What every effect shares: the `Effect` base class, the off-screen rule and the emitters.

An effect is called as `effect(buffers, light_xy, *, light_in_front=True,
light_depth=inf)` and returns the composited frame; `effect.layer(...)`
returns the effect alone, before blending. `light_depth` is the light's
distance from the camera in scene units (`+inf`, the default, for a light at
infinity such as a directional sun); the XNA crepuscular-rays article's depth
test and step clamp read it, other effects ignore it. Fields are declared
with `effects.fields` (`param`, `static`, ...): fittable ones are JAX scalars
or vectors, static ones Python values that select the algorithm.

Sizes are in frame units, so a preset gives the same picture at any
resolution: a flare's `flare_size` is in UV units as the articles write it
(a half-extent of `flare_size * W` pixels across and `flare_size * H` down),
every other size (blur sigmas and reaches, radii) is a fraction of the
frame's larger side `max(W, H)`; `blur_power` is in UV units as in the
sun-overcasting article. An effect built with `units="px"` takes its sizes
in pixels instead (`size_fields` names them).

Off-screen and behind-camera lights, one rule for every effect drawn from the
light's position on screen (the emitters' shafts and flares, the glows, the
lens dirt, `ScatteringFog`'s shafts): the layer is multiplied by
`light_visibility(light_xy, ..., fade=offscreen_fade)`, 1 while the light is
on screen, fading smoothly to 0 once the light is `offscreen_fade`
frame-widths beyond the edge, and 0 when the light is behind the camera
(`light_in_front` false: the frame comes back unchanged). `VolumetricFog`
lights its medium from the light wherever it is, behind the camera included;
`Bloom` does not depend on the light and ignores both.
"""

import dataclasses
import functools
import math
import typing
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike
from jaxtyping import Array, ArrayLike, Bool, Float

from godrays_jax.effects.fields import Part
from godrays_jax.kernels.composite import blend
from godrays_jax.kernels.masks import (
    coverage_mask,
    depth_test_mask,
    flare_image,
    hardware_depth,
    light_source_mask,
    procedural_flare,
    sky_mask,
)
from godrays_jax.primitives.buffers import Buffers
from godrays_jax.primitives.camera import focal_length_px, ray_depth_scale
from godrays_jax.primitives.checks import check_light

Source = Literal["disc", "sky", "light_pass"]


SOURCES: tuple[str, ...] = ("disc", "sky", "light_pass")

SceneMask = Literal["coverage", "sky", "depth"]
SCENE_MASKS: tuple[str, ...] = ("coverage", "sky", "depth")
"""What lets a flare emitter through: the antialiased open sky (`1 - coverage`), the hard sky test (kbEngine's
`1 - sign(depth)`: depth `+inf`), or the XNA crepuscular-rays article's depth test (pixels nearer than the light
blanked)."""

Units = Literal["frame", "px"]
UNITS: tuple[str, ...] = ("frame", "px")

FlareShape = Literal["glow", "cone"]
FLARE_SHAPES: tuple[str, ...] = ("glow", "cone")
"""The flare drawn without a `flare_texture`: `masks.procedural_flare()` (a bright core in a dim halo), or the
analytic cone `saturate(1 - r)` of `masks.light_source_mask` (bright out to its rim)."""


def pixels_per_unit(units: str, height: int, width: int) -> float:
    """What one size unit is in pixels: the larger side `max(H, W)` for `"frame"`, 1 for `"px"`."""
    return float(max(height, width)) if units == "frame" else 1.0


def reach_taps(reach: float, units: str, height: int, width: int, *, level: int = 1) -> int:
    """A static reach as a tap count on a `1/level` resolution image (at least 1)."""
    return max(1, math.ceil(reach * pixels_per_unit(units, height, width) / level - 1e-9))


def flare_size_px(size, units: str, height: int, width: int, dtype) -> Float[Array, "2"]:
    """A flare's half-extent `(rx, ry)` in pixels: UV units stretch with the frame (`(size * W, size * H)`)."""
    size = jnp.asarray(size, dtype)
    if units == "px":
        return jnp.stack([size, size])
    return jnp.stack([size * width, size * height])


class Effect(Part):
    """Base class: subclasses define `layer` and a static `blend_mode` field.

    `NEEDS_DEPTH` (a class constant) says whether the effect measures
    distance in the frame's depth (`needs_depth`). `FIELD_STAGES` (a class
    constant, `{fitted field: stage}`, fields named as `field_metadata` names
    them) says where a fittable field first enters the effect's computation:
    `fit`'s forward-mode Jacobian takes each stage's fields in a vectorised
    pass of their own, so that a field that enters late (a colour, a weight
    of the final sum) is differentiated through the late operations alone,
    not carried beside the others through the whole computation. Fields not
    listed share one stage; the values are the same either way.
    """

    NEEDS_DEPTH: typing.ClassVar[bool] = False
    FIELD_STAGES: typing.ClassVar[dict[str, str]] = {}
    SHARP_STAGES: typing.ClassVar[tuple[str, ...] | None] = None
    """The stages (of `FIELD_STAGES`) whose fields move edges a pixel or two wide, which a coarser frame's
    derivatives blur: a fit's polish after a coarse phase takes theirs at the frame's own resolution and the other
    fields' at the coarse one (`fit(..., coarse_jacobian=True)`). None: the effect does not say, and the polish takes
    every field's at the frame's own."""
    DIFFERENCED_STAGES: typing.ClassVar[tuple[str, ...]] = ()
    """The stages (of `FIELD_STAGES`) whose columns of `fit`'s Jacobian are central differences of two renders
    without derivatives (`values_only`) instead of forward-mode lanes: fields that reach a large intermediate the
    other fields of their stage do not, whose tangent would hold a copy of it per lane."""
    POLISH_FIELDS: typing.ClassVar[tuple[str, ...]] = ()
    """Fields a fit holds at their start's values while its starts race and descend, and fits in the polish alone
    (Levenberg-Marquardt's, `fit`): fields that trade against the others where the fit is still far from its
    minimum, and only refine it near there."""
    LIGHT_TINT_STAGE: typing.ClassVar[str] = ""
    """The stage (of `FIELD_STAGES`) where the tints of several lights enter (`effects.lights.lit_by` multiplies
    each light's part by its own): `fit`'s Jacobian takes a fitted tint's columns there."""
    CAMERA_FIELDS: typing.ClassVar[tuple[str, ...]] = ()
    """The fields in which the effect reads its frame's camera (`with_camera`): `"fov_x_deg"`, and `"near_plane"`
    with `"far_plane"`."""

    def with_camera(self, *, fov_x_deg: float | None = None, clip_planes: tuple[float, float] | None = None) -> "Effect":
        """This effect seen through a frame's camera: its horizontal field of view in degrees and its near and far
        clip planes in scene units (a renderer's, as `godrays:clip_planes` stores them), each set where the effect
        reads it (`CAMERA_FIELDS`) and left as it is when None. An effect that reads neither is returned as it is;
        the commands give every effect its frame's camera this way."""
        values = {}
        if fov_x_deg is not None and "fov_x_deg" in self.CAMERA_FIELDS:
            values["fov_x_deg"] = np.float32(fov_x_deg)
        if clip_planes is not None and "near_plane" in self.CAMERA_FIELDS:
            values["near_plane"], values["far_plane"] = (float(plane) for plane in clip_planes)
        return dataclasses.replace(self, **values) if values else self

    @property
    def reads_light_pass(self) -> bool:
        """Whether the effect draws from the frame's rendered light pass (`Buffers.light_pass`)."""
        return False

    def for_buffers(self, buffers: Buffers) -> tuple["Effect", str | None]:
        """The effect to draw on `buffers`, and why it is another one (None: it is this one). An effect that
        reads a pass the frame lacks gives its nearest stand-in, the commands warn with the reason; this effect
        itself by default."""
        return self, None

    def with_flare_texture(self, texture: Float[Array, "h w C"]) -> "Effect":
        """This effect drawing `texture` (linear, 1 to 4 channels) as its flare. Raises `ValueError` for an effect
        that draws no flare."""
        raise ValueError(f"{type(self).__name__} draws no flare (use a GodRays or FlareOuts effect)")

    def same_on(self, frames: typing.Sequence[Buffers]) -> "Effect":
        """An effect that draws `frames` as this one does (to float rounding), more cheaply where those frames allow
        it (a `VolumetricFog` on frames where nothing casts a shadow, or whose depth map seen from the light covers
        them, reads no shadows off the screen); this effect itself by default.
        `fit` fits it in this one's place and returns the fields it fitted in this one."""
        return self

    def frames_read_once(self, frames: typing.Sequence[Buffers], *, fitted: typing.Collection[str]) -> list[Buffers]:
        """`frames` with what this effect reads off a frame alone read beforehand (`Buffers.silhouettes`), where
        none of the fields in `fitted` changes it: calls on the frames returned draw what calls on `frames` draw,
        without reading it again. `fit` reads them once per frame and resolution, not in every step. The frames
        themselves by default."""
        return list(frames)

    def fit_stand_in(self) -> "Effect":
        """The effect `fit` fits in this one's place (`pipeline.fit.fit`'s `stand_in`): the same fields, read
        more cheaply where a cheaper reading gives nearly the same frame; this effect itself by default."""
        return self

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        _EFFECT_CLASSES[cls.__name__] = cls

    def layer(
        self,
        buffers: Buffers,
        light_xy: Float[ArrayLike, "2"],
        *,
        light_in_front: Bool[ArrayLike, ""] | bool = True,
        light_depth: Float[ArrayLike, ""] = math.inf,
    ) -> Float[Array, "H W L"]:
        raise NotImplementedError

    def __call__(
        self,
        buffers: Buffers,
        light_xy: Float[ArrayLike, "2"],
        *,
        light_in_front: Bool[ArrayLike, ""] | bool = True,
        light_depth: Float[ArrayLike, ""] = math.inf,
    ) -> Float[Array, "H W C"]:
        """The frame with the effect blended on: `blend(buffers.color, layer, mode=blend_mode)`.

        `light_depth`: the light's distance from the camera in scene units
        (`+inf`: at infinity), as `render` stores it (`godrays:light_depth`).
        """
        layer = self.layer(buffers, light_xy, light_in_front=light_in_front, light_depth=light_depth)
        return blend(buffers.color, layer, mode=self.blend_mode)


_EFFECT_CLASSES: dict[str, type[Effect]] = {}


def needs_depth(effect: "Effect | type[Effect]") -> bool:
    """Whether the effect measures distance in the frame's depth, and so cannot run on a frame without it.

    The shaft and glow effects find the open sky in the frame's coverage,
    which a frame without depth draws from its bright parts
    (`plates.buffers_without_depth`); a medium's extinction and the lens
    dirt's depth factor need the distances themselves.
    """
    cls = effect if isinstance(effect, type) else type(effect)
    return cls.NEEDS_DEPTH


def frame_ray_depth(effect: "Effect", buffers: Buffers) -> Float[Array, "H W"]:
    """`buffers.ray_depth(effect.fov_x_deg)`, or a `ValueError` naming the effects that run without depth."""
    if buffers.depth is None:
        without = sorted(name for name, cls in _EFFECT_CLASSES.items() if not cls.NEEDS_DEPTH)
        raise ValueError(
            f"buffers.depth: {type(effect).__name__} needs the frame's depth and this frame has none; "
            f"effects that run without depth: {', '.join(without)}"
        )
    return buffers.ray_depth(getattr(effect, "fov_x_deg", None))


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
    light_xy = check_light(light_xy)
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


def scene_mask_of(kind: str, buffers: Buffers, light_depth, clip: "ClipPlanes | None" = None) -> Float[Array, "H W"]:
    """The scene mask `kind` (`SCENE_MASKS`): 1 where an emitter shows, 0 where the scene hides it.

    `"depth"` is the XNA crepuscular-rays article's `LightSceneMask`: the
    pixel is blanked when its hardware depth (`masks.hardware_depth`, z/w of
    the camera's `clip` planes) is below the light's less `clip.depth_bias`
    (the article's .00025). Hardware depth is planar: a frame's ray depth is
    converted with `clip.fov_x_deg`, and the light's distance (`light_depth`,
    along its ray) at its pixel `clip.light_xy`. A light at infinity is on
    the far plane (z/w 1): the sky passes, and geometry within the bias of
    the far plane. A frame
    without depth gives the coverage mask for every kind: its coverage says
    what is open sky (`plates.buffers_without_depth`). The test is a hard
    step: its threshold has no gradient, so the bias and the planes are
    static fields.
    """
    dtype = buffers.color.dtype
    if kind == "coverage" or buffers.depth is None:
        return coverage_mask(buffers.coverage).astype(dtype)
    if kind == "sky":
        return sky_mask(buffers.depth).astype(dtype)
    planes = dict(near_plane=clip.near_plane, far_plane=clip.far_plane)
    if buffers.depth_kind == "planar":
        planar = buffers.depth.astype(dtype)
    else:
        planar = buffers.ray_depth() / ray_depth_scale(buffers.height, buffers.width, fov_x_deg=clip.fov_x_deg, dtype=dtype)
    light_planar = planar_light_depth(light_depth, clip.light_xy, buffers.height, buffers.width, clip.fov_x_deg, dtype)
    return depth_test_mask(
        hardware_depth(planar, **planes), light_depth=hardware_depth(light_planar, **planes), bias=clip.depth_bias
    ).astype(dtype)


class ClipPlanes(typing.NamedTuple):
    """What the XNA depth test needs besides the depth: the camera's planes (static) and where the light is."""

    near_plane: float
    far_plane: float
    depth_bias: float
    fov_x_deg: Float[Array, ""]
    light_xy: Float[Array, "2"]


def planar_light_depth(light_depth, light_xy, height: int, width: int, fov_x_deg, dtype) -> Float[Array, ""]:
    """The light's distance along the camera's axis (scene units) from its distance along its ray at `light_xy`.

    `light_depth / sqrt(1 + ((x - W/2) / f)^2 + ((H/2 - y) / f)^2)`, `f` the focal length in pixels of
    `fov_x_deg`; `+inf` stays `+inf`.
    """
    light_xy = jnp.asarray(light_xy, dtype)
    focal = focal_length_px(width, fov_x_deg, dtype)
    scale = jnp.sqrt(1.0 + ((light_xy[0] - 0.5 * width) / focal) ** 2 + ((0.5 * height - light_xy[1]) / focal) ** 2)
    light_depth = jnp.asarray(light_depth, dtype)
    at_infinity = jnp.isinf(light_depth)
    # Divided only where finite: inf / scale would give the gradient in the scale a NaN (0 * inf).
    return jnp.where(at_infinity, jnp.inf, jnp.where(at_infinity, 1.0, light_depth) / scale)


@functools.lru_cache(maxsize=1)
def default_flare() -> np.ndarray:
    """The flare texture used when an effect is given none: `masks.procedural_flare()`."""
    return procedural_flare()


def _emitter(
    source: str,
    scene_mask: str,
    squared: bool,
    planes: tuple[float, float, float] | None,
    buffers: Buffers,
    light_xy,
    flare_size,
    texture,
    light_in_front,
    fade,
    light_depth,
    fov_x_deg,
) -> Float[Array, "H W C"]:
    """What shines: a flare at the light through the scene mask, the sky's own colour, or the light pass.

    The flare is the XNA article's `2 * pow(tex, 2)` when `squared`, else the texture as sampled (kbEngine's).
    `planes` (near, far, depth bias) and `fov_x_deg` serve the depth test only.
    """
    dtype = buffers.color.dtype
    visible = light_visibility(
        light_xy, buffers.height, buffers.width, fade=fade, light_in_front=light_in_front, dtype=dtype
    )
    if source == "light_pass":
        if buffers.light_pass is None:
            raise ValueError("source='light_pass' needs buffers.light_pass (render it, or use source='disc')")
        return buffers.light_pass[..., None].astype(dtype) * visible
    clip = None if planes is None else ClipPlanes(*planes, fov_x_deg=fov_x_deg, light_xy=light_xy)
    mask = scene_mask_of(scene_mask, buffers, light_depth, clip)[..., None]
    if source == "disc":
        draw = light_source_mask if squared else flare_image
        flare = draw(buffers.height, buffers.width, light_xy, flare_size=flare_size, texture=texture, dtype=dtype)
        return flare * mask * visible
    colour = buffers.color[..., :3] if buffers.color.shape[-1] >= 3 else buffers.color[..., :1]
    return colour * mask * visible


def flare_texture_of(effect) -> Float[Array, "h w C"] | None:
    """The effect's flare texture as the XNA article's sampler reads it (`coord = .5 - offset`: turned by 180 degrees).

    `None` for the analytic cone (`flare_shape="cone"` without a texture).
    The texture is data, not a fitted parameter: no gradient flows into it.
    """
    if effect.flare_texture is None and effect.flare_shape == "cone":
        return None
    texture = default_flare() if effect.flare_texture is None else effect.flare_texture
    return jax.lax.stop_gradient(jnp.asarray(texture)[::-1, ::-1])


def emitter_inputs(effect, buffers: Buffers, light_xy, light_in_front, light_depth):
    """`(function, arguments)` drawing the effect's emitter; the arguments hold only what that source depends on.

    The loops differentiate an emitter's few-number arguments in forward mode,
    one sampled derivative image each, so an unused one (a sky's flare size)
    would cost a derivative image of zeros. The flare's half-extent is
    `effect.flare_size_in_px(...)` (its half-extent in pixels); the depth test reads the effect's
    `near_plane`, `far_plane`, `depth_bias` and `fov_x_deg`.
    """
    dtype = buffers.color.dtype
    flare = effect.source == "disc"
    flare_size = effect.flare_size_in_px(buffers.height, buffers.width, light_xy, light_depth, dtype) if flare else None
    texture = flare_texture_of(effect) if flare else None
    depth_test = effect.source != "light_pass" and effect.scene_mask == "depth" and buffers.depth is not None
    scene_mask = effect.scene_mask
    arguments = (
        buffers, light_xy, flare_size, texture, light_in_front, effect.offscreen_fade,
        light_depth if depth_test else None, effect.fov_x_deg if depth_test else None,
    )  # fmt: skip
    planes = (effect.near_plane, effect.far_plane, effect.depth_bias) if depth_test else None
    static = (effect.source, scene_mask, effect.FLARE_SQUARED, planes)
    return functools.partial(_emitter, *static), arguments
