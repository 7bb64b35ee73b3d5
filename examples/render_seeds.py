"""Render each source article's example scene and compose it with that article's preset.

    python examples/render_seeds.py [--docs | --out DIR]

For every seed scene in examples/scenes/ it writes `<scene>_<preset>.png` (the
render with the seed's effect), seed 000's glow pass, and `seed_scenes.png`, a
labelled contact sheet of them; into `out/seeds/`, `--out DIR`, or
`docs/images/` with `--docs` (the README's picture). Runs from any directory.
"""

import argparse
import dataclasses
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
from pictures import ROOT, contact_sheet, display, labelled, output_folder, write_display

import godrays_jax as gr

SCENES = ROOT / "examples" / "scenes"
# scene file -> the preset of the article it reproduces
PRESET_OF_SCENE = {
    "solar_system_000": "sun_overcast",
    "planet_001": "vbex_bloom",
    "occluders_002": "kbengine_flares",
    "crepuscular_003": "xna_crepuscular",
    "galaxy_004": "galaxy_vls",
}


def with_frame_camera(effect: gr.Effect, camera: gr.Camera) -> gr.Effect:
    """The effect told the frame's camera: its field of view and clip planes, where the effect reads them."""
    fields = {"fov_x_deg": camera.fov_x_deg, "near_plane": float(camera.near), "far_plane": float(camera.far)}
    return dataclasses.replace(effect, **{name: value for name, value in fields.items() if hasattr(effect, name)})


def make_seed_pictures(*, docs: bool = False, out: Path | None = None) -> None:
    """Every seed scene rendered and composed with its article's preset, and their contact sheet."""
    folder = output_folder(docs, "seeds", out)
    tiles = []
    for name, preset_name in PRESET_OF_SCENE.items():
        scene, camera = gr.load_scene(SCENES / f"{name}.json")
        buffers = gr.render(scene, camera)
        light_xy, _, in_front = gr.light_pixel(scene, camera)
        # The light's distance, as `render` stores it with a frame: the XNA depth test passes the sun's own pixels.
        light_depth = gr.light_distance(scene, camera)
        effect = with_frame_camera(gr.preset(preset_name), camera)
        compose = eqx.filter_jit(lambda e, b, l, front, depth: e(b, l, light_in_front=front, light_depth=depth))
        composed = compose(effect, buffers, jnp.asarray(light_xy), bool(in_front), light_depth)
        gr.write_image(folder / f"{name}_{preset_name}.png", composed)
        tiles.append(labelled(display(composed), f"{name}: {preset_name}"))
        if name == "solar_system_000":
            gr.write_image(folder / f"{name}_glow_pass.png", buffers.glow_pass)
            glow_pass = labelled(display(buffers.glow_pass), f"{name}: glow pass")
        light = f"({float(light_xy[0]):.1f}, {float(light_xy[1]):.1f})"
        print(f"{name}: light at {light} px, wrote {folder}/{name}_*.png", flush=True)
    write_display(folder / "seed_scenes.png", contact_sheet(tiles + [glow_pass], 3))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--docs", action="store_true", help="write the pictures to docs/images/")
    where.add_argument("--out", type=Path, help="folder for the pictures (default out/seeds/ at the repository root)")
    args = parser.parse_args()
    make_seed_pictures(docs=args.docs, out=args.out)


if __name__ == "__main__":
    main()
