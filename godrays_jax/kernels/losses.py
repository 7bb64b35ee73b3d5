"""Image losses for fitting effects to reference frames.

Every loss compares `image` with `target` (both linear HDR `(H, W, C)`) after
mapping both into a comparison `space`:

- `"display"` (the default): `x / (1 + |x|)` per channel (Reinhard). A visible
  sun is thousands of times brighter than the rest of an HDR frame; in linear
  space its few pixels drown every other difference, in display space each
  pixel counts about as much as it does on a screen. Values land in [0, 1)
  for non-negative input.
- `"linear"`: the values as they are.

Losses are differentiable everywhere (finite gradients also on constant or
black images), return float scalars, and run under `jit`, `vmap` and `grad`.
"""

from typing import Literal

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from godrays_jax.primitives.checks import check_image
from godrays_jax.primitives.color import display_map

Space = Literal["display", "linear"]
SPACES: tuple[str, ...] = ("display", "linear")


def check_space(space) -> None:
    """Raise `ValueError` naming `space` unless it is one of `SPACES`."""
    if space not in SPACES:
        raise ValueError(f"space must be one of {', '.join(SPACES)}; got {space!r}")


def to_space(image: Float[Array, "H W C"], space: Space = "display") -> Float[Array, "H W C"]:
    """Map a linear image into a comparison space (see the module docstring)."""
    check_space(space)
    return display_map(image) if space == "display" else image


def _pair(image, target, space):
    check_image(image)
    check_image(target, "target")
    if jnp.shape(image) != jnp.shape(target):
        raise ValueError(f"target must have the image's shape {jnp.shape(image)}, got {jnp.shape(target)}")
    return to_space(image, space), to_space(jnp.asarray(target, image.dtype), space)


def mse_loss(
    image: Float[Array, "H W C"], target: Float[ArrayLike, "H W C"], *, space: Space = "display"
) -> Float[Array, ""]:
    """Mean squared difference over pixels and channels, in `space`."""
    image, target = _pair(image, target, space)
    return jnp.mean((image - target) ** 2)


def l1_loss(
    image: Float[Array, "H W C"], target: Float[ArrayLike, "H W C"], *, space: Space = "display"
) -> Float[Array, ""]:
    """Mean absolute difference, in `space`. Its gradient is `sign(image - target)` (0 at equality)."""
    image, target = _pair(image, target, space)
    return jnp.mean(jnp.abs(image - target))


def charbonnier_loss(
    image: Float[Array, "H W C"],
    target: Float[ArrayLike, "H W C"],
    *,
    space: Space = "display",
    epsilon: float = 1e-3,
) -> Float[Array, ""]:
    """Mean of `sqrt(d**2 + epsilon**2) - epsilon`, `d = image - target` in `space`.

    A smooth L1: quadratic for `|d| << epsilon`, `|d|` beyond it, so a few
    outliers (Monte Carlo fireflies, a misplaced sun) weigh less than with MSE.
    `epsilon` is in the units of `space` (display values lie in [0, 1)).
    """
    if not epsilon > 0:
        raise ValueError(f"epsilon must be > 0, got {epsilon!r}")
    image, target = _pair(image, target, space)
    return jnp.mean(jnp.sqrt((image - target) ** 2 + epsilon**2) - epsilon)


SSIM_SIGMA = 1.5
"""Gaussian window of Wang et al. (2004): sigma 1.5 pixels, truncated at 3.5 sigma (11 taps)."""


def _gaussian_window() -> np.ndarray:
    radius = int(3.5 * SSIM_SIGMA + 0.5)
    taps = np.arange(-radius, radius + 1, dtype=np.float64)
    window = np.exp(-0.5 * (taps / SSIM_SIGMA) ** 2)
    return window / window.sum()


def _valid_band(length: int, window: np.ndarray) -> np.ndarray:
    """`(length - taps + 1, length)` matrix whose product with a signal is its valid correlation with `window`."""
    outputs = length - window.shape[0] + 1
    band = np.zeros((outputs, length))
    for k, weight in enumerate(window):
        band[np.arange(outputs), np.arange(outputs) + k] = weight
    return band


def _filter_valid(image, rows_band, cols_band):
    """Separable filtering keeping only pixels whose window lies inside the image (two matrix products)."""
    return jnp.einsum("sw,rwc->rsc", cols_band, jnp.einsum("rh,hwc->rwc", rows_band, image, precision="highest"), precision="highest")


def ssim(
    image: Float[Array, "H W C"],
    target: Float[ArrayLike, "H W C"],
    *,
    space: Space = "display",
    data_range: float = 1.0,
) -> Float[Array, ""]:
    """Mean structural similarity (Wang et al. 2004) over pixels and channels, in `space`.

    Gaussian window (`SSIM_SIGMA`), constants `K1 = 0.01`, `K2 = 0.03`, population
    covariances, averaged over the pixels whose 11x11 window lies inside the
    image (the border of 5 pixels is left out), channel by channel. This equals
    `skimage.metrics.structural_similarity(image, target, gaussian_weights=True,
    sigma=1.5, use_sample_covariance=False, data_range=data_range,
    channel_axis=-1)` on the mapped images. 1 for identical images; the
    constants keep it finite on flat or black images. Images must be at least
    11x11 pixels.

    Args:
        data_range: the span of values in `space` (1 for `"display"`).
    """
    image, target = _pair(image, target, space)
    window = _gaussian_window()
    if image.shape[0] < window.shape[0] or image.shape[1] < window.shape[0]:
        raise ValueError(f"image must be at least {window.shape[0]}x{window.shape[0]} pixels for SSIM, got {image.shape}")
    rows_band = jnp.asarray(_valid_band(image.shape[0], window), image.dtype)
    cols_band = jnp.asarray(_valid_band(image.shape[1], window), image.dtype)
    c1 = (0.01 * data_range) ** 2
    c2 = (0.03 * data_range) ** 2
    mean_x = _filter_valid(image, rows_band, cols_band)
    mean_y = _filter_valid(target, rows_band, cols_band)
    var_x = _filter_valid(image * image, rows_band, cols_band) - mean_x**2
    var_y = _filter_valid(target * target, rows_band, cols_band) - mean_y**2
    cov_xy = _filter_valid(image * target, rows_band, cols_band) - mean_x * mean_y
    similarity = ((2 * mean_x * mean_y + c1) * (2 * cov_xy + c2)) / (
        (mean_x**2 + mean_y**2 + c1) * (var_x + var_y + c2)
    )
    return jnp.mean(similarity)


def ssim_loss(
    image: Float[Array, "H W C"], target: Float[ArrayLike, "H W C"], *, space: Space = "display"
) -> Float[Array, ""]:
    """`1 - ssim(image, target)`: 0 for identical images, at most 2. `data_range` is 1 in display space.

    In `"linear"` space `data_range` is taken from the target (its max minus min, at least 1e-6).
    """
    data_range = 1.0
    if space == "linear":
        target_values = jnp.asarray(target)
        data_range = jnp.maximum(jnp.max(target_values) - jnp.min(target_values), 1e-6)
    return 1.0 - ssim(image, target, space=space, data_range=data_range)


LOSSES = {"mse": mse_loss, "l1": l1_loss, "charbonnier": charbonnier_loss, "ssim": ssim_loss}
"""Loss name -> `loss(image, target, *, space)`, the names `fit` and `godrays-jax fit` accept."""
