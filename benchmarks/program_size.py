"""Where the race's Jacobian program comes from: its operations by the kernel line that traced them, and its compile.

    python benchmarks/program_size.py [SCENE] [--fixed NAME,...] [--lines 25] [--compile] [--calls N] [--xla-defaults]

The program that a cold `godrays-jax fit` spends most of its compiling on is the race's Jacobian
(`fit_programs.residuals_and_jacobian`, benchmarks/README.md, "The fit as users run it"). XLA's time follows the
kernels it emits, and those follow the traced program: this script traces the Jacobian of the scene's fit as the
command does at its coarse resolution (`volumetric_haze`'s stand-in, `Effect.fit_stand_in`, with the frame's field of
view, the fields in their bounds, the frames downsampled by `auto_coarse_factor`) and counts the StableHLO operations
of the lowered program by where they were traced: by kernel file, and by the innermost line of this package with the
two calls above it. `--fixed` leaves fields out (a stage's columns gone: `FitProblem.lane_groups`), `--compile`
also compiles it (with the command's options, `exported.COMPILER_OPTIONS`) and prints the seconds; `--calls N`
compiles it too and prints the median of `N` calls of the compiled program after a first one. `--xla-defaults` also
compiles it with XLA's default options and times the two programs' calls in turn, and prints how far their
results lie apart.

Operations are a proxy: a line traced inside every stage's JVP counts once per stage, and XLA fuses elementwise
operations into one kernel, while each gather stays one.
"""

import argparse
import collections
import re
import statistics
import sys
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp

import godrays_jax as gr
from godrays_jax.app.options import auto_coarse_factor
from godrays_jax.pipeline.exported import COMPILER_OPTIONS
from godrays_jax.pipeline.fit_programs import residuals_and_jacobian
from godrays_jax.pipeline.problem import FitProblem, as_frames, fitted_bounds, with_frames_read_once
from godrays_jax.pipeline.reduced import downsample_frames
from godrays_jax.primitives.checks import ranges_guaranteed

sys.path.insert(0, str(Path(__file__).resolve().parent / "references"))
from baseline import read_rgb  # noqa: E402  (the references' folder joins the path first)
from scenes import BY_NAME  # noqa: E402

_LOCATION = re.compile(r"^(#loc\d+) = loc\((.*)\)$")
_PACKAGE_LINE = re.compile(r'"[^"]*godrays_jax/([^"]+)":(\d+)|(#loc\d+)')


def lowered_jacobian(scene_name: str, fixed: tuple[str, ...]):
    """The race's Jacobian of `scene_name`'s default fit, lowered (equinox's `Lowered`), and its arguments."""
    scene = BY_NAME[scene_name]
    frame = gr.read_buffers(scene.clean)
    start = eqx.tree_at(lambda effect: effect.fov_x_deg, gr.preset("volumetric_haze"), jnp.float32(scene.fov_x_deg))
    start = start.fit_stand_in().same_on([frame])
    target = jnp.asarray(read_rgb(scene.fog_a), jnp.float32)
    light = jnp.asarray(scene.light_px, jnp.float32)
    frame_data = as_frames(frame, light, target, scene.light_in_front, scene.light_depth)
    factor = auto_coarse_factor(frame.height, frame.width)
    if factor > 1:
        frame_data = downsample_frames(frame_data, factor)
    bounds = fitted_bounds(start, fixed=("fov_x_deg", *fixed))
    frame_data = with_frames_read_once(start, frame_data, bounds)  # the frames' silhouettes read once, as `fit` does
    problem = FitProblem.of(start, bounds, frame_data[0], loss="mse", space="display")
    positions = problem.positions(jnp.float32)
    with jax.default_matmul_precision("highest"), ranges_guaranteed():  # as `fit` traces its programs
        return residuals_and_jacobian.lower(problem, positions, frame_data), (problem, positions, frame_data)


def operations_by_line(text: str) -> tuple[int, collections.Counter, collections.Counter]:
    """The operations of `text` (MLIR with its locations), by kernel file and by the package's innermost three
    lines, innermost first."""
    locations = {}
    for line in text.splitlines():
        match = _LOCATION.match(line)
        if match:
            locations[match.group(1)] = match.group(2)

    def package_lines(reference, found, depth=0):
        """This package's `file:line`s in the location `reference`, innermost first."""
        for match in _PACKAGE_LINE.finditer(locations.get(reference, "")):
            if match.group(3):
                if depth < 64:
                    package_lines(match.group(3), found, depth + 1)
            else:
                found.append(f"{match.group(1)}:{match.group(2)}")
        return found

    total, files, sites = 0, collections.Counter(), collections.Counter()
    for line in text.splitlines():
        code, _, place = line.partition(" loc(")
        if "stablehlo." not in code or not place.startswith("#loc"):
            continue
        total += 1
        chain = list(dict.fromkeys(package_lines(place.rstrip(")").strip(), [])))
        if chain:
            files[chain[0].split(":")[0]] += 1
            sites[" <- ".join(chain[:3])] += 1
    return total, files, sites


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", nargs="?", default="hidden_sun", choices=sorted(BY_NAME))
    parser.add_argument("--fixed", default="", help="fields left out of the fit, comma-separated")
    parser.add_argument("--lines", type=int, default=25, help="how many call sites to print")
    parser.add_argument("--compile", action="store_true", help="also compile the program and print the seconds")
    parser.add_argument("--calls", type=int, default=0, help="compile it and time this many calls, print the median")
    parser.add_argument("--xla-defaults", action="store_true", help="also compile it with XLA's defaults, compare")
    args = parser.parse_args()
    fixed = tuple(name for name in args.fixed.split(",") if name)
    lowered, arguments = lowered_jacobian(args.scene, fixed)
    unknowns = len(arguments[1])
    total, files, sites = operations_by_line(lowered.lowered.as_text(debug_info=True))
    print(f"{args.scene}: the race's Jacobian in {unknowns} unknowns, {total} StableHLO operations")
    print("\n| kernel file | operations | share |\n|---|---|---|")
    for name, count in files.most_common():
        print(f"| {name} | {count} | {count / total:.1%} |")
    print("\n| where traced (innermost first) | operations |\n|---|---|")
    for site, count in sites.most_common(args.lines):
        print(f"| {site} | {count} |")
    if args.compile or args.calls > 0 or args.xla_defaults:
        options = {"the command's options": COMPILER_OPTIONS, **({"XLA's defaults": None} if args.xla_defaults else {})}
        compiled = {}
        for name, option in options.items():
            start = time.perf_counter()
            compiled[name] = lowered.compile(compiler_options=option)
            print(f"\ncompiled with {name} in {time.perf_counter() - start:.1f} s")
        if args.calls > 0:
            seconds, results = {name: [] for name in compiled}, {}
            with jax.default_matmul_precision("highest"), ranges_guaranteed():
                for name, program in compiled.items():
                    results[name] = jax.block_until_ready(program(*arguments))
                for _ in range(args.calls):
                    for name, program in compiled.items():  # in turn: the machine's speed moves
                        start = time.perf_counter()
                        jax.block_until_ready(program(*arguments))
                        seconds[name].append(time.perf_counter() - start)
            for name in compiled:
                print(f"a call with {name} in {statistics.median(seconds[name]):.3f} s (median of {args.calls})")
            if len(results) == 2:
                for label, ours, theirs in zip(("residuals", "Jacobian"), *results.values()):
                    difference = float(jnp.max(jnp.abs(ours - theirs))) / float(jnp.max(jnp.abs(theirs)))
                    print(f"{label}: largest difference {difference:.1e} of the largest value")


if __name__ == "__main__":
    main()
