"""Render each source article's example scene and compose it with that article's preset.

    python examples/render_seeds.py [OUTPUT_FOLDER]   (default examples/output/)

For every scene in examples/scenes/ it writes `<name>_render.png` (the raw
render), `<name>_<preset>.png` (the render with the seed's effect) and, for
seed 000, `<name>_glow_pass.png` (the overcast pass itself).
"""

import sys
from pathlib import Path

import jax.numpy as jnp

from godrays_jax.effects.presets import preset
from godrays_jax.primitives.io import write_image
from godrays_jax.raster import light_pixel, load_scene, render

SCENES = Path(__file__).parent / "scenes"
# scene file -> the preset of the article it reproduces
PRESET_OF_SCENE = {
    "solar_system_000": "sun_overcast",
    "planet_001": "vbex_bloom",
    "occluders_002": "kbengine_flares",
    "crepuscular_003": "xna_crepuscular",
    "galaxy_004": "galaxy_vls",
}


def main(output: Path) -> None:
    output.mkdir(parents=True, exist_ok=True)
    for name, preset_name in PRESET_OF_SCENE.items():
        scene, camera = load_scene(SCENES / f"{name}.json")
        buffers = render(scene, camera)
        light_xy, _, in_front = light_pixel(scene, camera)
        write_image(output / f"{name}_render.png", buffers.color)
        if name.endswith("000"):
            write_image(output / f"{name}_glow_pass.png", buffers.glow_pass)
        composed = preset(preset_name)(buffers, jnp.asarray(light_xy), light_in_front=bool(in_front))
        write_image(output / f"{name}_{preset_name}.png", composed)
        print(f"{name}: light at ({float(light_xy[0]):.1f}, {float(light_xy[1]):.1f}) px, wrote {output}/{name}_*.png", flush=True)


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).parent / "output")
