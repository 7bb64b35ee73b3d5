"""Fit every reference scene with `godrays-jax fit` and `apply --params` from one preset, as a user would.

    python benchmarks/references/baseline.py [SCENE ...] [--preset participating_media] [--pictures DIR]

Per scene: `godrays-jax fit CLEAN FOG_A --preset PRESET -o params.json`,
then `godrays-jax apply CLEAN --params params.json -o out.exr`, every other
option at its default; prints the display-space MSE
(`x / (1 + |x|)` per channel, the fit's loss) of `out.exr` against both fog
renders, each as a ratio to the scene's noise floor (`scenes.py`), and the
seconds the two commands took. Against FOG_B, which the fit never saw, a
perfect model scores 1. The default preset, `participating_media`
(`ScatteringFog`), was `fit`'s default start before `VolumetricFog`'s
(benchmarks/fit_volumetric.py measures that one): the figures, "today's
model", go to `baseline.json` (by scene, for `scenes.py`'s table). `--pictures DIR`: also each fit's report PNG and
parameters there.
"""

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

sys.path.insert(0, str(Path(__file__).resolve().parent))
from scenes import BY_NAME, HERE, SCENES  # noqa: E402  (this folder joins the path first)

RESULTS = HERE / "baseline.json"


def read_rgb(path: Path) -> np.ndarray:
    """The colour of an EXR, plain `R, G, B` or Blender's `*.Combined.R/G/B`, float64."""
    buffer = oiio.ImageBuf(str(path))
    names = buffer.spec().channelnames
    wanted = [n for c in "RGB" for n in names if n == c or n.endswith(f"Combined.{c}")]
    if len(wanted) != 3:
        raise ValueError(f"{path}: no single R, G, B layer among {names}")
    pixels = buffer.get_pixels(oiio.FLOAT)
    return pixels[..., [names.index(n) for n in wanted]].astype(np.float64)


def light_options(scene) -> list[str]:
    """`--light X,Y --light-depth D` from the scene's record, for frames whose header does not carry them
    (`X,Y,behind` for a light behind the camera; a scene of several lights, each, and their tints)."""
    if scene.lights:
        lights = scene.lights
        return ["--light", lights["lights"], "--light-depth", lights["lights_depth"], "--light-tint", lights["lights_tint"]]
    x, y = scene.light_px
    side = "" if scene.light_in_front else ",behind"
    return ["--light", f"{x:.4f},{y:.4f}{side}", "--light-depth", f"{scene.light_depth:g}"]


def display_mse(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.mean((a / (1 + np.abs(a)) - b / (1 + np.abs(b))) ** 2))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("scenes", nargs="*", help=f"default: all of {', '.join(BY_NAME)}")
    parser.add_argument("--preset", default="participating_media", help="the fit's start (default: %(default)s)")
    parser.add_argument("--pictures", type=Path, help="write each fit's report PNG here")
    args = parser.parse_args()
    scenes = [BY_NAME[name] for name in args.scenes] if args.scenes else list(SCENES)
    print("| scene | floor | MSE vs fog A | / floor | MSE vs fog B | / floor | fit + apply seconds |")
    print("|---|---|---|---|---|---|---|")
    for scene in scenes:
        with tempfile.TemporaryDirectory() as folder:
            params, out = Path(folder) / "params.json", Path(folder) / "out.exr"
            report = ["--report", str(args.pictures / f"{scene.name}_fit.png")] if args.pictures else []
            start = time.perf_counter()
            light = [] if scene.renderer == "mitsuba" else light_options(scene)  # Blender's headers lack it
            subprocess.run(["godrays-jax", "fit", str(scene.clean), str(scene.fog_a), "--preset", args.preset,
                            "-o", str(params), *report, *light], check=True, capture_output=True, text=True)
            subprocess.run(["godrays-jax", "apply", str(scene.clean), "--params", str(params), "-o", str(out), *light],
                           check=True, capture_output=True, text=True)
            seconds = time.perf_counter() - start
            fitted = read_rgb(out)
            if args.pictures:
                (args.pictures / f"{scene.name}_params.json").write_text(params.read_text())
        a, b = (display_mse(fitted, read_rgb(path)) for path in (scene.fog_a, scene.fog_b))
        floor = scene.noise_floor
        print(f"| {scene.name} | {floor:.3e} | {a:.3e} | {a / floor:.2f} | {b:.3e} | {b / floor:.2f} | {seconds:.0f} |",
              flush=True)
        results = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
        results[scene.name] = {"mse_fog_a": a, "mse_fog_b": b, "ratio_fog_a": a / floor, "ratio_fog_b": b / floor,
                               "seconds": round(seconds, 1)}
        RESULTS.write_text(json.dumps(dict(sorted(results.items())), indent=1) + "\n")


if __name__ == "__main__":
    main()
