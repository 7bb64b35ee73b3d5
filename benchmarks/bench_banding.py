"""Banding of 8-bit outputs on a smooth glow, rounded and dithered: `python benchmarks/bench_banding.py [--docs]`.

The glow: a sun on a dark sky with a wide Gaussian halo (sigma 12 % of the width), 640x360, linear
float. It is written as PNG and JPEG by `write_image`, rounded to the nearest code and dithered
(`dither_seed`, what `apply` and `batch` write), read back, and compared with the float image in sRGB
codes:

- band error: the difference, blurred by a Gaussian of sigma 2 pixels (what the eye averages at a normal
  viewing distance: grain averages out, bands do not), RMS and maximum over the frame, in codes;
- grain: the RMS difference per pixel, in codes (dither trades bands for it);
- widest band: the longest run of one code along the row through the sun (pixels; rounding draws flat
  steps that many pixels wide, dither none).

`--docs` also writes docs/images/banding.png: a crop of the glow's falloff, rounded and dithered PNG,
contrast stretched 12x about its mean so the codes show.
"""

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter

import godrays_jax as gr
from godrays_jax.primitives.color import srgb_encode

ROOT = Path(__file__).resolve().parents[1]
HEIGHT, WIDTH = 360, 640
LIGHT = (320.0, 120.0)


def glow() -> np.ndarray:
    """A sun on a dark sky with a wide Gaussian halo (sigma 12 % of the width): smooth everywhere, dark at its rim."""
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH] + 0.5
    squared = (x - LIGHT[0]) ** 2 + (y - LIGHT[1]) ** 2
    disc = (squared <= 12.0**2)[..., None]
    halo = np.exp(-squared / (2 * (0.12 * WIDTH) ** 2))[..., None]
    sky = 0.004 + 0.002 * (y / HEIGHT)[..., None]
    tint = np.asarray([1.0, 0.8, 0.55])
    return (sky + 0.05 * halo * tint + 4.0 * disc * tint).astype(np.float32)


def codes(path: str) -> np.ndarray:
    return srgb_encode(np.asarray(gr.read_image(path), np.float64)) * 255


def measure(image: np.ndarray, folder: str) -> dict[str, dict[str, float]]:
    truth = srgb_encode(np.clip(image.astype(np.float64), 0, 1)) * 255
    rows = {}
    for name, ext, seed in (("PNG rounded", ".png", None), ("PNG dithered", ".png", 1),
                            ("JPEG rounded", ".jpg", None), ("JPEG dithered", ".jpg", 1)):  # fmt: skip
        path = os.path.join(folder, name.replace(" ", "_") + ext)
        gr.write_image(path, image, dither_seed=seed)
        written = codes(path)
        difference = written - truth
        banding = gaussian_filter(difference, sigma=(2, 2, 0))
        row = np.rint(written[int(LIGHT[1]), int(LIGHT[0]) + 20 :, 1])
        edges = np.flatnonzero(np.diff(row) != 0)
        runs = np.diff(np.concatenate([[-1], edges, [row.size - 1]]))
        rows[name] = {
            "band RMS": float(np.sqrt(np.mean(banding**2))),
            "band max": float(np.max(np.abs(banding))),
            "grain RMS": float(np.sqrt(np.mean(difference**2))),
            "widest band": float(np.max(runs)),
        }
    return rows


def figure(image: np.ndarray, folder: str, out: Path) -> None:
    """Rounded | dithered, a crop of the falloff right of the sun, stretched 12x about its mean code."""
    crop = (slice(100, 360), slice(380, 640))
    panels = []
    for seed in (None, 1):
        path = os.path.join(folder, f"figure_{seed}.png")
        gr.write_image(path, image, dither_seed=seed)
        panels.append(codes(path)[crop])
    mean = float(np.mean(panels[0]))
    stretched = [np.clip((panel - mean) * 12 + 128, 0, 255) / 255 for panel in panels]
    gap = np.ones((stretched[0].shape[0], 6, 3))
    sheet = np.concatenate([stretched[0], gap, stretched[1]], axis=1)
    gr.write_image(out, gr.srgb_decode(sheet.astype(np.float32)))  # these are display values already


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--docs", action="store_true", help="also write docs/images/banding.png")
    args = parser.parse_args()
    began = time.perf_counter()
    image = glow()
    with tempfile.TemporaryDirectory() as folder:
        rows = measure(image, folder)
        if args.docs:
            figure(image, folder, ROOT / "docs" / "images" / "banding.png")
    print(f"smooth glow ({WIDTH}x{HEIGHT}, a sun's wide halo on a dark sky), errors in 8-bit sRGB codes")
    print("| output | band error RMS | band error max | grain RMS | widest band (px) |")
    print("|---|---|---|---|---|")
    for name, row in rows.items():
        print(f"| {name} | {row['band RMS']:.3f} | {row['band max']:.3f} | {row['grain RMS']:.3f} | {row['widest band']:.0f} |")
    print(f"({time.perf_counter() - began:.1f} s)")


if __name__ == "__main__":
    main()
