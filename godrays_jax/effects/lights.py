"""Several lights in one frame: `Light`, and `lit_by`, an effect drawn for each light where their light adds.

An effect is called with one light (`effect(buffers, light_xy, ...)`). A
scene often has more (two street lamps, the sun and a lamp): the light each
scatters toward the camera adds, so the frame under several lights is the
frame as the effect leaves it plus every light's own contribution, each
multiplied by that light's `tint`. `lit_by(effect, buffers, lights)` draws it,
and with one light of tint 1 it is `effect(buffers, ...)` itself.

What each kind of effect adds:

- an effect blended `"add"` or `"screen"` (rays, flare-outs, the glows, the
  lens dirt, bloom): the sum of its layers, one per light, each times its
  light's tint, blended once; `Bloom` reads no light and is drawn once;
- `VolumetricFog`: every light's in-scattering times its tint, the
  ambient light once, and the surfaces dimmed by the medium toward each
  light in proportion to that light's share of the lights' tints (the
  frame's direct light is split among them so), and the frame's own light
  the medium scatters aside once, from those dimmed surfaces;
- `ScatteringFog`: the first light draws the fogged frame with the medium's
  ambient light, every other light adds its in-scattering alone.

Effects blended `"multiply"` or `"alpha_over"` have no such sum and are
refused (`ValueError` naming `lights`).
"""

import dataclasses
import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from godrays_jax.effects.base import Effect
from godrays_jax.effects.fog import ScatteringFog
from godrays_jax.effects.glow import Bloom
from godrays_jax.effects.volumetric import VolumetricFog
from godrays_jax.kernels.bounded_medium import is_static_sun
from godrays_jax.kernels.composite import blend
from godrays_jax.kernels.volumetric import composite_fog, fog_light
from godrays_jax.primitives.buffers import Buffers
from godrays_jax.primitives.checks import check_light


class Light(eqx.Module):
    """One light of a frame, as an effect takes it.

    `xy`: its position in pixels (x right, y down, pixel centres at `i + 0.5`; off screen allowed, as for one
    light). `in_front`: False for a light behind the camera, `xy` then the projection of the light mirrored
    through the camera plane (as `light_in_front=False` means for one light). `depth`: its distance from the
    camera in scene units (`inf`, the default, for the sun). `tint`: the linear RGB its light is multiplied by,
    its colour and intensity beside the others' (>= 0; 1, the default: the effect's own light as it is).
    """

    xy: Float[ArrayLike, "2"]
    in_front: Bool[ArrayLike, ""] | bool = True
    depth: Float[ArrayLike, ""] = math.inf
    tint: Float[ArrayLike, "3"] = (1.0, 1.0, 1.0)


def lit_by(effect: Effect, buffers: Buffers, lights: Sequence[Light]) -> Float[Array, "H W C"]:
    """The frame `buffers.color` with `effect` drawn for every light of `lights` (at least one), their light
    added as the module's docstring says. One light of tint 1 gives `effect(buffers, light.xy, ...)`."""
    lights = list(lights)
    if not lights or not all(isinstance(light, Light) for light in lights):
        raise ValueError(f"lights must be a non-empty sequence of Light, got {lights!r}")
    for index, light in enumerate(lights):
        tint = light.tint
        if not isinstance(tint, jax.core.Tracer) and not (np.isfinite(tint).all() and (np.asarray(tint) >= 0).all()):
            raise ValueError(f"lights[{index}].tint must be finite and >= 0 (linear RGB), got {tint!r}")
    dtype = buffers.color.dtype
    tints = [jnp.broadcast_to(jnp.asarray(light.tint, dtype), (3,)) for light in lights]
    if isinstance(effect, VolumetricFog):
        return _volumetric_fog(effect, buffers, lights, tints)
    if isinstance(effect, ScatteringFog):
        return _scattering_fog(effect, buffers, lights, tints)
    if isinstance(effect, Bloom):
        return effect(buffers, lights[0].xy)
    check_lights_add(effect)
    layer = sum(
        _tinted(effect.layer(buffers, light.xy, **_side(light)), tint) for light, tint in zip(lights, tints)
    )
    return blend(buffers.color, layer, mode=effect.blend_mode)


def check_lights_add(effect: Effect) -> None:
    """`ValueError` naming `lights` where `effect`'s light does not add over lights (`lit_by`: blended `"multiply"`
    or `"alpha_over"`), so that a caller drawing many frames refuses before the first."""
    if isinstance(effect, (VolumetricFog, ScatteringFog, Bloom)) or effect.blend_mode in ("add", "screen"):
        return
    raise ValueError(
        f"lights: {type(effect).__name__} blends {effect.blend_mode!r}, whose layers do not add; "
        "several or tinted lights take effects blended 'add' or 'screen'"
    )


def _side(light: Light) -> dict:
    return {"light_in_front": light.in_front, "light_depth": light.depth}


def _tinted(layer: Float[Array, "H W L"], tint: Float[Array, "3"]) -> Float[Array, "H W L"]:
    """`layer`'s colour channels times `tint` (a 1-channel layer by the tint's mean), its alpha as it is."""
    channels = min(layer.shape[-1], 3)
    scale = jnp.mean(tint, keepdims=True) if channels == 1 else tint[:channels]
    return jnp.concatenate([layer[..., :channels] * scale, layer[..., channels:]], axis=-1)


def _terms_of_each(effect: VolumetricFog, buffers, lights) -> list[tuple]:
    """`effect.terms` under each light. Lights alike in what the kernel reads when it is traced (their side given as
    a Python bool or not, the sun given as a Python number or not) are traced once, in a loop over them: a fit under
    several lamps then compiles smaller programs and holds less memory, for slower calls of its Jacobian
    (benchmarks/README.md, "Several lights, light views and rooms at 480x270")."""
    kinds = {(light.in_front if isinstance(light.in_front, bool) else None, is_static_sun(light.depth)) for light in lights}
    if len(lights) == 1 or len(kinds) > 1:
        return [effect.terms(buffers, light.xy, **_side(light)) for light in lights]
    (static_front, static_sun), dtype = kinds.pop(), buffers.color.dtype
    stacked = {"xy": jnp.stack([jnp.asarray(check_light(light.xy), dtype) for light in lights])}
    if static_front is None:
        stacked["in_front"] = jnp.stack([jnp.asarray(light.in_front) for light in lights])
    if not static_sun:
        stacked["depth"] = jnp.stack([jnp.asarray(light.depth, dtype) for light in lights])

    def terms(light):
        side = {"light_in_front": light.get("in_front", static_front), "light_depth": light.get("depth", math.inf)}
        return effect.terms(buffers, light["xy"], **side)

    surface, scattered, ambient = jax.lax.map(terms, stacked)
    return [(surface[index], scattered[index], ambient[index]) for index in range(len(lights))]


def _volumetric_fog(effect: VolumetricFog, buffers, lights, tints):
    terms = _terms_of_each(effect, buffers, lights)
    # The surfaces' direct light, dimmed toward each light, split among the lights by their tints' means.
    means = jnp.stack([jnp.mean(tint) for tint in tints])
    total = jnp.sum(means)
    shares = jnp.where(total > 0, means / jnp.where(total > 0, total, 1.0), 1.0 / len(lights))
    surface = sum(share * surface for share, (surface, _, _) in zip(shares, terms))
    ambient = terms[0][2]  # the ambient light reaches every point whatever the lights: counted once
    medium = effect.medium
    ambient_color = medium.ambient_color
    light = fog_light(terms[0][1], ambient, light_color=medium.light_color * tints[0], ambient_color=ambient_color)
    for (_, scattered, _), tint in zip(terms[1:], tints[1:]):
        light = light + fog_light(
            scattered, jnp.zeros_like(ambient), light_color=medium.light_color * tint, ambient_color=ambient_color
        )  # fmt: skip
    return composite_fog(buffers.color, surface, light + effect.surface_light_aside(buffers.color, surface))


def _scattering_fog(effect: ScatteringFog, buffers, lights, tints):
    # The fogged frame lit by the ambient light alone, then each light's in-scattering without the ambient's: a
    # light's tint scales its layer, not the medium's field (whose range a product could leave).
    medium = effect.medium
    dark = dataclasses.replace(medium, light_color=jnp.zeros_like(medium.light_color))
    unlit = dataclasses.replace(medium, ambient_color=jnp.zeros_like(medium.ambient_color))
    dark, unlit = (dataclasses.replace(effect, medium=part) for part in (dark, unlit))
    layer = sum(_tinted(unlit.layer(buffers, light.xy, **_side(light)), tint) for light, tint in zip(lights, tints))
    return blend(dark(buffers, lights[0].xy, **_side(lights[0])), layer, mode="add")
