"""Colour encodings: linear HDR to display values and sRGB, for JAX and NumPy arrays alike.

`display_map(x) = x / (1 + |x|)` per channel (Reinhard) maps linear HDR into
`(-1, 1)`: losses compare in it, and pictures tone-map with it. sRGB is the
standard transfer curve on values clipped to [0, 1].
"""

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, UInt8


def _namespace(values):
    """`jax.numpy` for JAX arrays and tracers (stays on the device, under jit), NumPy otherwise."""
    return jnp if isinstance(values, jax.Array) else np


def display_map(image: Float[ArrayLike, "*S"]) -> Float[ArrayLike, "*S"]:
    """`x / (1 + |x|)`: linear HDR into (-1, 1), 0 at 0, monotone, differentiable everywhere."""
    return image / (1.0 + abs(image))


def srgb_encode(linear: Float[ArrayLike, "*S"]) -> Float[ArrayLike, "*S"]:
    """Linear values in [0, 1] (clipped) to the sRGB transfer curve; finite gradients at 0."""
    xp = _namespace(linear)
    x = xp.clip(linear, 0.0, 1.0)
    return xp.where(x <= 0.0031308, 12.92 * x, 1.055 * xp.power(xp.maximum(x, 0.0031308), 1 / 2.4) - 0.055)


def srgb_decode(encoded: Float[ArrayLike, "*S"]) -> Float[ArrayLike, "*S"]:
    """sRGB-encoded values in [0, 1] (clipped) back to linear."""
    xp = _namespace(encoded)
    x = xp.clip(encoded, 0.0, 1.0)
    return xp.where(x <= 0.04045, x / 12.92, xp.power((xp.maximum(x, 0.04045) + 0.055) / 1.055, 2.4))


def to_srgb8(display: Float[Array, "H W C"]) -> UInt8[Array, "H W 3"]:
    """Display values in [0, 1] to 8-bit sRGB RGB: one channel is shown grey, a fourth (alpha) is dropped."""
    xp = _namespace(display)
    rgb = xp.broadcast_to(display[..., :1], (*display.shape[:2], 3)) if display.shape[-1] < 3 else display[..., :3]
    return xp.round(srgb_encode(rgb) * 255.0).astype(xp.uint8)
