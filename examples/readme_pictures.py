"""Regenerate every picture in the README.

    python examples/readme_pictures.py [--docs | --out DIR]

- `hero.png`: the hero frame (examples/data/forest_hero.exr) before and after
  the `gpu_gems` preset, as the README's main command makes it;
- `hidden_sun.png`: a sun fully hidden behind a box in haze (`hidden_sun.py`):
  a single-scattering reference, `VolumetricFog` with the reference's medium,
  `physically_based`, `participating_media` and `gpu_gems` (their layers);
- `plate.png`: a photograph without depth (the hero frame's colour as an
  8-bit PNG), the open sky `apply` finds in it, and `gpu_gems` on it;
- `gallery.png` (every preset on the hero frame, `gallery.py`) and
  `seed_scenes.png` (each article's scene with its preset, `render_seeds.py`).

Into `out/readme/` (the gallery and seed pictures into `out/gallery/` and
`out/seeds/`), all into `--out DIR`, or into `docs/images/` with `--docs`.
Runs from any directory.
"""

import argparse
import tempfile
from pathlib import Path

import equinox as eqx
import hidden_sun
import jax.numpy as jnp
import numpy as np
from gallery import make_gallery
from pictures import HERO_FRAME, apply_command, contact_sheet, display, labelled, output_folder, write_display
from render_seeds import make_seed_pictures

import godrays_jax as gr

HERO_PRESET = "gpu_gems"
HIDDEN_SUN_SIZE = (320, 180)
HIDDEN_SUN_PRESETS = ("physically_based", "participating_media", "gpu_gems")
"""The presets whose layers `hidden_sun.png` shows beside the reference and `VolumetricFog`, in this order."""


def make_hero(folder) -> None:
    """Before and after: the README's main command on the hero frame."""
    buffers = gr.read_buffers(HERO_FRAME)
    with tempfile.TemporaryDirectory() as scratch:
        after = gr.read_image(apply_command(HERO_FRAME, HERO_PRESET, Path(scratch) / "after.exr"))
    tiles = [labelled(display(buffers.color), "before: the rendered frame"),
             labelled(display(after), f"after: --preset {HERO_PRESET}")]  # fmt: skip
    write_display(folder / "hero.png", contact_sheet(tiles, 2))


def _ring_normalised(layer: np.ndarray, open_sky: np.ndarray, light_xy) -> np.ndarray:
    """A layer scaled so its mean over open sky 1.5-2.5 silhouette-radii from the light is 0.25 (shapes compare)."""
    height, width = layer.shape
    y, x = np.mgrid[0:height, 0:width] + 0.5
    radius = np.hypot(x - light_xy[0], y - light_xy[1])
    silhouette = radius[~open_sky].max()
    ring = open_sky & (radius > 1.5 * silhouette) & (radius < 2.5 * silhouette)
    return np.repeat((0.25 * layer / layer[ring].mean())[..., None], 3, axis=-1)


def make_hidden_sun(folder) -> None:
    """The hidden-sun box: reference halo against the presets' in-scattered light (each scaled to the same level)."""
    buffers, camera, light_xy, open_sky, _ = hidden_sun.render_frame(*HIDDEN_SUN_SIZE)
    layers = {"single-scattering reference": hidden_sun.single_scattering(camera)}
    # The reference's own medium and camera, no ambient light (the reference scatters the sun alone); surfaces
    # 0.3 of their depth deep and 128 shadow samples, so the march toward the hidden sun does not step over the box.
    medium = gr.Medium(extinction=hidden_sun.EXTINCTION, anisotropy=hidden_sun.ANISOTROPY,
                       max_distance=hidden_sun.MEDIUM_RADIUS, light_color=(1.0, 1.0, 1.0), ambient_color=(0.0, 0.0, 0.0))
    volumetric = gr.VolumetricFog(medium=medium, fov_x_deg=camera.fov_x_deg, thickness=0.3, num_shadow_samples=128)
    effects = {"VolumetricFog, the reference's medium": volumetric}
    effects |= {f"{name} ({type(gr.preset(name)).__name__})": gr.preset(name) for name in HIDDEN_SUN_PRESETS}
    for name, effect in effects.items():
        layer = eqx.filter_jit(lambda e, b, l: e.layer(b, l))(effect, buffers, jnp.asarray(light_xy))
        layers[name] = np.asarray(layer)[..., :3].mean(-1)
    tiles = [labelled(display(buffers.color), "the frame: a box hides the sun")]
    tiles += [labelled(display(_ring_normalised(layer, open_sky, light_xy)), name) for name, layer in layers.items()]
    write_display(folder / "hidden_sun.png", contact_sheet(tiles, 3))


def make_plate(folder) -> None:
    """A preset on a frame without depth: what `godrays-jax apply photo.png --light X,Y --preset gpu_gems` does."""
    buffers = gr.read_buffers(HERO_FRAME)
    light_xy, _ = gr.read_light(HERO_FRAME)
    with tempfile.TemporaryDirectory() as scratch:
        photo_path = Path(scratch) / "photo.png"
        gr.write_image(photo_path, buffers.color, dither_seed=0)  # sRGB, 8 bits: a photograph, no depth, no alpha
        photo = gr.read_buffers(photo_path, without_depth=True)
        plate = gr.buffers_without_depth(photo.color, light_xy, alpha=photo.coverage)
        light = f"{light_xy[0]},{light_xy[1]}"
        after = gr.read_image(apply_command(photo_path, HERO_PRESET, Path(scratch) / "after.exr", "--light", light))
    tiles = [labelled(display(photo.color), "a photograph: no depth, no alpha"),
             labelled(display(np.repeat(1.0 - np.asarray(plate.coverage)[..., None], 3, axis=-1)), "the open sky found around the light"),
             labelled(display(after), f"--preset {HERO_PRESET} on it")]  # fmt: skip
    write_display(folder / "plate.png", contact_sheet(tiles, 3))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--docs", action="store_true", help="write the pictures to docs/images/")
    where.add_argument("--out", type=Path, help="one folder for every picture (default out/<kind>/ at the repository root)")
    args = parser.parse_args()
    folder = output_folder(args.docs, "readme", args.out)
    make_hero(folder)
    make_hidden_sun(folder)
    make_plate(folder)
    make_gallery(docs=args.docs, out=args.out)
    make_seed_pictures(docs=args.docs, out=args.out)


if __name__ == "__main__":
    main()
