"""The picture of a fit: target, fitted frame, their difference and the loss curve."""

from collections.abc import Sequence

import numpy as np
from jaxtyping import ArrayLike, Float

from godrays_jax.primitives.color import display_map


def _display_tile(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image, np.float64)[..., :3]
    if image.shape[-1] == 1:
        image = np.repeat(image, 3, axis=-1)
    return display_map(np.maximum(image, 0.0))


def _heat(values: np.ndarray) -> np.ndarray:
    """Black -> red -> yellow -> white for values in [0, 1]."""
    scaled = np.clip(values, 0.0, 1.0)[..., None] * 3.0
    return np.clip(scaled - np.array([0.0, 1.0, 2.0]), 0.0, 1.0)


def _curve_tile(history: np.ndarray, height: int, width: int) -> np.ndarray:
    """The loss curve (log scale) as a dark polyline on a light tile; axes span the history."""
    tile = np.full((height, width, 3), 0.9)
    margin = max(2, min(height, width) // 12)
    tile[margin:-margin, margin] = tile[height - margin - 1, margin:-margin] = 0.5  # axes
    logs = np.log10(np.maximum(np.asarray(history, np.float64), 1e-30))
    if logs.size < 2:
        logs = np.repeat(logs, 2)
    span = max(logs.max() - logs.min(), 1e-12)
    xs = margin + (width - 2 * margin - 1) * np.arange(logs.size) / (logs.size - 1)
    ys = margin + (height - 2 * margin - 1) * (logs.max() - logs) / span
    dense = np.linspace(0.0, logs.size - 1, 8 * width)
    px = np.rint(np.interp(dense, np.arange(logs.size), xs)).astype(int)
    py = np.rint(np.interp(dense, np.arange(logs.size), ys)).astype(int)
    for dy in (0, 1):
        tile[np.clip(py + dy, 0, height - 1), px] = (0.1, 0.2, 0.7)
    return tile


def fit_report_image(
    target: Float[ArrayLike, "H W C"], fitted: Float[ArrayLike, "H W C"], loss_history: Sequence[float]
) -> Float[np.ndarray, "2H 2W 3"]:
    """A 2x2 picture of a fit, in display space (`x / (1 + x)`), values in [0, 1].

    Top left the target, top right the fitted frame, bottom left the absolute
    difference as a heat map (black 0, white the largest difference), bottom
    right the loss history on a log scale (left to right: steps).
    """
    target_tile = _display_tile(target)
    fitted_tile = _display_tile(fitted)
    difference = np.abs(fitted_tile - target_tile).mean(axis=-1)
    difference_tile = _heat(difference / max(difference.max(), 1e-12))
    height, width = target_tile.shape[:2]
    curve = _curve_tile(np.asarray(loss_history), height, width)
    return np.concatenate(
        [np.concatenate([target_tile, fitted_tile], axis=1), np.concatenate([difference_tile, curve], axis=1)], axis=0
    )


