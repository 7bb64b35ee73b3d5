"""Render the sample frame through every preset: one PNG per preset and a labelled contact sheet.

    python examples/gallery.py [--frame examples/data/sample_frame.exr] [--out out/gallery]
                               [--sheet docs/images/gallery.png]

The frame carries colour, depth and coverage but no light pass, so for the
presets that read seed 004's pass (the light white, everything else black) it
is drawn here around the sun's disc (`SUN_RADIUS_PX`, the radius
`make_sample_frame.py` draws) where the sky shows.
Labels are drawn with OpenImageIO's built-in font (`ImageBufAlgo.render_text`).
"""

import argparse
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import OpenImageIO as oiio

import godrays_jax as gr

SUN_RADIUS_PX = 10.0
COLUMNS = 3
LABEL_HEIGHT = 22


def with_light_pass(buffers: gr.Buffers, light_xy) -> gr.Buffers:
    disc = gr.light_source_mask(buffers.height, buffers.width, light_xy, radius=SUN_RADIUS_PX * 2)[..., 0]
    light_pass = jnp.clip(disc * 4.0, 0.0, 1.0) * gr.coverage_mask(buffers.coverage)
    return eqx.tree_at(lambda b: b.light_pass, buffers, light_pass, is_leaf=lambda x: x is None)


def display(image) -> np.ndarray:
    """Linear HDR -> sRGB-encoded [0, 1], as `write_image` encodes PNGs."""
    linear = np.clip(np.asarray(image[..., :3], np.float32), 0.0, 1.0)
    return np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear ** (1 / 2.4) - 0.055)


def labelled(tile: np.ndarray, label: str) -> np.ndarray:
    height, width, _ = tile.shape
    canvas = oiio.ImageBuf(oiio.ImageSpec(width, height + LABEL_HEIGHT, 3, oiio.FLOAT))
    canvas.set_pixels(oiio.ROI(0, width, LABEL_HEIGHT, height + LABEL_HEIGHT), np.ascontiguousarray(tile))
    oiio.ImageBufAlgo.render_text(canvas, 6, LABEL_HEIGHT - 6, label, 15, "", (1.0, 1.0, 1.0))
    return canvas.get_pixels(oiio.FLOAT)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frame", default="examples/data/sample_frame.exr")
    parser.add_argument("--out", default="out/gallery", help="folder for one PNG per preset")
    parser.add_argument("--sheet", default="docs/images/gallery.png", help="the contact sheet PNG")
    args = parser.parse_args()

    buffers = gr.read_buffers(args.frame)
    light_xy, in_front = gr.read_light(args.frame)
    light = jnp.asarray(light_xy, jnp.float32)
    # Only effects that read seed 004's pass get it: SunOvercast would take it as its glow source.
    light_buffers = with_light_pass(buffers, light)
    Path(args.out).mkdir(parents=True, exist_ok=True)
    Path(args.sheet).parent.mkdir(parents=True, exist_ok=True)

    tiles = [labelled(display(buffers.color), "input frame")]
    for name in sorted(gr.PRESETS):
        effect = gr.preset(name)
        frame = light_buffers if getattr(effect, "source", None) == "light_pass" else buffers
        image = eqx.filter_jit(lambda e, b, l: e(b, l, light_in_front=in_front))(effect, frame, light)
        gr.write_image(Path(args.out) / f"{name}.png", image)
        tiles.append(labelled(display(image), f"{name} ({type(effect).__name__})"))
        print(f"wrote {Path(args.out) / (name + '.png')}")
    while len(tiles) % COLUMNS:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.concatenate(tiles[i : i + COLUMNS], axis=1) for i in range(0, len(tiles), COLUMNS)]
    sheet = np.concatenate(rows, axis=0)
    # The tiles are display-encoded already: write them as they are, not through write_image's sRGB encoding.
    temporary = Path(args.sheet).with_suffix(".tmp.png")
    oiio.ImageBuf(np.ascontiguousarray(sheet)).write(str(temporary), oiio.UINT8)
    temporary.replace(args.sheet)
    print(f"wrote {args.sheet}")


if __name__ == "__main__":
    main()
