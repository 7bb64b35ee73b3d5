"""`VolumetricFog` against the path-traced references, through the command line with its defaults.

    python benchmarks/fit_volumetric.py [SCENE ...] [--report DIR] [--jitter K] [--light-auto]

Per scene (`benchmarks/references/scenes.py`): `godrays-jax fit CLEAN FOG_A -o
params.json` (the default model, `VolumetricFog` from `volumetric_haze`; light,
its distance and the field of view from the frames' headers; the depth map seen
from the light, `SCENE_light_view.exr`, where the scene has one), then
`godrays-jax apply CLEAN --params params.json -o out.exr`; the display-space
MSE (`x / (1 + |x|)` per channel, the fit's loss) of `out.exr` against both
fog renders as ratios to the scene's noise floor, beside `ScatteringFog`'s
(`references/baseline.json`, the same commands on the previous default).
Robustness: `--starts` also fits from `physically_based` and `participating`
starts given as presets and prints the spread of the final losses. Rounding:
`--jitter K` also fits `K` copies of fog A, each times `1 + 2^-22 n` with `n`
standard normal noise of its own seed (a float32 rounding of the target, which
no render or loss can tell apart), and prints the ratios' range and mean: how
far a fit's end moves when nothing but rounding does, the yardstick for a change
that moves a scene's ratio a little. `--light-auto` also fits with the light found by `fit --light auto`
(none read from the headers) and prints its ratios and how far that light lies from the header's. Results go to `fit_volumetric.json` beside
this script; `uptime` is printed first (the machine is shared: times are wall
seconds under that load).
"""

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / "references"))
from baseline import display_mse, light_options, read_rgb  # noqa: E402  (the references' folder joins the path first)
from scenes import BY_NAME, HERE as REFERENCES, SCENES  # noqa: E402

RESULTS = HERE / "fit_volumetric.json"


def _run(*arguments: str, log: Path | None = None) -> float:
    start = time.perf_counter()
    done = subprocess.run(["godrays-jax", *arguments], check=True, capture_output=True, text=True)
    if log is not None:
        log.write_text(done.stdout)
    return time.perf_counter() - start


JITTER = 2.0**-22
"""`--jitter`'s relative noise on the target: a float32 rounding (its spacing is 2^-23 to 2^-24 of a value)."""


def fit_scene(
    scene, folder: Path, preset: str | None, report: Path | None, target: Path | None = None, light_auto: bool = False
) -> dict:
    """Fit `scene`'s fog A (or `target` in its place) and apply the fit: its ratios to the noise floor.
    `light_auto`: the light found by `fit --light auto` (which `apply --params` then reads), not given."""
    folder = folder if report is None else report  # the report's folder also keeps the parameters and the frame
    params, output = folder / f"{scene.name}_{preset or 'default'}.json", folder / f"{scene.name}.exr"
    options = ["--preset", preset] if preset else []
    if report is not None:
        options += ["--report", str(report / f"fit_report_{scene.name}.png")]
    light = [] if scene.renderer == "mitsuba" else light_options(scene)  # Blender's headers lack the light
    light = [] if light_auto else light
    # A scene whose shadows are cast from outside the frame ships the depth map seen from its light beside it.
    light_view = scene.clean.with_name(scene.clean.name.replace("_clean.exr", "_light_view.exr"))
    light += ["--light-view", str(light_view)] if light_view.exists() else []
    log = None if report is None else report / f"fit_{scene.name}.txt"  # what the command printed: steps, start
    target = scene.fog_a if target is None else target
    found = ["--light", "auto"] if light_auto else []
    seconds = _run("fit", str(scene.clean), str(target), "-o", str(params), *options, *light, *found, log=log)
    seconds += _run("apply", str(scene.clean), "--params", str(params), "-o", str(output), *light)
    fogged = read_rgb(output)
    return {
        "ratio_fog_a": display_mse(fogged, read_rgb(scene.fog_a)) / scene.noise_floor,
        "ratio_fog_b": display_mse(fogged, read_rgb(scene.fog_b)) / scene.noise_floor,
        "seconds": round(seconds, 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("scenes", nargs="*", help=f"default: all of {', '.join(BY_NAME)}")
    parser.add_argument("--starts", nargs="*", default=[], help="presets to fit from besides the default")
    parser.add_argument(
        "--report", type=Path, help="write each fit's report PNG, printed lines, parameters and fogged frame here"
    )
    parser.add_argument("--jitter", type=int, default=0, help="also fit this many copies of fog A at rounding noise")
    parser.add_argument(
        "--light-auto", action="store_true",
        help="also fit with the light found by fit --light auto (its ratios and the light's distance from the header's)",
    )  # fmt: skip
    args = parser.parse_args()
    print(subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip())
    scenes = [BY_NAME[name] for name in args.scenes] if args.scenes else list(SCENES)
    baseline = json.loads((REFERENCES / "baseline.json").read_text())
    results = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
    if args.report is not None:
        args.report.mkdir(parents=True, exist_ok=True)
    print("| scene | floor | ScatteringFog / floor (fog A, B) | VolumetricFog / floor (fog A, B) | seconds |")
    print("|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as folder:
        for scene in scenes:
            entry = fit_scene(scene, Path(folder), None, args.report)
            for preset in args.starts:
                entry[f"ratio_fog_a_from_{preset}"] = fit_scene(scene, Path(folder), preset, None)["ratio_fog_a"]
            jittered = [fit_scene(scene, Path(folder), None, None, _jittered(scene, seed, Path(folder)))
                        for seed in range(1, args.jitter + 1)]  # fmt: skip
            for fog in ("a", "b") if jittered else ():
                entry[f"ratio_fog_{fog}_jittered"] = [round(fit[f"ratio_fog_{fog}"], 4) for fit in jittered]
            if args.light_auto:
                auto = fit_scene(scene, Path(folder), None, None, light_auto=True)
                entry.update({f"{key}_light_auto": value for key, value in auto.items()})
                entry["light_auto_px_off"] = round(_light_off(scene, Path(folder)), 3)
            results[scene.name] = entry
            RESULTS.write_text(json.dumps(results, indent=1) + "\n")
            old = baseline.get(scene.name, {})
            before = f"{old['ratio_fog_a']:.2f}, {old['ratio_fog_b']:.2f}" if old else "not measured"
            print(f"| {scene.name} | {scene.noise_floor:.3g} | {before} | {entry['ratio_fog_a']:.2f}, "
                  f"{entry['ratio_fog_b']:.2f} | {entry['seconds']} |", flush=True)  # fmt: skip
            starts = [entry[key] for key in entry if key.startswith("ratio_fog_a_from_")]
            if starts:
                spread = (max([entry["ratio_fog_a"], *starts]) / min([entry["ratio_fog_a"], *starts]) - 1) * 100
                print(f"  from {', '.join(args.starts)}: {', '.join(f'{s:.3f}' for s in starts)}; spread {spread:.1f} %")
            if args.light_auto:
                print(f"  --light auto: {entry['ratio_fog_a_light_auto']:.2f}, {entry['ratio_fog_b_light_auto']:.2f}, "
                      f"the light {entry['light_auto_px_off']} px from the header's, "
                      f"{entry['seconds_light_auto']} s", flush=True)  # fmt: skip
            if jittered:
                ratios = [entry["ratio_fog_a"], *entry["ratio_fog_a_jittered"]]
                print(f"  fog A and {len(jittered)} roundings of it: {min(ratios):.3f}-{max(ratios):.3f}, "
                      f"mean {np.mean(ratios):.3f}", flush=True)  # fmt: skip


def _light_off(scene, folder: Path) -> float:
    """How far, in pixels, the light `--light auto` found for `scene` lies from the one its header stores."""
    found = json.loads((folder / f"{scene.name}_default.light.json").read_text())["lights"][0]["light_px"]
    return float(np.linalg.norm(np.subtract(found, scene.light_px)))


def _jittered(scene, seed: int, folder: Path) -> Path:
    """Fog A times `1 + JITTER n` (`n` standard normal noise of `seed`), written beside the fit's files."""
    import godrays_jax as gr
    from godrays_jax.app.options import read_target

    target = np.asarray(read_target(str(scene.fog_a)), np.float32)
    noise = np.random.default_rng(seed).standard_normal(target.shape).astype(np.float32)
    path = folder / f"{scene.name}_fog_a_jittered_{seed}.exr"
    gr.write_image(path, target * (1 + np.float32(JITTER) * noise))
    return path


if __name__ == "__main__":
    main()
