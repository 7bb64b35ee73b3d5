"""Fitting figures: the path-traced fog frame, parameter recovery, fit time, gradient cost and memory.

Run as a script, on the CPU or a GPU (JAX's default device):

    python benchmarks/bench_fit.py [--only fog,recovery,time,grad] [--out benchmarks/fit_results.md]
    python benchmarks/bench_fit.py --only time,grad --time-size 1080x1920 --sizes 1080x1920   # the GPU figures

Timings are medians of repeated runs after a warm-up (compilation reported
separately); memory is XLA's compiled temporary-buffer size
(`memory_analysis()`), the peak working set of one call beside its inputs and
outputs. The load average is printed with the timings: the machine is shared.
"""

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import godrays_jax as gr
from godrays_jax.effects.fields import field_value
from godrays_jax.pipeline.fit import fit
from godrays_jax.kernels.losses import mse_loss, ssim

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def interleaved_medians(functions, *args, rounds=11):
    """Median seconds of each function, timed in turn round after round (a shared machine's slow spells hit all)."""
    for function in functions:
        jax.block_until_ready(function(*args))
    times = [[] for _ in functions]
    for _ in range(rounds):
        for function, spent in zip(functions, times):
            start = time.perf_counter()
            jax.block_until_ready(function(*args))
            spent.append(time.perf_counter() - start)
    return [statistics.median(spent) for spent in times]


def temp_mib(function, *args):
    return jax.jit(function).lower(*args).compile().memory_analysis().temp_size_in_bytes / 2**20


def load_average() -> str:
    return "load average " + ", ".join(f"{value:.1f}" for value in os.getloadavg())


def device_name() -> str:
    device = jax.devices()[0]
    return device.platform if device.platform == "cpu" else f"{device.platform} {device.device_kind}"


def parse_size(text: str) -> tuple[int, int]:
    height, width = (int(v) for v in text.split("x"))
    return height, width


def resized(buffers, height, width):
    """Nearest-neighbour resize of a frame (enough for timing, memory and synthetic targets)."""
    rows = np.arange(height) * buffers.height // height
    cols = np.arange(width) * buffers.width // width
    pick = lambda a: None if a is None else jnp.asarray(np.asarray(a)[rows][:, cols])  # noqa: E731
    return gr.Buffers(color=pick(buffers.color), depth=pick(buffers.depth), coverage=pick(buffers.coverage),
                      light_pass=pick(buffers.light_pass))  # fmt: skip


def colonnade():
    frame = gr.read_buffers(DATA / "colonnade_buffers.exr")
    fog = gr.read_image(DATA / "colonnade_fog.exr")[..., :3]
    scene = json.loads((DATA / "scenes.json").read_text())["colonnade"]
    return frame, fog, jnp.asarray(scene["light_px"], jnp.float32), float(scene["fov_x_deg"])


def scores(image, target):
    """Display-space MSE, display-space SSIM, linear MSE."""
    return (float(mse_loss(image, target)), float(ssim(image, target)), float(mse_loss(image, target, space="linear")))


FOG_FIXED = ("fov_x_deg", "offscreen_fade", "num_samples")
"""The field of view is known (scenes.json); the fade never acts (the sun is on screen); 32 samples."""


def bench_fog(lines, fog_steps, additive_steps):
    """Every preset untuned against the fog frame, then fitted models."""
    frame, fog, light, fov = colonnade()
    lines += ["## Path-traced fog frame (colonnade, 320x180)", "",
              "Display space is `x / (1 + x)` per channel; SSIM on display values; linear MSE for completeness "
              "(dominated by the few sun pixels).", "",
              "| model | MSE (display) | SSIM | MSE (linear) |", "|---|---|---|---|"]  # fmt: skip
    untuned = {}
    for name in sorted(gr.PRESETS):
        try:
            untuned[name] = scores(gr.preset(name)(frame, light), fog)
        except ValueError as error:  # a preset that needs a pass this frame lacks
            lines.append(f"| {name} (untuned) | n/a: {error} | | |")
            continue
        lines.append(f"| {name} (untuned) | {untuned[name][0]:.5f} | {untuned[name][1]:.4f} | {untuned[name][2]:.2f} |")
        print(lines[-1], flush=True)
    lines.append(f"| clean frame, no effect | {scores(frame.color, fog)[0]:.5f} | {scores(frame.color, fog)[1]:.4f} | "
                 f"{scores(frame.color, fog)[2]:.2f} |")  # fmt: skip
    best_name = min(untuned, key=lambda n: untuned[n][0])
    fog_start = eqx.tree_at(lambda e: e.fov_x_deg, gr.preset("participating_media"), jnp.asarray(fov))
    models = {
        "ScatteringFog from participating_media": (fog_start, FOG_FIXED, fog_steps),
        "GodRays source=sky from xna_crepuscular": (
            gr.GodRays(source="sky", density=0.5, decay=0.95, exposure=0.15, num_samples=32.0, max_samples=32),
            ("tint", "threshold", "flare_size", "offscreen_fade", "num_samples"), additive_steps),
        "FlareOuts from kbengine_flares": (gr.preset("kbengine_flares"), ("offscreen_fade", "num_iters"), additive_steps),
    }  # fmt: skip
    fitted = {}
    for name, (start, fixed, steps) in models.items():
        started = time.perf_counter()
        result = fit(start, frame, light, fog, fixed=fixed, max_steps=steps)
        fitted[name] = scores(result.rounded(frame, light), fog)
        lines.append(f"| {name} (fitted: {len(result.fitted)} fields, {result.steps} steps, "
                     f"{time.perf_counter() - started:.0f} s) | {fitted[name][0]:.5f} | {fitted[name][1]:.4f} | "
                     f"{fitted[name][2]:.2f} |")  # fmt: skip
        print(lines[-1], flush=True)
        if name.startswith("ScatteringFog"):
            values = gr.effect_to_dict(result.rounded)
            fitted_values = ", ".join(f"{n} {np.round(values[n], 4).tolist()}" for n in result.fitted)
    best_fit = min(fitted, key=lambda n: fitted[n][0])
    cut = 1 - fitted[best_fit][0] / untuned[best_name][0]
    lines += ["", f"Best untuned preset: {best_name} (MSE {untuned[best_name][0]:.5f}, SSIM {untuned[best_name][1]:.4f}); "
              f"best fitted model: {best_fit} (MSE {fitted[best_fit][0]:.5f}, SSIM {fitted[best_fit][1]:.4f}): "
              f"display MSE cut by {100 * cut:.0f} %.", "", f"Fitted ScatteringFog: {fitted_values}.", ""]  # fmt: skip
    print(lines[-4], flush=True)


def _recovery_frame():
    """The colonnade at 160x90 with a seed-004 light pass: a sun disc (radius 4.3 px) where sky shows.

    The sun sits at (78, 30), beside a pillar's edge, rather than where the path
    tracer put it (behind a pillar, 2 visible pixels: too little signal).
    """
    frame, _, _, _ = colonnade()
    small = resized(frame, 90, 160)
    light = jnp.asarray([78.0, 30.0], jnp.float32)
    x, y = np.meshgrid(np.arange(160) + 0.5, np.arange(90) + 0.5)
    disc = np.clip(4.3 - np.hypot(x - float(light[0]), y - float(light[1])) + 0.5, 0.0, 1.0)
    light_pass = jnp.asarray(disc * (1.0 - np.asarray(small.coverage)), jnp.float32)
    return eqx.tree_at(lambda b: b.light_pass, small, light_pass, is_leaf=lambda v: v is None), light


def _with(effect, **changes):
    """A copy of `effect` with some fields (static ones too) changed."""
    return gr.effect_from_dict({**gr.effect_to_dict(effect), **changes})


def _recovery_cases():
    """(name, truth, start, fixed, why): starts are the seeds' presets, truths other values of the same model."""
    rays_fixed = ("weight", "flare_size", "threshold", "tint", "offscreen_fade", "num_samples")
    why_rays = ("weight and tint scale the rays exactly like exposure; for a smooth source the sample loop is a "
                "Riemann sum, so num_samples, decay and exposure trade off (only decay^(n/density) and "
                "exposure n/density are identifiable): num_samples is kept; the disc size, threshold and fade are "
                "scene choices")  # fmt: skip
    xna = _with(gr.preset("xna_crepuscular"), flare_size=30.0 / 320, num_samples=48.0, max_samples=64)
    galaxy = _with(gr.preset("galaxy_vls"), num_samples=48.0, max_samples=64)
    flares = gr.preset("kbengine_flares")
    # A short reach: the unrolled morphology taps slow compilation, and both reaches are fixed here.
    overcast = _with(gr.preset("sun_overcast"), max_passes=3, morphology_reach=2.0 / 320)
    return [
        ("seed 003 xna_crepuscular (disc 30 px, bright pass)",
         _with(xna, density=0.8, decay=0.9, exposure=0.3), xna, rays_fixed, why_rays),
        ("seed 004 galaxy_vls (light pass)",
         _with(galaxy, density=0.7, decay=0.95, exposure=0.1), galaxy, rays_fixed, why_rays),
        ("seed 002 kbengine_flares (disc 40 px)",
         _with(flares, scale_step=1.06, intensity=0.2, blur_sigma=3.0 / 320), flares,
         ("copy_decay", "flare_size", "tint", "offscreen_fade", "num_iters"),
         "on a smooth disc the copies blur into one glow whose reach is scale_step^num_iters and whose brightness "
         "is about intensity x num_iters, so the count trades off with both (measured: a fit from 20 copies to a "
         "14-copy truth stopped at 20 copies x1.041 with loss 4e-7); copy_decay likewise; tint scales like intensity"),
        ("seed 000 sun_overcast (image-space glow pass)",
         _with(overcast, blur_power=0.025, source_radius=20.0 / 320, num_passes=3.0), overcast,
         ("tint", "offscreen_fade", "source_grow", "occluder_shrink"),
         "the layer is rgb x alpha of the tint (only their product is identifiable); source_grow adds to "
         "source_radius; occluder_shrink is scene geometry"),
    ]  # fmt: skip


COUNTS = ("num_samples", "num_iters", "num_passes")


def bench_recovery(lines, steps):
    """Render with known parameters, start from the seed's preset, fit; every fitted field's relative error."""
    with_light_pass, light = _recovery_frame()
    without_light_pass = eqx.tree_at(lambda b: b.light_pass, with_light_pass, None)
    lines += ["## Parameter recovery (colonnade 160x90, Levenberg-Marquardt, display-space MSE)", "",
              "Counts are fitted through the kernels' relaxations and reported rounded (relative error of the rounded "
              "count).", ""]  # fmt: skip
    all_passed = True
    for name, truth, start, fixed, why in _recovery_cases():
        # Seed 000's image-space glow grows a disc of source_radius where no light pass exists.
        frame = without_light_pass if isinstance(truth, gr.SunOvercast) else with_light_pass
        target = truth(frame, light)
        started = time.perf_counter()
        result = fit(start, frame, light, target, fixed=fixed, max_steps=steps)
        seconds = time.perf_counter() - started
        lines += [f"### {name}", "", f"Fixed: {', '.join(fixed)} ({why}). {result.steps} steps, {seconds:.0f} s, "
                  f"loss {result.loss_before:.3g} -> {result.loss_rounded:.3g}.", "",
                  "| field | true | start | fitted | relative error |", "|---|---|---|---|---|"]  # fmt: skip
        for field in result.fitted:
            chosen = result.rounded if field in COUNTS else result.effect
            true, first, got = (np.asarray(field_value(e, field), np.float64) for e in (truth, start, chosen))
            error = float(np.max(np.abs(got - true) / np.maximum(np.abs(true), 1e-12)))
            ok = (got == true).all() if field in COUNTS else error <= 0.02
            all_passed &= bool(ok)
            fmt = lambda v: np.round(v, 5).tolist()  # noqa: E731
            lines.append(f"| {field} | {fmt(true)} | {fmt(first)} | {fmt(got)} | {100 * error:.3f} %{'' if ok else ' FAIL'} |")
        lines.append("")
        print("\n".join(lines[-len(result.fitted) - 6 :]), flush=True)
    lines += [f"Every fitted field within 2 % and every count exact: {'yes' if all_passed else 'NO'}.", ""]
    print(lines[-2], flush=True)


SIX = ("medium.extinction", "medium.max_distance", "medium.anisotropy", "medium.light_color")
"""Six unknowns (light_color is RGB). The shaft fields (density, decay, shadow_strength) are left out of the
timing fit: they change few pixels and made 50 Levenberg-Marquardt steps end unconverged (23 % off)."""


def bench_time(lines, repeats, height, width):
    """A 6-parameter ScatteringFog fit at `width`x`height` to a frame rendered with known parameters."""
    frame, _, light, fov = colonnade()
    frame, light = resized(frame, height, width), light * jnp.array([width / 320, height / 180])
    medium = gr.Medium(extinction=0.015, max_distance=60.0, anisotropy=0.85, light_color=(0.6, 0.45, 0.27),
                       ambient_color=(0.05, 0.03, 0.02))  # fmt: skip
    truth = gr.ScatteringFog(medium=medium, shadow_strength=0.7, density=0.8, decay=0.95, fov_x_deg=fov)
    start = eqx.tree_at(lambda e: [field_value(e, n) for n in SIX], truth,
                        [jnp.asarray(v) for v in (0.01, 100.0, 0.76, (1.0, 0.9, 0.75))])  # fmt: skip
    target = truth(frame, light)
    fixed = tuple(n for n in gr.parameter_bounds(truth) if n not in SIX)
    seconds, results = [], []
    for _ in range(repeats):
        started = time.perf_counter()
        results.append(fit(start, frame, light, target, fixed=fixed, max_steps=50))
        seconds.append(time.perf_counter() - started)
    errors = max(float(np.max(np.abs(np.asarray(field_value(results[-1].effect, n)) / np.asarray(field_value(truth, n)) - 1)))
                 for n in SIX)  # fmt: skip
    warm = statistics.median(seconds[1:])
    lines += [f"## Fit time: 6 parameters at {width}x{height} (ScatteringFog, 32 samples, {device_name()})", "",
              f"Fitted {', '.join(SIX)} from the participating_media values to a frame rendered with known ones: "
              f"{results[-1].steps} steps, converged: {results[-1].converged}, largest relative error "
              f"{100 * errors:.3f} %.", "",
              f"- first fit (with compilation): {seconds[0]:.1f} s",
              f"- later fits (compiled step reused), median of {len(seconds) - 1}: {warm:.1f} s "
              f"(so compilation about {seconds[0] - warm:.1f} s)",
              f"- {load_average()} on {os.cpu_count()} cores while measuring", ""]  # fmt: skip
    print("\n".join(lines[-6:]), flush=True)


FITTED_RAYS = ("density", "decay", "exposure", "num_samples", "weight", "flare_size")


def bench_gradient(lines, sizes):
    """Forward vs value+gradient (reverse mode and forward-mode Jacobian), 6 parameters, with temp memory."""
    frame, fog, light, _ = colonnade()
    lines += ["## Gradient cost and memory (6 parameters, display-space MSE against the fog frame)", "",
              "| model | size | forward s | reverse value+grad s (ratio) | forward-mode value + 6 JVPs s (ratio) | "
              "temp MiB forward / reverse / forward-mode |", "|---|---|---|---|---|---|"]  # fmt: skip
    models = {
        "GodRays sky, 128 samples": (gr.GodRays(source="sky", num_samples=100.0, max_samples=128), FITTED_RAYS),
        # The disc emitter depends on flare_size: its derivative image is a third plane sampled by every copy.
        "GodRays disc, 128 samples": (gr.GodRays(source="disc", num_samples=100.0, max_samples=128), FITTED_RAYS),
        "ScatteringFog, 32 samples": (gr.preset("participating_media"), SIX),
    }
    for height, width in sizes:
        buffers = resized(frame, height, width)
        target = resized(gr.Buffers(color=fog, depth=frame.depth, coverage=frame.coverage), height, width).color
        scaled_light = light * jnp.array([width / 320, height / 180])
        for model, (effect, names) in models.items():
            values = {n: field_value(effect, n) for n in names}

            def loss(values, effect=effect, names=names):
                candidate = eqx.tree_at(lambda e: [field_value(e, n) for n in names], effect, [values[n] for n in names])
                return mse_loss(candidate(buffers, scaled_light), target)

            def forward_mode(values, loss=loss):
                flat, unravel = jax.flatten_util.ravel_pytree(values)
                basis = jnp.eye(flat.size, dtype=flat.dtype)
                return jax.vmap(lambda d: jax.jvp(lambda f: loss(unravel(f)), (flat,), (d,)), out_axes=(None, 0))(basis)

            forward, reverse, fwd_mode = interleaved_medians(
                [jax.jit(loss), jax.jit(jax.value_and_grad(loss)), jax.jit(forward_mode)], values
            )
            memory = [temp_mib(loss, values), temp_mib(jax.value_and_grad(loss), values), temp_mib(forward_mode, values)]
            lines.append(f"| {model} | {width}x{height} | {forward:.3g} | {reverse:.3g} ({reverse / forward:.1f}x) | "
                         f"{fwd_mode:.3g} ({fwd_mode / forward:.1f}x) | {memory[0]:.0f} / {memory[1]:.0f} / {memory[2]:.0f} |")  # fmt: skip
            print(lines[-1], flush=True)
    lines += ["", f"Medians of 11 rounds (each round times the three in turn) after a warm-up; {load_average()} "
              f"on {os.cpu_count()} CPU cores, {device_name()}.", ""]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default="fog,recovery,time,grad", help="comma-separated: fog, recovery, time, grad")
    parser.add_argument("--sizes", default="270x480", help="HxW list for the gradient table, e.g. 270x480,1080x1920")
    parser.add_argument("--fog-steps", type=int, default=30, help="solver steps for the ScatteringFog fit")
    parser.add_argument("--additive-steps", type=int, default=15, help="solver steps for the additive models' fits")
    parser.add_argument("--recovery-steps", type=int, default=40)
    parser.add_argument("--repeats", type=int, default=3, help="fits timed (the first compiles)")
    parser.add_argument("--time-size", default="270x480", help="HxW of the timed fit (the GPU figure: 1080x1920)")
    parser.add_argument("--out", help="append the Markdown tables to this file")
    args = parser.parse_args()
    parts = args.only.split(",")
    lines = [f"# bench_fit ({device_name()}, jax {jax.__version__}, {os.cpu_count()} CPU cores; "
             f"{load_average()} at the start)", ""]  # fmt: skip
    if "fog" in parts:
        bench_fog(lines, args.fog_steps, args.additive_steps)
    if "recovery" in parts:
        bench_recovery(lines, args.recovery_steps)
    if "time" in parts:
        bench_time(lines, args.repeats, *parse_size(args.time_size))
    if "grad" in parts:
        bench_gradient(lines, [parse_size(size) for size in args.sizes.split(",")])
    if args.out:
        with open(args.out, "a") as stream:
            stream.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
