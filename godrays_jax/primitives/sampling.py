"""Bilinear texture sampling at continuous pixel positions, as a GPU sampler does it.

Positions are pixel coordinates: x right, y down, pixel centres at `i + 0.5`, so
sampling at `(i + 0.5, j + 0.5)` returns pixel `(j, i)` exactly.
"""

from typing import Literal

import jax.numpy as jnp
from jax.typing import DTypeLike
from jaxtyping import Array, Float, Int

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
    flat = jnp.asarray(image).reshape(height * width, image.shape[2])

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


def axis_taps(size: int, u, addressing: Addressing):
    """Lower/upper texel indices and weights for linear interpolation at texel coordinates `u` (texel `i` at `u = i`)."""
    if addressing == "clamp":
        # Clamp-to-edge bilinear equals sampling the clamped coordinate.
        u = jnp.clip(u, 0.0, size - 1.0)
        low = jnp.clip(jnp.floor(u), 0.0, size - 1.0)
        fraction = u - low
        low = low.astype(jnp.int32)
        return low, jnp.minimum(low + 1, size - 1), 1.0 - fraction, fraction
    # Past one texel outside the image every tap is 0, so clipping there changes nothing.
    u = jnp.clip(u, -1.0, float(size))
    low = jnp.floor(u)
    fraction = u - low
    low = low.astype(jnp.int32)
    high = low + 1
    low_weight = jnp.where((low >= 0) & (low < size), 1.0 - fraction, 0.0)
    high_weight = jnp.where((high >= 0) & (high < size), fraction, 0.0)
    return jnp.clip(low, 0, size - 1), jnp.clip(high, 0, size - 1), low_weight, high_weight


def _lerp(values, axis: int, low, high, low_weight, high_weight):
    """`values[low] * low_weight + values[high] * high_weight` along `axis`; the indices are already in range."""
    index = (slice(None),) * axis
    shape = [1] * values.ndim
    shape[axis] = -1
    lower = values.at[index + (low,)].get(mode="promise_in_bounds")
    upper = values.at[index + (high,)].get(mode="promise_in_bounds")
    return lower * low_weight.reshape(shape) + upper * high_weight.reshape(shape)


def sample_separable(
    image: Float[Array, "H W C"],
    xs: Float[Array, " W2"],
    ys: Float[Array, " H2"],
    *,
    addressing: Addressing = "clamp",
) -> Float[Array, "H2 W2 C"]:
    """Bilinear samples on the grid `xs x ys`: `out[j, i] = sample_bilinear(image, xs[i], ys[j])`.

    Equal to `sample_bilinear` on that grid (bilinear interpolation is a tensor
    product), at the cost of two 1-D gathers instead of four per-pixel ones: the
    fast path for any warp that moves x and y independently (constant shifts,
    scaling about a point).
    """
    if addressing not in ("clamp", "zero"):
        raise ValueError(f"addressing must be 'clamp' or 'zero', got {addressing!r}")
    image = jnp.asarray(image)
    height, width, _ = image.shape
    rows = _lerp(image, 0, *axis_taps(height, ys - 0.5, addressing))
    return _lerp(rows, 1, *axis_taps(width, xs - 0.5, addressing))


def pixel_centres(height: int, width: int, dtype: DTypeLike = jnp.float32) -> tuple[Float[Array, "H W"], Float[Array, "H W"]]:
    """The `(x, y)` pixel-centre coordinates of an `height x width` image."""
    xs = jnp.arange(width, dtype=dtype) + 0.5
    ys = jnp.arange(height, dtype=dtype) + 0.5
    return jnp.broadcast_to(xs[None, :], (height, width)), jnp.broadcast_to(ys[:, None], (height, width))


def bilinear_corners(
    u: Float[Array, "*S"], v: Float[Array, "*S"], rows: int, cols: int
) -> tuple[Int[Array, "4 *S"], Int[Array, "4 *S"], Float[Array, "4 *S"]]:
    """The four samples around the continuous indices `(u, v)` (column, row; integers on samples) of a
    `rows x cols` grid, clamped at its borders: `(row, col, weight)`, each stacked along a new first axis of 4."""
    col0, row0 = jnp.floor(u), jnp.floor(v)
    fx, fy = u - col0, v - row0
    corners = [(dy, dx, wy * wx) for dy, wy in ((0, 1.0 - fy), (1, fy)) for dx, wx in ((0, 1.0 - fx), (1, fx))]
    row = jnp.stack([jnp.broadcast_to(jnp.clip(row0 + dy, 0, rows - 1), w.shape) for dy, _, w in corners])
    col = jnp.stack([jnp.broadcast_to(jnp.clip(col0 + dx, 0, cols - 1), w.shape) for _, dx, w in corners])
    return row.astype(jnp.int32), col.astype(jnp.int32), jnp.stack([w for _, _, w in corners])
