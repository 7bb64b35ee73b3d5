"""Calls without `jit`: what a repeated eager call of each preset and of the loop kernels costs, and what it compiles.

    python benchmarks/bench_eager.py [--size 180x320] [--repeats 5]

Research code calls effects and kernels eagerly (op by op) before it wraps
anything in `jit`. JAX compiles each operation once per shape and reuses it,
but a loop (`lax.fori_loop`, `lax.scan`, `lax.platform_dependent`) over a
function defined inside the call is traced anew on every call and compiled
again. Per preset (at its defaults on a frame of `--size`, with every
optional pass and the light's distance) and per loop kernel, this prints the
first call's seconds, then the median of `--repeats` more calls on the same
shapes (another light each time) and how many programs XLA compiled during
those repeats (JAX's own compile events), beside the median of the same call
under `jit` (the frame passed as an argument). The machine's load shows in `uptime`, printed first.
"""

import argparse
import collections
import math
import statistics
import subprocess
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import godrays_jax as gr

_compiled = collections.Counter()


def _count_compiles(event: str, duration: float, **_) -> None:
    if event == "/jax/core/compile/backend_compile_duration":
        _compiled["programs"] += 1


def frame(height: int, width: int) -> gr.Buffers:
    """Sky above a ragged horizon, a pillar near the light, every optional pass."""
    rng = np.random.default_rng(0)
    rows = np.arange(height)[:, None] + 0.5
    horizon = height * (0.55 + 0.1 * np.sin(np.arange(width) / (width / 12)))[None, :]
    covered = (rows > horizon) | ((np.abs(np.arange(width) - 0.4 * width) < 0.08 * width)[None, :] & (rows > height / 3))
    depth = np.where(covered, rng.uniform(5.0, 40.0, (height, width)), np.inf).astype(np.float32)
    coverage = covered.astype(np.float32)
    color = rng.uniform(0.0, 1.5, (height, width, 3)).astype(np.float32)
    return gr.Buffers(
        color=jnp.asarray(color),
        depth=jnp.asarray(depth),
        coverage=jnp.asarray(coverage),
        light_pass=jnp.asarray(1.0 - coverage),
        glow_pass=jnp.asarray(np.concatenate([color * 0.3, coverage[..., None] * 0.5], axis=-1)),
        glow_target=jnp.asarray(color * (1.0 - coverage[..., None])),
    )


def timed(call, buffers, lights, repeats: int) -> tuple[float, float, int]:
    """First call's seconds, the median of `repeats` calls after it, and the programs compiled during those."""
    started = time.perf_counter()
    jax.block_until_ready(call(buffers, lights[0]))
    first = time.perf_counter() - started
    before, seconds = _compiled["programs"], []
    for light in lights[1 : repeats + 1]:
        started = time.perf_counter()
        jax.block_until_ready(call(buffers, light))
        seconds.append(time.perf_counter() - started)
    return first, statistics.median(seconds), _compiled["programs"] - before


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="180x320", help="HxW of the frame")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    height, width = map(int, args.size.split("x"))
    print(subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip())
    jax.monitoring.register_event_duration_secs_listener(_count_compiles)
    buffers = frame(height, width)
    lights = [jnp.asarray([0.6 * width + i, 0.2 * height], jnp.float32) for i in range(args.repeats + 1)]
    calls = {}
    for name in sorted(gr.PRESETS):
        effect = gr.preset(name)
        calls[name] = lambda frame, light, effect=effect: effect(frame, light, light_depth=math.inf)
    calls["radial_rays (kernel)"] = lambda frame, light: gr.radial_rays(
        frame.color, light, num_samples=64, density=0.9, decay=0.97, weight=0.05, exposure=1.0
    )
    calls["poisson_blur (kernel)"] = lambda frame, light: gr.poisson_blur(frame.color, blur_power=0.01 + 0.0 * light[0])
    print(f"\n{height}x{width}, {args.repeats} repeats after a first call\n")
    print("| call | first call s | eager median ms | programs compiled in the repeats | jit median ms | eager / jit |")
    print("|---|---|---|---|---|---|")
    for name, call in calls.items():
        first, eager, compiled = timed(call, buffers, lights, args.repeats)
        _, jitted, _ = timed(eqx.filter_jit(call), buffers, lights, args.repeats)  # the frame an argument, as `fit`
        print(f"| {name} | {first:.2f} | {1000 * eager:.1f} | {compiled} | {1000 * jitted:.1f} | {eager / jitted:.1f} |")


if __name__ == "__main__":
    main()
