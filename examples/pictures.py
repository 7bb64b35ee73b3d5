"""What the example scripts share: where pictures go, display encoding, labels and contact sheets.

Every path is relative to this file, so the scripts run from any directory.
Pictures go to `out/` at the repository root unless a script is given
`--docs`, which writes the README's pictures in `docs/images/`, or `--out DIR`.
"""

from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from godrays_jax.app.cli import main as godrays_jax_command

ROOT = Path(__file__).resolve().parents[1]
HERO_FRAME = ROOT / "examples" / "data" / "forest_hero.exr"
DOCS_IMAGES = ROOT / "docs" / "images"
LABEL_HEIGHT = 24
LABEL_SIZE = 16


def output_folder(docs: bool, name: str, out: Path | None = None) -> Path:
    """`docs/images/` with `--docs`, else `out` if given, else `out/<name>/` at the repository root; created if missing."""
    folder = DOCS_IMAGES if docs else out if out is not None else ROOT / "out" / name
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def display(image) -> np.ndarray:
    """Linear HDR -> sRGB-encoded [0, 1] RGB, as `write_image` encodes PNGs."""
    linear = np.clip(np.asarray(image[..., :3], np.float32), 0.0, 1.0)
    return np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear ** (1 / 2.4) - 0.055)


def resized(tile: np.ndarray, width: int) -> np.ndarray:
    """A display tile resized to `width` pixels (aspect kept; OpenImageIO's filtered resize)."""
    height = round(tile.shape[0] * width / tile.shape[1])
    source = oiio.ImageBuf(np.ascontiguousarray(tile, np.float32))
    return oiio.ImageBufAlgo.resize(source, roi=oiio.ROI(0, width, 0, height, 0, 1, 0, 3)).get_pixels(oiio.FLOAT)


def labelled(tile: np.ndarray, label: str) -> np.ndarray:
    """The tile under a black strip with `label` in OpenImageIO's built-in font."""
    height, width, _ = tile.shape
    canvas = oiio.ImageBuf(oiio.ImageSpec(width, height + LABEL_HEIGHT, 3, oiio.FLOAT))
    canvas.set_pixels(oiio.ROI(0, width, LABEL_HEIGHT, height + LABEL_HEIGHT), np.ascontiguousarray(tile, np.float32))
    oiio.ImageBufAlgo.render_text(canvas, 6, LABEL_HEIGHT - 7, label, LABEL_SIZE, "", (1.0, 1.0, 1.0))
    return canvas.get_pixels(oiio.FLOAT)


def contact_sheet(tiles: list[np.ndarray], columns: int) -> np.ndarray:
    """Tiles of one size in rows of `columns`, the last row padded with black."""
    tiles = tiles + [np.zeros_like(tiles[0])] * (-len(tiles) % columns)
    rows = [np.concatenate(tiles[i : i + columns], axis=1) for i in range(0, len(tiles), columns)]
    return np.concatenate(rows, axis=0)


def write_display(path: Path, picture: np.ndarray) -> None:
    """Write display-encoded pixels as an 8-bit PNG (through a temporary file, so no partial picture is left)."""
    temporary = path.with_name(f".{path.name}.tmp.png")
    if not oiio.ImageBuf(np.ascontiguousarray(picture, np.float32)).write(str(temporary), oiio.UINT8):
        raise OSError(f"cannot write {temporary}")
    temporary.replace(path)
    print(f"wrote {path}")


def apply_command(frame: Path, preset: str, output: Path, *options: str) -> Path:
    """Run `godrays-jax apply FRAME --preset PRESET -o OUTPUT [options]`: pictures show what the command makes.

    In this process (the command's own entry point), so a script that applies every preset starts JAX once.
    """
    if godrays_jax_command(["apply", str(frame), "--preset", preset, "-o", str(output), *options]) != 0:
        raise RuntimeError(f"godrays-jax apply {frame} --preset {preset} failed (its message is above)")
    return output
