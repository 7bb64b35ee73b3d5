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

from pictures import HERO_FRAME, apply_command, contact_sheet, display, labelled, output_folder, resized, write_display

import godrays_jax as gr

COLUMNS = 3
TILE_WIDTH = 480


def make_gallery(frame: Path = HERO_FRAME, *, docs: bool = False, out: Path | None = None) -> None:
    """One PNG per preset in out/gallery/ (or `out`) and the labelled contact sheet (in docs/images/ with `docs`).

    Each PNG is `godrays-jax apply FRAME --preset NAME -o NAME.png`, so the
    gallery shows what the command makes: the frame's light, its distance and
    camera from the header, the disc emitter where the frame has no light pass.
    """
    buffers = gr.read_buffers(frame)
    folder = output_folder(False, "gallery", out)
    tiles = [labelled(resized(display(buffers.color), TILE_WIDTH), "input frame (no effect)")]
    for name in sorted(gr.PRESETS):
        picture = apply_command(frame, name, folder / f"{name}.png")
        print(f"wrote {picture}")
        label = f"{name} ({type(gr.preset(name)).__name__})"
        tiles.append(labelled(resized(display(gr.read_image(picture)), TILE_WIDTH), label))
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
