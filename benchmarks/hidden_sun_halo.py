"""How each preset's halo compares with a single-scattering reference when a box hides the sun.

    python benchmarks/hidden_sun_halo.py [--size 160x90]

The scene (`examples/scenes/hidden_sun.json`), the NumPy reference and the
angular profile are `examples/hidden_sun.py` (the medium of
the path-traced colonnade frame). For every preset, the layer's mean per
angle about the light over open sky in a ring just outside the silhouette
(1-1.25 and 1.25-1.6 times its largest radius), divided by its mean, is
compared with the reference's: the RMS difference (0 = the same halo shape;
spikes from the silhouette's corners raise it). `tests/test_presets_look.py`
checks `physically_based` against the same measure.
"""

import argparse
import sys
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np

import godrays_jax as gr

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
import hidden_sun  # after its folder joins the path

RINGS = ((1.0, 1.25), (1.25, 1.6))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="160x90", help="WIDTHxHEIGHT")
    width, height = (int(v) for v in parser.parse_args().size.split("x"))
    buffers, camera, light_xy, open_sky, silhouette = hidden_sun.render_frame(width, height)
    reference = hidden_sun.single_scattering(camera)
    expected = [hidden_sun.angular_profile(reference, light_xy, open_sky, a * silhouette, b * silhouette) for a, b in RINGS]
    print(f"{width}x{height}, reference profile std {expected[0].std():.3f} / {expected[1].std():.3f}")
    print("| preset | RMS vs reference, 1-1.25 x silhouette | 1.25-1.6 x |")
    print("|---|---|---|")
    for name in sorted(gr.PRESETS):
        effect = gr.preset(name)
        if getattr(effect, "source", None) == "light_pass":
            print(f"| {name} | (its light pass is black: the sun is hidden) | |")
            continue
        layer = eqx.filter_jit(lambda e, b, l: e.layer(b, l))(effect, buffers, jnp.asarray(light_xy))
        layer = np.asarray(layer)[..., :3].mean(-1)
        if layer[open_sky].max() <= 0.0:
            print(f"| {name} | (no light on the open sky) | |")
            continue
        cells = []
        for (a, b), e in zip(RINGS, expected):
            profile = hidden_sun.angular_profile(layer, light_xy, open_sky, a * silhouette, b * silhouette)
            cells.append(f"{np.sqrt(np.mean((profile - e) ** 2)):.3f}" if np.isfinite(profile).all() else "(no light here)")
        print(f"| {name} | {cells[0]} | {cells[1]} |")


if __name__ == "__main__":
    main()
