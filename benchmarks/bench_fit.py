"""Fitting figures: gradient cost and memory, fit time, parameter recovery, the path-traced fog frame.

Run as a script (CPU here; no GPU is lent to this project's sessions):

    python benchmarks/bench_fit.py [--only grad,time,recovery,fog] [--out benchmarks/fit_results.md]

Timings are medians of repeated runs after a warm-up (compilation excluded);
memory is XLA's compiled temporary-buffer size (`memory_analysis()`), the
peak working set of one call beside its inputs and outputs.
"""

import argparse
import dataclasses
import json
import statistics
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import godrays_jax as gr
from godrays_jax.fit import fit
from godrays_jax.losses import mse_loss, ssim

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
SAMPLE = Path(__file__).resolve().parents[1] / "examples" / "data" / "sample_frame.exr"


def median_seconds(function, *args, repeats=3):
    jax.block_until_ready(function(*args))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(function(*args))
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def temp_mib(function, *args):
    return jax.jit(function).lower(*args).compile().memory_analysis().temp_size_in_bytes / 2**20


def resized(buffers, height, width):
    """Nearest-neighbour resize of a frame (enough for timing and memory)."""
    rows = np.arange(height) * buffers.height // height
    cols = np.arange(width) * buffers.width // width
    pick = lambda a: None if a is None else jnp.asarray(np.asarray(a)[rows][:, cols])  # noqa: E731
    return gr.Buffers(color=pick(buffers.color), depth=pick(buffers.depth), coverage=pick(buffers.coverage))


def colonnade():
    frame = gr.read_buffers(DATA / "colonnade_buffers.exr")
    fog = gr.read_image(DATA / "colonnade_fog.exr")[..., :3]
    light = jnp.asarray(json.loads((DATA / "scenes.json").read_text())["colonnade"]["light_px"], jnp.float32)
    return frame, fog, light


FITTED_RAYS = ("density", "decay", "exposure", "num_samples", "weight", "light_radius")


def bench_gradient(lines, sizes):
    """Forward vs value+gradient (reverse mode, forward-mode Jacobian) for GodRays's 6 parameters."""
    frame, fog, light = colonnade()
    lines += ["## Gradient cost and memory (GodRays, 128 samples, 6 parameters)", "",
              "| size | forward s | reverse value+grad s (ratio) | forward-mode value+Jacobian s (ratio) | temp MiB forward / reverse / forward-mode |",
              "|---|---|---|---|---|"]  # fmt: skip
    for height, width in sizes:
        buffers = resized(frame, height, width)
        target = jnp.asarray(resized(gr.Buffers(color=fog, depth=frame.depth, coverage=frame.coverage), height, width).color)
        scaled_light = light * jnp.array([width / 320, height / 180])
        effect = gr.GodRays(source="sky", num_samples=100.0, max_samples=128)
        values = {n: getattr(effect, n) for n in FITTED_RAYS}

        def render(values):
            return eqx.tree_at(lambda e: [getattr(e, n) for n in FITTED_RAYS], effect, [values[n] for n in FITTED_RAYS])(buffers, scaled_light)

        def loss(values):
            return mse_loss(render(values), target)

        def forward_mode(values):
            flat, unravel = jax.flatten_util.ravel_pytree(values)
            basis = jnp.eye(flat.size, dtype=flat.dtype)
            return jax.vmap(lambda d: jax.jvp(lambda f: loss(unravel(f)), (flat,), (d,)), out_axes=(None, 0))(basis)

        forward = median_seconds(jax.jit(loss), values)
        memory = [temp_mib(loss, values), temp_mib(jax.value_and_grad(loss), values), temp_mib(forward_mode, values)]
        reverse = "not run (memory)" if memory[1] > 8 * 1024 else median_seconds(jax.jit(jax.value_and_grad(loss)), values)
        fwd_mode = median_seconds(jax.jit(forward_mode), values)
        ratio = lambda t: t if isinstance(t, str) else f"{t:.2f} ({t / forward:.1f}x)"  # noqa: E731
        lines.append(f"| {width}x{height} | {forward:.3f} | {ratio(reverse)} | {ratio(fwd_mode)} | "
                     f"{memory[0]:.0f} / {memory[1]:.0f} / {memory[2]:.0f} |")  # fmt: skip
        print(lines[-1], flush=True)
    lines.append("")


def bench_fog(lines):
    """Every preset untuned against the fog frame, then fitted models; display-space MSE and SSIM."""
    frame, fog, light = colonnade()
    lines += ["## Path-traced fog frame (colonnade, 320x180): display-space MSE and SSIM", "",
              "| model | MSE | SSIM |", "|---|---|---|"]  # fmt: skip

    def score(effect):
        image = effect(frame, light)
        return float(mse_loss(image, fog)), float(ssim(image, fog))

    untuned = {}
    candidates = {name: gr.preset(name) for name in sorted(gr.PRESETS)}
    candidates["xna_crepuscular with source=sky"] = dataclasses.replace(gr.preset("xna_crepuscular"), source="sky")
    candidates["galaxy_vls with source=sky"] = dataclasses.replace(gr.preset("galaxy_vls"), source="sky")
    for name, effect in candidates.items():
        try:
            untuned[name] = score(effect)
        except ValueError as error:  # a preset that needs a pass this frame lacks
            lines.append(f"| {name} (untuned) | n/a: {error} | |")
            continue
        lines.append(f"| {name} (untuned) | {untuned[name][0]:.5f} | {untuned[name][1]:.4f} |")
        print(lines[-1], flush=True)
    best_name = min(untuned, key=lambda n: untuned[n][0])
    models = {
        "GodRays source=sky": (gr.GodRays(source="sky", num_samples=64.0, max_samples=64), ("tint", "threshold", "light_radius", "offscreen_fade")),
        "GodRays source=disc": (gr.GodRays(source="disc", num_samples=64.0, max_samples=64), ("tint", "threshold", "offscreen_fade")),
        "FlareOuts": (gr.preset("kbengine_flares"), ("tint", "offscreen_fade")),
        "SunOvercast": (gr.preset("sun_overcast"), ("offscreen_fade", "source_grow", "occluder_shrink")),
    }
    fitted = {}
    for name, (start, fixed) in models.items():
        fixed = tuple(f for f in fixed if f in gr.effects.parameter_bounds(start))
        started = time.perf_counter()
        result = fit(start, frame, light, fog, fixed=fixed, max_steps=30)
        fitted[name] = score(result.rounded)
        lines.append(f"| {name} (fitted, {result.steps} steps, {time.perf_counter() - started:.0f} s) | "
                     f"{fitted[name][0]:.5f} | {fitted[name][1]:.4f} |")  # fmt: skip
        print(lines[-1], flush=True)
    best_fit = min(fitted, key=lambda n: fitted[n][0])
    cut = 1 - fitted[best_fit][0] / untuned[best_name][0]
    lines += ["", f"Best untuned preset: {best_name} (MSE {untuned[best_name][0]:.5f}); best fitted model: {best_fit} "
              f"(MSE {fitted[best_fit][0]:.5f}): MSE cut by {100 * cut:.0f} %.", ""]  # fmt: skip
    print(lines[-2], flush=True)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default="grad,fog", help="comma-separated: grad, fog")
    parser.add_argument("--sizes", default="270x480", help="HxW list for the gradient table, e.g. 270x480,1080x1920")
    parser.add_argument("--out", help="append the Markdown tables to this file")
    args = parser.parse_args()
    parts = args.only.split(",")
    lines = [f"# bench_fit ({jax.devices()[0].platform}, jax {jax.__version__})", ""]
    if "grad" in parts:
        bench_gradient(lines, [tuple(int(v) for v in size.split("x")) for size in args.sizes.split(",")])
    if "fog" in parts:
        bench_fog(lines)
    if args.out:
        with open(args.out, "a") as stream:
            stream.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
