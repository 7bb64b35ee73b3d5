"""Blurs: the sun-overcasting article's 12-tap Poisson-disk blur, a separable Gaussian, the VBex article's bloom pyramid.

All use clamp-to-edge addressing, so a constant image stays constant.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from godrays_jax.primitives.checks import (
    check_image,
    check_scalar,
    checked_count,
    is_static_int,
    resolve_count,
)
from godrays_jax.primitives.sampling import sample_separable

POISSON_OFFSETS = np.array(
    [
        [-0.326212, -0.405805],
        [-0.840144, -0.073580],
        [-0.695914, 0.457137],
        [-0.203345, 0.620716],
        [0.962340, -0.194983],
        [0.473434, -0.480026],
        [0.519456, 0.767022],
        [0.185461, -0.893124],
        [0.507431, 0.064425],
        [0.896420, 0.412458],
        [-0.321940, -0.932615],
        [-0.791559, -0.597705],
    ]
)
"""The sun-overcasting article's 12 Poisson-disk offsets, in UV units before scaling by `blur_power`."""


@jax.jit  # called eagerly, the loop over a function defined in the call would compile again every call
def _poisson_pass(image, blur_power):
    height, width, _ = image.shape
    xs = jnp.arange(width, dtype=image.dtype) + 0.5
    ys = jnp.arange(height, dtype=image.dtype) + 0.5
    offsets = jnp.asarray(POISSON_OFFSETS, image.dtype) * blur_power * jnp.asarray([width, height], image.dtype)

    # A loop, not 12 unrolled taps: as fast to run, and its gradient compiles
    # much faster (XLA's CPU compile time grows steeply with unrolled scatters).
    def add_tap(k, total):
        return total + sample_separable(image, xs + offsets[k, 0], ys + offsets[k, 1])

    return jax.lax.fori_loop(0, len(POISSON_OFFSETS), add_tap, image) / 13.0


def poisson_blur(
    image: Float[Array, "H W C"],
    *,
    blur_power: Float[ArrayLike, ""],
    num_passes: int | Float[ArrayLike, ""] = 1,
    max_passes: int | None = None,
) -> Float[Array, "H W C"]:
    """The sun-overcasting article's blur: the centre tap plus 12 Poisson-disk taps, summed and divided by 13.

    Tap `i` reads the image at `p + offsets[i] * blur_power * (W, H)` pixels: the
    offsets are in UV units, so `blur_power = 0.01` reaches about 1 % of the
    image's width and height. Bilinear, clamp-to-edge.

    Args:
        image: the image to blur.
        blur_power: tap radius in UV units; 0 returns the image unchanged.
        num_passes: how many times to apply the blur (the sun-overcasting article uses 2). A Python
            int >= 0 is exact. A float `p` is the relaxation
            `(1 - f) * blur^k(image) + f * blur^(k+1)(image)` with `k = floor(p)`,
            `f = p - k`: the piecewise-linear interpolation between whole pass
            counts, equal to the exact blur at integers.
        max_passes: static upper bound for a relaxed `num_passes`.
    """
    check_image(image)
    check_scalar(blur_power, "blur_power")
    blur_power = jnp.asarray(blur_power, image.dtype)
    loop_length, relaxed = resolve_count(num_passes, max_passes, "num_passes", "max_passes", minimum=0)
    # The barrier makes XLA materialise each pass: fused into the next pass's
    # gathers it would be recomputed for every tap.
    # A Python loop, not fori_loop: XLA's CPU while loop runs these gathers far slower.
    count = checked_count(num_passes, loop_length, "num_passes", "max_passes", image.dtype) if relaxed else None
    blurred = image
    total = jnp.clip(1.0 - jnp.abs(count), 0.0, 1.0) * image if relaxed else None
    for k in range(1, loop_length + 1):
        blurred = jax.lax.optimization_barrier(_poisson_pass(blurred, blur_power))
        if relaxed:
            total = total + jnp.clip(1.0 - jnp.abs(count - k), 0.0, 1.0) * blurred
    return total if relaxed else blurred


def gaussian_blur(
    image: Float[Array, "H W C"],
    *,
    sigma: Float[ArrayLike, ""],
    reach: int | None = None,
) -> Float[Array, "H W C"]:
    """Separable Gaussian blur, `sigma` in pixels, clamp-to-edge.

    The kernel has `2 * reach + 1` taps per axis, normalised to sum 1, so a
    constant image stays constant. `reach` defaults to `ceil(3 * sigma)` when
    `sigma` is a Python number and must be given when it is traced (fitted).
    `sigma` near 0 returns the image unchanged.
    """
    check_image(image)
    check_scalar(sigma, "sigma")
    if reach is None:
        if not isinstance(sigma, (int, float)) or isinstance(sigma, bool):
            raise ValueError("reach must be given (a Python int) when sigma is an array or traced value")
        reach = max(1, math.ceil(3 * sigma))
    if not is_static_int(reach) or reach < 0:
        raise ValueError(f"reach must be a Python int >= 0, got {reach!r}")
    sigma = jnp.maximum(jnp.asarray(sigma, image.dtype), 1e-6)
    taps = jnp.arange(-reach, reach + 1, dtype=image.dtype)
    kernel = jnp.exp(-0.5 * (taps / sigma) ** 2)
    kernel = kernel / jnp.sum(kernel)

    channels = image.shape[2]

    # One depthwise convolution per axis: its gradient compiles in a fraction of
    # the time an unrolled sum of shifted slices takes on XLA's CPU backend.
    def blur_axis(values, axis):
        pad = [(0, 0)] * 3
        pad[axis] = (reach, reach)
        padded = jnp.pad(values, pad, mode="edge")[None]
        shape = [1, 1, 1, channels]
        shape[axis] = 2 * reach + 1
        weights = jnp.broadcast_to(kernel.reshape([-1 if i == axis else 1 for i in range(4)]), shape)
        return jax.lax.conv_general_dilated(
            padded, weights, (1, 1), "VALID", dimension_numbers=("NHWC", "HWIO", "NHWC"), feature_group_count=channels,
            precision="highest",
        )[0]

    return blur_axis(blur_axis(image, 0), 1)


def pooled_gaussian_matrices(size: int, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """A wide Gaussian along one axis of `size` pixels as two constant matrices, `pool` (`n x size`) and
    `read_back` (`size x n`), `n = ceil(size / factor)`, `factor = max(1, floor(sigma / 2))`.

    `pool` averages blocks of `factor` pixels (the last completed with the edge pixel, as `primitives.box_pool`)
    and blurs them with `gaussian_blur` of `sigma / factor` block widths (clamp-to-edge); `read_back` reads the
    blocks back bilinearly at each pixel's centre (`primitives.upsample_bilinear`). Along both axes,
    `read_back_h @ (pool_h @ X @ pool_w.T) @ read_back_w.T` is that blur of `X`: its cost does not grow with
    `sigma`, and as products of matrices its derivatives in every forward-mode lane are products too, where the
    same blur by gathers and a convolution costs each lane its own reads.
    """
    if not is_static_int(size) or size < 1:
        raise ValueError(f"size must be a Python int >= 1, got {size!r}")
    if not isinstance(sigma, (int, float)) or isinstance(sigma, bool) or not sigma > 0:
        raise ValueError(f"sigma must be a Python number > 0 (pixels), got {sigma!r}")
    factor = max(1, int(sigma // 2))
    blocks = -(-size // factor)
    average = np.zeros((blocks, size))
    for offset in range(factor):
        np.add.at(average, (np.arange(blocks), np.minimum(np.arange(blocks) * factor + offset, size - 1)), 1.0 / factor)
    low_sigma = sigma / factor
    reach = max(1, math.ceil(3 * low_sigma))
    taps = np.arange(-reach, reach + 1)
    weights = np.exp(-0.5 * (taps / low_sigma) ** 2)
    gaussian = np.zeros((blocks, blocks))
    for tap, weight in zip(taps, weights / weights.sum()):
        np.add.at(gaussian, (np.arange(blocks), np.clip(np.arange(blocks) + tap, 0, blocks - 1)), weight)
    position = (np.arange(size) + 0.5) / factor - 0.5
    left = np.floor(position)
    fraction = position - left
    read_back = np.zeros((size, blocks))
    for neighbour, weight in ((left, 1.0 - fraction), (left + 1, fraction)):
        np.add.at(read_back, (np.arange(size), np.clip(neighbour, 0, blocks - 1).astype(int)), weight)
    return gaussian @ average, read_back


BLOOM_LEVELS = (2, 4, 8, 16)
"""The VBex article's bloom pyramid: blurs at 1/2, 1/4, 1/8 and 1/16 of the full resolution."""


def bloom_level_shape(height: int, width: int, factor: int) -> tuple[int, int]:
    """A bloom level's render target: `Fullsize / factor` in whole pixels (`H // factor` x `W // factor`, at least 1)."""
    return max(1, height // factor), max(1, width // factor)


def draw_at_uv(image: Float[Array, "H W C"], height: int, width: int) -> Float[Array, "h w C"]:
    """`image` drawn into a `height x width` target: each target pixel reads it at its own UV, bilinearly, clamp.

    Target pixel `i` (centre `(i + 0.5) / width` in UV) reads `image` at
    position `(i + 0.5) / width * W` of its `W` pixels, as a full-screen quad
    with linear filtering does; halving a side of even length averages pixel pairs.
    """
    xs = (jnp.arange(width, dtype=image.dtype) + 0.5) * (image.shape[1] / width)
    ys = (jnp.arange(height, dtype=image.dtype) + 0.5) * (image.shape[0] / height)
    return sample_separable(image, xs, ys)


def bloom(
    image: Float[Array, "H W C"],
    *,
    threshold: Float[ArrayLike, ""] = 1.0,
    weights: Float[ArrayLike, "4"] = (1.0, 1.0, 1.0, 1.0),
    sigma: Float[ArrayLike, ""] = 2.0,
    reach: int = 6,
) -> Float[Array, "H W C"]:
    """The VBex article's bright glow: a bright pass, blurred at 1/2, 1/4, 1/8, 1/16 resolution, summed.

    Bright pass: `max(image - threshold, 0)` per channel, unclipped (HDR: a
    sun at 40 keeps its energy; the XNA crepuscular-rays article's clipped `bright_pass` is for LDR).
    Level `k` (factor `2, 4, 8, 16`, `BLOOM_LEVELS`) is a render target of
    whole pixels, `Fullsize / factor` (`bloom_level_shape`), drawn from the
    level before it (the first from the bright pass) by UV (`draw_at_uv`:
    each halving of an even side averages pixel pairs), blurred with a
    Gaussian of `sigma` pixels *of that level* (`gaussian_blur`, `reach`
    taps each side, static), and read back at full resolution by UV,
    bilinearly, clamp-to-edge. The output is `sum_k weights[k] * level_k`,
    no clipping; the VBex article adds the four levels with equal weights.
    Compare with one large Gaussian: `gaussian_blur(bright, sigma=sigma_px)`.
    """
    check_image(image)
    check_scalar(threshold, "threshold")
    check_scalar(sigma, "sigma")
    if np.shape(weights) != (len(BLOOM_LEVELS),):
        raise ValueError(f"weights must have shape ({len(BLOOM_LEVELS)},), one per level, got {np.shape(weights)}")
    dtype = image.dtype
    height, width = image.shape[0], image.shape[1]
    weights = jnp.asarray(weights, dtype)
    level = jnp.maximum(image - jnp.asarray(threshold, dtype), 0.0)
    total = jnp.zeros_like(image)
    for index, factor in enumerate(BLOOM_LEVELS):
        level = draw_at_uv(level, *bloom_level_shape(height, width, factor))
        low = gaussian_blur(level, sigma=sigma, reach=reach)
        total = total + weights[index] * draw_at_uv(low, height, width)
    return total
