"""Resolution changes: box pooling over `factor x factor` blocks and bilinear read-back.

Output pixel `(j, i)` of a `1/factor` image covers full-resolution pixels
`[factor * i, factor * (i + 1))` x `[factor * j, factor * (j + 1))`; a ragged
last row or column of blocks is completed with the edge pixels
(clamp-to-edge). Full-resolution pixel position `x` is position `x / factor`.
"""

from typing import Literal

import jax.numpy as jnp
from jaxtyping import Array, Float

from godrays_jax.primitives.checks import check_image, is_static_int
from godrays_jax.primitives.sampling import sample_separable

Pooling = Literal["mean", "min", "max"]
POOLINGS: tuple[str, ...] = ("mean", "min", "max")


def _check_factor(factor) -> None:
    if not is_static_int(factor) or factor < 1:
        raise ValueError(f"factor must be a Python int >= 1, got {factor!r}")


def box_pool(image: Float[Array, "H W *C"], factor: int, *, pooling: Pooling = "mean") -> Float[Array, "h w *C"]:
    """Each `factor x factor` block's mean (or min or max), `h = ceil(H / factor)`, `w = ceil(W / factor)`.

    Works on images `(H, W, C)` and planes `(H, W)`. `pooling="min"` keeps a
    block's nearest depth (sky, `+inf`, only where the whole block is sky).
    """
    _check_factor(factor)
    if pooling not in POOLINGS:
        raise ValueError(f"pooling must be one of {', '.join(POOLINGS)}; got {pooling!r}")
    height, width = image.shape[:2]
    low_h, low_w = -(-height // factor), -(-width // factor)
    padding = ((0, low_h * factor - height), (0, low_w * factor - width)) + ((0, 0),) * (image.ndim - 2)
    blocks = jnp.pad(image, padding, mode="edge").reshape(low_h, factor, low_w, factor, *image.shape[2:])
    return getattr(blocks, pooling)(axis=(1, 3))


def downsample_box(image: Float[Array, "H W C"], factor: int) -> Float[Array, "h w C"]:
    """Average each `factor x factor` block of pixels, `h = ceil(H / factor)`, `w = ceil(W / factor)` (`box_pool`)."""
    check_image(image)
    return box_pool(image, factor)


def upsample_bilinear(image: Float[Array, "h w C"], factor: int, height: int, width: int) -> Float[Array, "H W C"]:
    """Read a `1/factor` resolution image back at `height x width` bilinearly, clamp-to-edge.

    Full-resolution pixel centre `x` reads low-resolution position `x / factor`,
    the inverse of `downsample_box`'s block layout.
    """
    check_image(image)
    _check_factor(factor)
    dtype = image.dtype
    ys = (jnp.arange(height, dtype=dtype) + 0.5) / factor
    xs = (jnp.arange(width, dtype=dtype) + 0.5) / factor
    return sample_separable(image, xs, ys)
