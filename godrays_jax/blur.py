"""Blurs: seed 000's 12-tap Poisson-disk blur and a separable Gaussian.

Both use clamp-to-edge addressing, so a constant image stays constant.
"""

import math

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from godrays_jax._checks import checked_count, check_image, check_scalar, is_static_int, resolve_count
from godrays_jax.sampling import pixel_centres, sample_bilinear

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
"""Seed 000's 12 Poisson-disk offsets, in UV units before scaling by `blur_power`."""


def _poisson_pass(image, blur_power):
    height, width, _ = image.shape
    x, y = pixel_centres(height, width, image.dtype)
    total = image
    for offset_u, offset_v in POISSON_OFFSETS:
        total = total + sample_bilinear(
            image, x + offset_u * blur_power * width, y + offset_v * blur_power * height
        )
    return total / 13.0


def poisson_blur(
    image: Float[Array, "H W C"],
    blur_power: Float[ArrayLike, ""],
    *,
    passes: int | Float[ArrayLike, ""] = 1,
    max_passes: int | None = None,
) -> Float[Array, "H W C"]:
    """Seed 000's blur: the centre tap plus 12 Poisson-disk taps, summed and divided by 13.

    Tap `i` reads the image at `p + offsets[i] * blur_power * (W, H)` pixels: the
    offsets are in UV units, so `blur_power = 0.01` reaches about 1 % of the
    image's width and height. Bilinear, clamp-to-edge.

    Args:
        image: the image to blur.
        blur_power: tap radius in UV units; 0 returns the image unchanged.
        passes: how many times to apply the blur (seed 000 uses 2). A Python
            int >= 0 is exact. A float `p` is the relaxation
            `(1 - f) * blur^k(image) + f * blur^(k+1)(image)` with `k = floor(p)`,
            `f = p - k`: the piecewise-linear interpolation between whole pass
            counts, equal to the exact blur at integers.
        max_passes: static upper bound for a relaxed `passes`.
    """
    check_image(image)
    check_scalar(blur_power, "blur_power")
    blur_power = jnp.asarray(blur_power, image.dtype)
    loop_length, relaxed = resolve_count(passes, max_passes, "passes", "max_passes", minimum=0)
    if not relaxed:
        for _ in range(loop_length):
            image = _poisson_pass(image, blur_power)
        return image
    count = checked_count(passes, loop_length, "passes", "max_passes", image.dtype)
    blurred = image
    total = jnp.clip(1.0 - jnp.abs(count), 0.0, 1.0) * image
    for k in range(1, loop_length + 1):
        blurred = _poisson_pass(blurred, blur_power)
        total = total + jnp.clip(1.0 - jnp.abs(count - k), 0.0, 1.0) * blurred
    return total


def gaussian_blur(
    image: Float[Array, "H W C"],
    sigma: Float[ArrayLike, ""],
    *,
    radius: int | None = None,
) -> Float[Array, "H W C"]:
    """Separable Gaussian blur, `sigma` in pixels, clamp-to-edge.

    The kernel has `2 * radius + 1` taps per axis, normalised to sum 1, so a
    constant image stays constant. `radius` defaults to `ceil(3 * sigma)` when
    `sigma` is a Python number and must be given when it is traced (fitted).
    `sigma` near 0 returns the image unchanged.
    """
    check_image(image)
    check_scalar(sigma, "sigma")
    if radius is None:
        if not isinstance(sigma, (int, float)) or isinstance(sigma, bool):
            raise ValueError("radius must be given (a Python int) when sigma is an array or traced value")
        radius = max(1, math.ceil(3 * sigma))
    if not is_static_int(radius) or radius < 0:
        raise ValueError(f"radius must be a Python int >= 0, got {radius!r}")
    sigma = jnp.maximum(jnp.asarray(sigma, image.dtype), 1e-6)
    taps = jnp.arange(-radius, radius + 1, dtype=image.dtype)
    kernel = jnp.exp(-0.5 * (taps / sigma) ** 2)
    kernel = kernel / jnp.sum(kernel)

    def blur_axis(values, axis):
        pad = [(0, 0)] * 3
        pad[axis] = (radius, radius)
        padded = jnp.pad(values, pad, mode="edge")
        length = values.shape[axis]
        total = jnp.zeros_like(values)
        for tap in range(2 * radius + 1):
            total = total + kernel[tap] * jnp.take(padded, jnp.arange(tap, tap + length), axis=axis)
        return total

    return blur_axis(blur_axis(image, 0), 1)
