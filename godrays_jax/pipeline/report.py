"""The picture of a fit (target, fitted frame, their difference and the loss curve, labelled) and its metrics."""

import math
from collections.abc import Sequence

import numpy as np
import OpenImageIO as oiio
import skimage.metrics
from jaxtyping import ArrayLike, Float

from godrays_jax.primitives.color import display_map, srgb_decode

_PANEL_WIDTH = 320
"""Panels narrower than this are enlarged (nearest pixel, integer factor) so their labels stay legible."""

_TITLE = 26
_BAR = 46
_TEXT = 15
_SMALL = 12
_BACKGROUND = 0.13
_INK = (0.92, 0.92, 0.92)
_CURVE = (0.35, 0.65, 1.0)
_SMALLEST_SCALE = 1.0 / 255.0
"""The difference map's scale never drops below one 8-bit display step: a near-perfect fit stays dark."""


def _display_tile(image: np.ndarray, scale: int) -> np.ndarray:
    image = np.asarray(image, np.float32)[..., :3]
    if image.shape[-1] == 1:
        image = np.repeat(image, 3, axis=-1)
    return _enlarge(display_map(np.maximum(image, 0.0)), scale)


def _enlarge(tile: np.ndarray, scale: int) -> np.ndarray:
    return np.repeat(np.repeat(tile, scale, axis=0), scale, axis=1)


def _heat(values: np.ndarray) -> np.ndarray:
    """Black -> red -> yellow -> white for values in [0, 1]."""
    scaled = np.clip(values, 0.0, 1.0)[..., None] * 3.0
    return np.clip(scaled - np.array([0.0, 1.0, 2.0], np.float32), 0.0, 1.0)


class _Canvas:
    """An RGB picture in [0, 1] that NumPy paints and OpenImageIO letters (its bundled font), in float32 as
    `write_image` writes it: a report of a large frame is large, and NumPy's float64 took most of its time."""

    def __init__(self, height: int, width: int):
        self.pixels = np.full((height, width, 3), _BACKGROUND, np.float32)
        self.labels: list[tuple[int, int, str, int, str]] = []

    def paste(self, top: int, left: int, tile: np.ndarray) -> None:
        self.pixels[top : top + tile.shape[0], left : left + tile.shape[1]] = tile

    def text(self, x: int, baseline: int, text: str, *, size: int = _TEXT, align: str = "left") -> None:
        self.labels.append((x, baseline, text, size, align))

    def finished(self) -> np.ndarray:
        height, width = self.pixels.shape[:2]
        buffer = oiio.ImageBuf(oiio.ImageSpec(width, height, 3, oiio.FLOAT))
        buffer.set_pixels(oiio.ROI(), self.pixels)
        for x, baseline, text, size, align in self.labels:
            extent = oiio.ImageBufAlgo.text_size(text, size, "")
            shift = {"left": 0, "centre": extent.width // 2, "right": extent.width}[align]
            oiio.ImageBufAlgo.render_text(buffer, int(x - shift), int(baseline), text, size, "", _INK)
        return np.clip(buffer.get_pixels(oiio.FLOAT), 0.0, 1.0)


def _for_writing(picture: np.ndarray) -> np.ndarray:
    """The picture's display values as linear light: `write_image` sRGB-encodes them back to these values."""
    return srgb_decode(picture)


def _number(value: float) -> str:
    return f"{value:.2g}".replace("e-0", "e-").replace("e+0", "e")


def _colour_bar(canvas: _Canvas, top: int, left: int, width: int, scale: float) -> None:
    """A horizontal heat bar from 0 to `scale` with labelled ticks in the difference's own units."""
    margin = 12
    length = width - 2 * margin
    bar = _heat(np.linspace(0.0, 1.0, length))[None].repeat(10, axis=0)
    canvas.paste(top + 6, left + margin, bar)
    for fraction in (0.0, 0.25, 0.5, 0.75, 1.0):
        x = left + margin + round(fraction * (length - 1))
        canvas.pixels[top + 16 : top + 20, x] = _INK
        align = "left" if fraction == 0 else "right" if fraction == 1 else "centre"
        canvas.text(x, top + 33, _number(fraction * scale), size=_SMALL, align=align)


def _loss_plot(canvas: _Canvas, top: int, left: int, height: int, width: int, history: np.ndarray) -> None:
    """The loss per solver step on a log axis with decade ticks, its x axis in steps."""
    x0, x1, y0, y1 = left + 58, left + width - 16, top + 10, top + height - 34
    logs = np.log10(np.maximum(np.asarray(history, np.float64), 1e-30))
    low, high = math.floor(logs.min()), math.ceil(logs.max())
    high = max(high, low + 1)
    every = max(1, math.ceil((high - low) / 6))
    canvas.pixels[y0 : y1 + 1, x0] = canvas.pixels[y1, x0 : x1 + 1] = _INK
    for decade in range(low, high + 1, every):
        y = round(y1 - (decade - low) / (high - low) * (y1 - y0))
        canvas.pixels[y, x0 - 4 : x0] = _INK
        canvas.pixels[y, x0 + 1 : x1 + 1 : 4] = 0.35  # dotted grid line
        canvas.text(x0 - 7, y + 5, f"1e{decade}", size=_SMALL, align="right")
    steps = max(len(logs) - 1, 1)
    for step in sorted({0, steps // 2, steps}):
        x = round(x0 + step / steps * (x1 - x0))
        canvas.pixels[y1 + 1 : y1 + 5, x] = _INK
        canvas.text(x, y1 + 18, str(step), size=_SMALL, align="centre")
    canvas.text((x0 + x1) // 2, y1 + 31, "solver step", size=_SMALL, align="centre")
    xs = x0 + (x1 - x0) * (np.arange(len(logs)) / steps if len(logs) > 1 else np.zeros(1))
    ys = y1 - (logs - low) / (high - low) * (y1 - y0)
    dense = np.linspace(0.0, len(logs) - 1, 8 * width)
    px = np.rint(np.interp(dense, np.arange(len(logs)), xs)).astype(int)
    py = np.rint(np.interp(dense, np.arange(len(logs)), ys)).astype(int)
    for dy in (0, 1):
        canvas.pixels[np.clip(py + dy, y0, y1), px] = _CURVE
    for x, y in zip(np.rint(xs).astype(int), np.rint(ys).astype(int)):
        canvas.pixels[max(y - 2, y0) : y + 3, max(x - 2, x0) : x + 3] = _CURVE


def fit_report_image(
    target: Float[ArrayLike, "H W C"], fitted: Float[ArrayLike, "H W C"], loss_history: Sequence[float]
) -> Float[np.ndarray, "h w 3"]:
    """A labelled 2x2 picture of a fit: linear RGB in [0, 1] whose PNG (`write_image`) shows the panels below.

    Top: the target and the fitted frame in display space (`x / (1 + x)`).
    Bottom left: `|fitted - target|` in display space (mean over colour
    channels) as a heat map (black 0 -> red -> yellow -> white at the scale),
    with a colour bar in those absolute units; the scale is the largest
    difference but never less than one 8-bit step (1/255), so a near-perfect
    fit stays dark. Bottom right: the loss after every solver step on a log
    axis (decade ticks), step 0 the start. Every panel is titled. Frames
    narrower than 320 pixels are enlarged by an integer factor (nearest
    pixel) so the labels stay legible; the picture is `2 * (26 + h) + 46`
    pixels high and `2 * w + 8` wide for panels `h x w`.
    """
    height, width = np.shape(target)[:2]
    scale = max(1, math.ceil(_PANEL_WIDTH / width))
    target_tile, fitted_tile = _display_tile(target, scale), _display_tile(fitted, scale)
    ph, pw = target_tile.shape[:2]
    difference = np.abs(fitted_tile - target_tile).mean(axis=-1)
    top_scale = max(float(difference.max()), _SMALLEST_SCALE)
    gap = 8
    canvas = _Canvas(2 * (_TITLE + ph) + _BAR, 2 * pw + gap)
    right = pw + gap
    second = _TITLE + ph
    canvas.paste(_TITLE, 0, target_tile)
    canvas.paste(_TITLE, right, fitted_tile)
    canvas.paste(second + _TITLE, 0, _heat(difference / top_scale))
    _colour_bar(canvas, second + _TITLE + ph, 0, pw, top_scale)
    _loss_plot(canvas, second + _TITLE, right, ph + _BAR, pw, np.asarray(loss_history))
    for left, row, title in (
        (0, 0, "target"),
        (right, 0, "fitted"),
        (0, second, "|fitted - target|, display space"),
        (right, second, "loss (log scale)"),
    ):
        canvas.text(left + 6, row + 19, title)
    return _for_writing(canvas.finished())


def image_metrics(image: Float[ArrayLike, "H W C"], target: Float[ArrayLike, "H W C"]) -> tuple[float, float]:
    """`(PSNR in dB, SSIM)` of `image` against `target` in display space, SSIM by scikit-image.

    Both are linear HDR; their first `min(C, 3)` channels are clipped at 0 and
    mapped by `x / (1 + x)` into [0, 1) (`data_range=1`), then compared by
    PSNR (`10 log10(1 / MSE)`, as `skimage.metrics.peak_signal_noise_ratio`)
    and scikit-image's `structural_similarity` (Gaussian-weighted, sigma 1.5,
    per channel, in float32): an independent check of a fit's own loss. Identical images
    give `(inf, 1.0)`.
    """
    image, target = np.asarray(image, np.float64), np.asarray(target, np.float64)
    channels = min(image.shape[-1], target.shape[-1], 3)
    ours, theirs = (display_map(np.maximum(a[..., :channels], 0.0)) for a in (image, target))
    if np.array_equal(ours, theirs):
        return math.inf, 1.0
    # By its formula: skimage's `peak_signal_noise_ratio` imports scipy.stats, much of a repeated fit's start-up.
    psnr = 10.0 * math.log10(1.0 / np.mean((theirs - ours) ** 2))
    # In float32: its Gaussian filters take half the time of float64's on a large frame, the index the same to float32.
    ssim = skimage.metrics.structural_similarity(
        theirs.astype(np.float32), ours.astype(np.float32), data_range=1.0, channel_axis=-1, gaussian_weights=True,
        sigma=1.5, use_sample_covariance=False,
    )  # fmt: skip
    return float(psnr), float(ssim)
