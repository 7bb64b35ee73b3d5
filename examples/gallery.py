"""Every preset applied to the hero frame: one PNG per preset and a labelled contact sheet.

    python examples/gallery.py [--frame FRAME.exr] [--docs | --out DIR]

Writes `out/gallery/<preset>.png` and `out/gallery/gallery.png` (or into
`--out DIR`); with `--docs` the contact sheet goes to `docs/images/gallery.png`
(the README's picture).
The default frame is `examples/data/forest_hero.exr` (rendered by
`make_hero_frame.py`), which carries the light and glow passes the seed-004
and seed-000 presets read. Runs from any directory.
"""

import argparse
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
from pictures import HERO_FRAME, contact_sheet, display, labelled, output_folder, resized, write_display

import godrays_jax as gr

COLUMNS = 3
TILE_WIDTH = 480


def make_gallery(frame: Path = HERO_FRAME, *, docs: bool = False, out: Path | None = None) -> None:
    """One PNG per preset in out/gallery/ (or `out`) and the labelled contact sheet (in docs/images/ with `docs`)."""
    buffers = gr.read_buffers(frame)
    light_xy, in_front = gr.read_light(frame)
    light = jnp.asarray(light_xy, jnp.float32)
    folder = output_folder(False, "gallery", out)
    tiles = [labelled(resized(display(buffers.color), TILE_WIDTH), "input frame (no effect)")]
    for name in sorted(gr.PRESETS):
        effect = gr.preset(name)
        if getattr(effect, "source", None) == "light_pass" and buffers.light_pass is None:
            print(f"skipped {name}: the frame has no light pass (render it with godrays-jax render)")
            continue
        image = eqx.filter_jit(lambda e, b, l: e(b, l, light_in_front=in_front))(effect, buffers, light)
        gr.write_image(folder / f"{name}.png", image)
        print(f"wrote {folder / (name + '.png')}")
        tiles.append(labelled(resized(display(image), TILE_WIDTH), f"{name} ({type(effect).__name__})"))
    write_display(output_folder(docs, "gallery", out) / "gallery.png", contact_sheet(tiles, COLUMNS))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frame", type=Path, default=HERO_FRAME, help="an EXR with colour, depth and the light's position")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--docs", action="store_true", help="write the contact sheet to docs/images/gallery.png")
    where.add_argument("--out", type=Path, help="folder for the pictures (default out/gallery/ at the repository root)")
    args = parser.parse_args()
    make_gallery(args.frame, docs=args.docs, out=args.out)


if __name__ == "__main__":
    main()
