"""Blend an effect layer onto a scene.

The scene is `(H, W, C)`; the layer `(H, W, 1)` or `(H, W, 3)` is broadcast over
the colour channels. A fourth (alpha) channel of the scene passes through
unchanged, except in `alpha_over`. No operation clips: values stay linear HDR.
"""

from typing import Literal

import jax.numpy as jnp
from jaxtyping import Array, Float

from godrays_jax.primitives.checks import check_image

BlendMode = Literal["add", "screen", "multiply", "alpha_over"]
BLEND_MODES: tuple[str, ...] = ("add", "screen", "multiply", "alpha_over")
"""The ways `blend` puts a layer onto a scene."""


def _split(scene, layer):
    check_image(scene, "scene")
    check_image(layer, "layer")
    if layer.shape[:2] != scene.shape[:2]:
        raise ValueError(f"layer shape {layer.shape} does not match scene shape {scene.shape}")
    colour_channels = min(scene.shape[-1], 3)
    if layer.shape[-1] not in (1, colour_channels, 4):
        raise ValueError(f"layer must have 1 or {colour_channels} channels (or 4 with alpha), got {layer.shape[-1]}")
    return scene[..., :colour_channels], scene[..., colour_channels:]


def _join(colour, rest):
    return jnp.concatenate([colour, rest], axis=-1) if rest.shape[-1] else colour


def add(scene: Float[Array, "H W C"], layer: Float[Array, "H W L"]) -> Float[Array, "H W C"]:
    """`scene + layer` (the sun-overcasting, kbEngine and XNA crepuscular-rays articles' Additive, 004)."""
    colour, rest = _split(scene, layer)
    return _join(colour + layer[..., : colour.shape[-1]], rest)


def screen(scene: Float[Array, "H W C"], layer: Float[Array, "H W L"]) -> Float[Array, "H W C"]:
    """`1 - (1 - scene) * (1 - layer)` (Unity SunShafts). Meant for values in [0, 1]."""
    colour, rest = _split(scene, layer)
    return _join(1.0 - (1.0 - colour) * (1.0 - layer[..., : colour.shape[-1]]), rest)


def multiply(scene: Float[Array, "H W C"], layer: Float[Array, "H W L"]) -> Float[Array, "H W C"]:
    """`scene * layer` (the XNA crepuscular-rays article's Blend technique)."""
    colour, rest = _split(scene, layer)
    return _join(colour * layer[..., : colour.shape[-1]], rest)


def alpha_over(scene: Float[Array, "H W C"], layer: Float[Array, "H W 4"]) -> Float[Array, "H W C"]:
    """Straight-alpha "over": `layer.rgb * a + scene * (1 - a)`; a scene alpha becomes `a + alpha * (1 - a)`."""
    if layer.shape[-1] != 4:
        raise ValueError(f"layer must be RGBA (4 channels) for alpha_over, got {layer.shape[-1]}")
    colour, rest = _split(scene, layer)
    alpha = layer[..., 3:]
    colour = layer[..., : colour.shape[-1]] * alpha + colour * (1.0 - alpha)
    return _join(colour, rest + alpha * (1.0 - rest) if rest.shape[-1] else rest)


def blend(scene: Float[Array, "H W C"], layer: Float[Array, "H W L"], *, mode: BlendMode = "add") -> Float[Array, "H W C"]:
    """Blend `layer` onto `scene` with one of `BLEND_MODES`."""
    functions = {"add": add, "screen": screen, "multiply": multiply, "alpha_over": alpha_over}
    if mode not in functions:
        raise ValueError(f"mode must be one of {', '.join(BLEND_MODES)}; got {mode!r}")
    return functions[mode](scene, layer)
