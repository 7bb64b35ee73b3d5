"""Re-derive the `physically_based` preset: fit ScatteringFog to the path-traced colonnade fog frame.

    python benchmarks/fit_physically_based.py [--steps 60]

The reference frames live beside the checkout (`../shared/data/colonnade_*`,
Mitsuba 3, a homogeneous medium with sigma_t .02, albedo .95, g .8), so the
preset holds the fitted constants; this script starts from the
`participating_media` preset, fits every field but the camera's field of view,
the off-screen fade and the sample count at 32 samples, then again at 128
(the decay per sample rescaled to keep the reach), and prints the fitted values beside the
preset's, the losses (display-space MSE and SSIM) and the largest relative
difference. The preset is current when that difference is well under 1 %.
"""

import argparse
import json
import time
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np

import godrays_jax as gr
from godrays_jax.effects.fields import replace_fields
from godrays_jax.kernels.losses import mse_loss, ssim

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
SAMPLES = 128
COARSE_SAMPLES = 32
FIXED = ("fov_x_deg", "offscreen_fade", "num_samples")


def with_samples(effect: gr.ScatteringFog, samples: int) -> gr.ScatteringFog:
    """The same medium summed over `samples` steps: the decay per step rescaled so the shafts keep their reach."""
    decay = float(effect.decay) ** (float(effect.num_samples) / samples)
    return replace_fields(effect, {"decay": decay, "num_samples": float(samples), "max_samples": samples})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=60, help="most Levenberg-Marquardt steps")
    args = parser.parse_args()
    frame = gr.read_buffers(DATA / "colonnade_buffers.exr")
    fog = gr.read_image(DATA / "colonnade_fog.exr")[..., :3]
    scene = json.loads((DATA / "scenes.json").read_text())["colonnade"]
    light = jnp.asarray(scene["light_px"], jnp.float32)

    haze = eqx.tree_at(lambda e: e.fov_x_deg, gr.preset("participating_media"), jnp.asarray(float(scene["fov_x_deg"])))
    start = with_samples(haze, COARSE_SAMPLES)
    began = time.perf_counter()
    # 32 samples first (the sum is cheap and the valley shallow), then 128 from there.
    coarse = gr.fit(start, frame, light, fog, fixed=FIXED, max_steps=args.steps).effect
    result = gr.fit(with_samples(coarse, SAMPLES), frame, light, fog, fixed=FIXED, max_steps=args.steps)
    print(f"fit: {result.steps} steps at {SAMPLES} samples, {time.perf_counter() - began:.1f} s in all")

    fitted, baked = gr.effect_to_dict(result.effect), gr.effect_to_dict(gr.preset("physically_based"))
    worst = 0.0
    for name in result.fitted:
        new, old = np.asarray(fitted[name], float), np.asarray(baked[name], float)
        difference = float(np.max(np.abs(new - old) / np.maximum(np.abs(old), 1e-3)))
        worst = max(worst, difference)
        print(f"{name:15s} fitted {np.round(new, 5).tolist()}  preset {np.round(old, 5).tolist()}  ({100 * difference:.2f} %)")
    for label, effect in (("haze", start), ("fitted", result.effect), ("preset", gr.preset("physically_based"))):
        image = eqx.filter_jit(lambda e, b, l: e(b, l))(effect, frame, light)
        print(f"{label:7s} display MSE {float(mse_loss(image, fog)):.5f}  SSIM {float(ssim(image, fog)):.4f}")
    print(f"largest relative difference between the fit and the preset: {100 * worst:.2f} %")


if __name__ == "__main__":
    main()
