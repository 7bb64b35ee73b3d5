"""Bilinear texture sampling at continuous pixel positions, as a GPU sampler does it.

Positions are pixel coordinates: x right, y down, pixel centres at `i + 0.5`, so
sampling at `(i + 0.5, j + 0.5)` returns pixel `(j, i)` exactly.
"""

from typing import Literal

import jax.numpy as jnp
from jaxtyping import Array, Float

Addressing = Literal["clamp", "zero"]


def sample_bilinear(
    image: Float[Array, "H W C"],
    x: Float[Array, "*S"],
    y: Float[Array, "*S"],
    *,
    addressing: Addressing = "clamp",
) -> Float[Array, "*S C"]:
    """Bilinearly interpolate `image` at pixel positions `(x, y)`.

    Args:
        image: the texture.
        x, y: pixel coordinates of equal shape; any real values.
        addressing: what lies off the image. `"clamp"` repeats the edge texels
            (GPU clamp-to-edge); `"zero"` makes texels outside the image 0, so
            values fade to 0 over the half pixel past the border (GPU border
            colour 0).

    Returns:
        The samples, shape `x.shape + (C,)`. Differentiable in `image`, `x`, `y`.
    """
    if addressing not in ("clamp", "zero"):
        raise ValueError(f"addressing must be 'clamp' or 'zero', got {addressing!r}")
    height, width = image.shape[0], image.shape[1]
    u = x - 0.5
    v = y - 0.5
    u0 = jnp.floor(u)
    v0 = jnp.floor(v)
    fu = (u - u0)[..., None]
    fv = (v - v0)[..., None]
    u0 = u0.astype(jnp.int32)
    v0 = v0.astype(jnp.int32)
    flat = image.reshape(height * width, image.shape[2])

    def texel(col, row):
        inside = (col >= 0) & (col < width) & (row >= 0) & (row < height)
        col = jnp.clip(col, 0, width - 1)
        row = jnp.clip(row, 0, height - 1)
        values = flat[row * width + col]
        if addressing == "zero":
            values = jnp.where(inside[..., None], values, 0.0)
        return values

    top = texel(u0, v0) * (1 - fu) + texel(u0 + 1, v0) * fu
    bottom = texel(u0, v0 + 1) * (1 - fu) + texel(u0 + 1, v0 + 1) * fu
    return top * (1 - fv) + bottom * fv


def pixel_centres(height: int, width: int, dtype=jnp.float32) -> tuple[Float[Array, "H W"], Float[Array, "H W"]]:
    """The `(x, y)` pixel-centre coordinates of an `height x width` image."""
    xs = jnp.arange(width, dtype=dtype) + 0.5
    ys = jnp.arange(height, dtype=dtype) + 0.5
    return jnp.broadcast_to(xs[None, :], (height, width)), jnp.broadcast_to(ys[:, None], (height, width))
