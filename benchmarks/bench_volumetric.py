"""`VolumetricFog`'s forward pass at 320x180 and 1920x1080 on this machine, and its compiled memory against the sample counts.

    python benchmarks/bench_volumetric.py [--repeats 3]
    python benchmarks/bench_volumetric.py --fit
    python benchmarks/bench_volumetric.py --jacobian [--repeats 5]
    python benchmarks/bench_volumetric.py --profile [--top 25]
    python benchmarks/bench_volumetric.py --light-view [--repeats 5]

Forward: the `hidden_sun` reference's clean frame at 320x180 and upscaled (nearest) to 1920x1080, the
`volumetric_haze` preset (shadows read along lines through the light, every pixel's ray at 320 wide), the
same with its shadows from samples toward the light on rays 4 pixels apart at 320 wide (the preset before
that), and `physically_based` at its own counts, jitted, march spacings scaled with the frame
(`march_factor`); the median of `--repeats` runs after one warm-up. Memory: XLA's compiled temporary bytes
(`memory_analysis`) of the forward pass and of one forward-mode derivative (what `fit`'s Jacobian takes per
parameter) at 480x270 for several `num_view_steps` x `num_shadow_samples`, and for shadows read along lines. `--fit` times the 480x270 fit instead: the reference's
clean frame and fog render upscaled (nearest), `fit` from `volumetric_haze` with the field of view
fixed (the frame gives it), once as `godrays-jax fit` runs it (the model's presets and a ground
layer read from the frame on each start as other starts (`fit_command.fit_starts`), raced by successive halving, its default coarse phase and
plateau stop) and once as at 8905696 (the presets each fitted to the end in the coarse phase, its
plateau stop at 0.1 % in both phases); each
fit twice, the first compiling, the second's wall and process CPU seconds (less hit by other jobs on a
shared machine) split into its coarse phase and the rest, and the final display-space MSE. `--profile`: where
the 1920x1080 forward of `volumetric_haze` goes, from JAX's profiler over three runs after a warm-up: the
`--top` compiled kernels (XLA's fusions, named as in the compiled program's HLO text, which says what each
holds) by their mean milliseconds a run, summed over the threads that ran them. `--jacobian`: the fit's
forward-mode Jacobian (`fit_programs.forward_mode`) of the display-space residuals at 480x270 (the `--fit` frame and
target, `volumetric_haze`'s stand-in, which `fit` differentiates, the field of view fixed), compiled: one vectorised JVP of every unknown against one
per stage (`Effect.FIELD_STAGES`), medians of `--repeats` runs after one that compiles, alternating, and the
largest difference between the two. `--light-view`: a render of `volumetric_haze` that reads a depth map seen from
the light (`window_ahead` made 480x270 as `bench_fit_cli.py` makes it, with its map), jitted inside `values_only()`
as a caller jits it, compiled with XLA's defaults and without YNNPACK's fusions (`exported.COMPILER_OPTIONS`, as the
commands compile it), alternating, medians of `--repeats` runs. `uptime` first: the machine is shared.
"""

import argparse
import collections
import dataclasses
import gzip
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import godrays_jax as gr
from godrays_jax.app.fit_command import fit_starts
from godrays_jax.app.options import auto_coarse_factor, model_presets
from godrays_jax.effects.volumetric import march_factor
from godrays_jax.pipeline.exported import COMPILER_OPTIONS
from godrays_jax.pipeline.fit_programs import forward_mode
from godrays_jax.pipeline.problem import FitProblem, as_frames, fitted_bounds, start_point
from godrays_jax.primitives.light_metadata import read_light

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / "references"))
from scenes import BY_NAME  # noqa: E402  (the references' folder joins the path first)

from bench_fit_cli import frame_pair  # noqa: E402  (this script's own folder)


SCENE = BY_NAME["hidden_sun"]


def upscaled(image: np.ndarray, height: int, width: int) -> jnp.ndarray:
    """`image` at `height x width`, nearest."""
    rows = (np.arange(height) * image.shape[0]) // height
    cols = (np.arange(width) * image.shape[1]) // width
    return jnp.asarray(np.asarray(image)[rows][:, cols])


def frame(height: int, width: int) -> tuple[gr.Buffers, jnp.ndarray]:
    small = gr.read_buffers(str(SCENE.clean))
    pick = lambda a: upscaled(a, height, width)  # noqa: E731
    light = jnp.asarray([SCENE.light_px[0] * width / small.width, SCENE.light_px[1] * height / small.height])
    return gr.Buffers(color=pick(small.color), depth=pick(small.depth), coverage=pick(small.coverage)), light


def fit_row(label: str, **options) -> None:
    """Time `fit` at 480x270 twice (the first compiles) with `options`; print the row, the second run's seconds
    split into the coarse phase (every start's steps there) and the rest (the full-resolution phase, the losses)."""
    buffers, light = frame(270, 480)
    target = upscaled(gr.read_image(str(SCENE.fog_a))[..., :3], 270, 480)
    start = eqx.tree_at(lambda e: e.fov_x_deg, gr.preset("volumetric_haze"), jnp.asarray(SCENE.fov_x_deg, jnp.float32))
    times = []
    for _ in range(2):
        stamps = {}  # step -> (wall, process CPU) seconds
        began, began_cpu = time.perf_counter(), time.process_time()
        result = gr.fit(
            start, buffers, light, target, fixed=("fov_x_deg",), light_depth=SCENE.light_depth,
            progress=lambda step, _: stamps.__setitem__(step, (time.perf_counter(), time.process_time())), **options,
        )  # fmt: skip
        times.append((time.perf_counter() - began, time.process_time() - began_cpu))
    wall, cpu = times[1]
    coarse_wall, coarse_cpu = (
        (stamps[result.coarse_steps][0] - began, stamps[result.coarse_steps][1] - began_cpu) if result.coarse_steps
        else (0.0, 0.0)
    )  # fmt: skip
    steps = f"{result.coarse_steps} + {result.steps}" if result.coarse_steps else str(result.steps)
    print(f"| {label} | {steps} | {times[0][0]:.1f} | {wall:.1f} ({coarse_wall:.1f} + {wall - coarse_wall:.1f}) | "
          f"{cpu:.1f} ({coarse_cpu:.1f} + {cpu - coarse_cpu:.1f}) | {result.loss_after:.4g} | {result.start} |",
          flush=True)  # fmt: skip


def jacobian_rows(repeats: int) -> None:
    """Time the fit's Jacobian at 480x270: one vectorised JVP of every unknown, and one per stage."""
    buffers, light = frame(270, 480)
    target = upscaled(gr.read_image(str(SCENE.fog_a))[..., :3], 270, 480)
    # What `fit` differentiates: the preset's stand-in (`Effect.fit_stand_in`).
    effect = dataclasses.replace(gr.preset("volumetric_haze"), fov_x_deg=np.float32(SCENE.fov_x_deg)).fit_stand_in()
    frame_data = as_frames(buffers, light, target, True, SCENE.light_depth)
    bounds = fitted_bounds(effect, fixed=("fov_x_deg",))
    problem = FitProblem.of(effect, bounds, frame_data[0], loss="mse", space="display")
    y = start_point(problem, jnp.float32)

    # The frames an argument, as `fit` passes them: closed over, XLA would fold the kernel's work on them as constants.
    def one_pass(y, frame_data):
        return forward_mode(lambda flat: problem.residuals(flat, frame_data))(y)

    def by_stage(y, frame_data):
        residuals = lambda *vectors: problem.residuals_of(problem.effect_of_groups(vectors), frame_data)  # noqa: E731
        return forward_mode(residuals, problem.lane_groups)(y)

    ways = {"one vectorised JVP of all": one_pass, "one per stage": by_stage}
    compiled = {name: jax.jit(jax.jacfwd(way)) for name, way in ways.items()}
    jacobians = {name: jax.block_until_ready(run(y, frame_data)) for name, run in compiled.items()}
    times = collections.defaultdict(list)
    for _ in range(repeats):
        for name, run in compiled.items():
            began = time.perf_counter()
            jax.block_until_ready(run(y, frame_data))
            times[name].append(time.perf_counter() - began)
    groups = [[name for name in bounds if problem.stages[problem.names.index(name)] == stage] for stage in
              dict.fromkeys(problem.stages)]  # fmt: skip
    print(f"{y.size} unknowns; stages: " + "; ".join(", ".join(group) for group in groups))
    print("| 480x270 Jacobian | median seconds |")
    print("|---|---|")
    for name in ways:
        print(f"| {name} | {statistics.median(times[name]):.3f} |")
    difference = float(jnp.max(jnp.abs(jacobians["one per stage"] - jacobians["one vectorised JVP of all"])))
    print(f"largest difference {difference:.3g} (largest entry {float(jnp.max(jnp.abs(jacobians['one per stage']))):.3g})")


def profile_rows(top: int) -> None:
    """The 1920x1080 forward's compiled kernels by mean milliseconds a run (JAX's profiler, three runs)."""
    buffers, light = frame(1080, 1920)
    effect = gr.preset("volumetric_haze")
    run = eqx.filter_jit(lambda e, b, l: e(b, l))
    run(effect, buffers, light).block_until_ready()
    runs = 3
    with tempfile.TemporaryDirectory() as folder:
        with jax.profiler.trace(folder, create_perfetto_trace=True):
            for _ in range(runs):
                run(effect, buffers, light).block_until_ready()
        events = json.load(gzip.open(next(Path(folder).rglob("*.trace.json.gz"))))["traceEvents"]
    # The executor's and Python's own spans hold the kernels; only the kernels are listed.
    kernels = [e for e in events if e.get("ph") == "X" and "Execute" not in e["name"] and not e["name"].startswith("$")]
    total, count = collections.Counter(), collections.Counter()
    for event in kernels:
        total[event["name"]] += event.get("dur", 0) / 1e3 / runs
        count[event["name"]] += 1
    print(f"| compiled kernel (of {len(total)}) | ms a run | times a run |")
    print("|---|---|---|")
    for name, milliseconds in total.most_common(top):
        print(f"| {name} | {milliseconds:.1f} | {count[name] // runs} |")
    print(f"| all kernels | {sum(total.values()):.1f} | |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--fit", action="store_true", help="time the 480x270 fit instead, as fit runs it and as before")
    parser.add_argument("--profile", action="store_true", help="split the 1920x1080 forward by compiled kernel instead")
    parser.add_argument("--jacobian", action="store_true", help="time the fit's Jacobian at 480x270, by stages and not")
    parser.add_argument("--top", type=int, default=25, help="kernels listed by --profile")
    parser.add_argument("--light-view", action="store_true", help="a render reading a light view, by compile options")
    args = parser.parse_args()
    print(subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip())
    if args.profile:
        profile_rows(args.top)
        return
    if args.jacobian:
        jacobian_rows(args.repeats)
        return
    if args.light_view:
        light_view_rows(args.repeats)
        return
    if args.fit:
        print("| 480x270 fit | steps (coarse + full) | seconds, compiling | seconds, again (coarse + rest) | "
              "CPU seconds, again (coarse + rest) | display MSE | winning start |")  # fmt: skip
        print("|---|---|---|---|---|---|---|")
        presets = [gr.preset(name) for name in model_presets(gr.preset("volumetric_haze"))]
        given = dataclasses.replace(gr.preset("volumetric_haze"), fov_x_deg=np.float32(SCENE.fov_x_deg))
        starts = fit_starts(given, [frame(270, 480)[0]], SCENE.fov_x_deg)[1]
        factor = auto_coarse_factor(270, 480)
        fit_row(f"godrays-jax fit's way: coarse factor {factor}, {len(presets)} presets and a ground layer on each "
                "start raced by successive halving", coarse_factor=factor, starts=starts)  # fmt: skip
        fit_row(f"as at 8905696: coarse factor {factor}, each of {len(presets)} presets fitted to the end",
                coarse_factor=factor, starts=presets, probe_steps=50, coarse_plateau_rtol=1e-3)  # fmt: skip
        print(subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip())
        return
    print("| forward | march spacing, pixels | median seconds |")
    print("|---|---|---|")
    rows = (
        ("volumetric_haze", {}),
        ("volumetric_haze", dict(shadows="samples", resolution_factor=4)),  # the preset before its shadows by lines
        ("physically_based", {}),
    )  # fmt: skip
    for height, width in ((180, 320), (1080, 1920)):
        buffers, light = frame(height, width)
        for name, changes in rows:
            effect = dataclasses.replace(gr.preset(name), **changes)
            run = eqx.filter_jit(lambda e, b, l: e(b, l))
            run(effect, buffers, light).block_until_ready()
            times = []
            for _ in range(args.repeats):
                start = time.perf_counter()
                run(effect, buffers, light).block_until_ready()
                times.append(time.perf_counter() - start)
            shadows = (f"{effect.num_shadow_lines} lines x {effect.num_shadow_bins} bins" if effect.shadows == "lines"
                       else f"{effect.num_shadow_samples} shadow samples")  # fmt: skip
            label = (f"{width}x{height}, {name} ({effect.num_view_steps} view steps, {shadows}), resolution_factor "
                     f"{effect.resolution_factor}")  # fmt: skip
            spacing = march_factor(height, width, effect.resolution_factor)
            print(f"| {label} | {spacing:g} | {statistics.median(times):.3f} |", flush=True)
    buffers, light = frame(270, 480)
    print("| 480x270 | forward MiB | one JVP MiB |")
    print("|---|---|---|")
    counts = [dict(num_view_steps=steps, num_shadow_samples=samples, resolution_factor=4, shadows="samples")
              for steps, samples in ((8, 16), (16, 32), (32, 32), (16, 128))]  # fmt: skip
    counts += [dict(num_view_steps=16, resolution_factor=factor, shadows="lines") for factor in (1, 4)]
    for count in counts:
        effect = gr.VolumetricFog(**count)
        forward = jax.jit(lambda b, l, effect=effect: effect(b, l)).lower(buffers, light).compile()

        # The frame an argument, as `fit` passes it: closed over, XLA would fold the kernel's work on it as constants.
        def tangent(extinction, buffers, light, effect=effect):
            return jax.jvp(lambda x: eqx.tree_at(lambda e: e.medium.extinction, effect, x)(buffers, light), (extinction,),
                           (jnp.ones_like(extinction),))[1]  # fmt: skip

        derivative = jax.jit(tangent).lower(effect.medium.extinction, buffers, light).compile()
        mib = [c.memory_analysis().temp_size_in_bytes / 2**20 for c in (forward, derivative)]
        shadows = (f"{effect.num_shadow_lines} lines x {effect.num_shadow_bins} bins" if effect.shadows == "lines"
                   else f"{effect.num_shadow_samples} shadow samples")  # fmt: skip
        spacing = march_factor(270, 480, effect.resolution_factor)
        print(f"| {effect.num_view_steps} view steps x {shadows}, spacing {spacing:g} | {mib[0]:.1f} | {mib[1]:.1f} |",
              flush=True)

def light_view_rows(repeats: int) -> None:
    """A render that reads a light view, compiled with XLA's defaults and with the commands' options, alternating."""
    reference = HERE / "references" / "window_ahead"
    with tempfile.TemporaryDirectory() as folder:
        clean, _ = frame_pair(Path(folder), 270, 480, reference)
        buffers = gr.read_buffers(clean)
        (x, y), in_front = read_light(clean)
    light_view = gr.read_light_view(reference.with_name("window_ahead_light_view.exr"))
    buffers = dataclasses.replace(buffers, light_view=light_view)
    light = jnp.asarray([x, y], jnp.float32)
    effect = gr.preset("volumetric_haze")

    def render(frame):
        with gr.values_only():
            return effect(frame, light, light_in_front=in_front)

    lowered = jax.jit(render).lower(buffers)
    programs = {"XLA's defaults": lowered.compile(),
                "without YNNPACK's fusions": lowered.compile(compiler_options=COMPILER_OPTIONS)}
    times = {name: [] for name in programs}
    for program in programs.values():
        program(buffers).block_until_ready()
    for _ in range(repeats):
        for name, program in programs.items():
            start = time.perf_counter()
            program(buffers).block_until_ready()
            times[name].append(time.perf_counter() - start)
    print("| 480x270 render reading a light view, compiled with | median ms |")
    print("|---|---|")
    for name, seconds in times.items():
        print(f"| {name} | {1e3 * statistics.median(seconds):.0f} |")


if __name__ == "__main__":
    main()
