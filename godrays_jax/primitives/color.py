"""Colour encodings: linear HDR to display values and sRGB, for JAX and NumPy arrays alike.

`display_map(x) = x / (1 + |x|)` per channel (Reinhard) maps linear HDR into
`(-1, 1)`: losses compare in it, and pictures tone-map with it. sRGB is the
standard transfer curve on values clipped to [0, 1].

Quantising a smooth gradient to 8 bits draws bands one code apart, visible
in dark glows and skies; `quantize` can add triangular (TPDF) noise of one
code before rounding, which trades the bands for fine grain whose mean is the
true value. The noise comes from a seed, so a frame is written the same way
every time.
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


def quantize(
    encoded: Float[ArrayLike, "*S"], *, bits: int, dither_seed: int | None = None
) -> np.ndarray:
    """Display-encoded values in [0, 1] (clipped) to integer codes `0 .. 2**bits - 1` (NumPy, on the host).

    Without `dither_seed` each value is rounded to the nearest code. With one,
    triangular noise spanning one code either side (the sum of two uniform
    variables of one code, the dither that makes the rounding error's mean
    and variance independent of the value) is added before rounding, drawn
    from `numpy.random.default_rng(dither_seed)`: the same seed gives the same
    codes. Values at exactly 0 or 1 (black, clipped white) are not dithered.
    Returns `uint8` for 8 bits, `uint16` for 16.
    """
    if bits not in (8, 16):
        raise ValueError(f"bits must be 8 or 16, got {bits!r}")
    scale = 2**bits - 1
    values = np.clip(np.asarray(encoded, dtype=np.float64), 0.0, 1.0) * scale
    if dither_seed is not None:
        generator = np.random.default_rng(dither_seed)
        noise = generator.random(values.shape) - generator.random(values.shape)
        # Pure black and clipped white stay clean: no grain in letterboxes or blown highlights.
        values = np.where((values > 0) & (values < scale), values + noise, values)
    return np.clip(np.rint(values), 0, scale).astype(np.uint8 if bits == 8 else np.uint16)
