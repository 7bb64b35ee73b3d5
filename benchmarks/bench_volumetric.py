"""`VolumetricFog`'s forward pass at 1920x1080 on this machine, and its compiled memory against the sample counts.

    python benchmarks/bench_volumetric.py [--repeats 3]

Forward: the `hidden_sun` reference's clean frame upscaled (nearest) to 1920x1080, the
`volumetric_haze` preset at `resolution_factor` 4 and 8, jitted; the median of `--repeats` runs
after one warm-up. Memory: XLA's compiled temporary bytes (`memory_analysis`) of the forward pass
and of one forward-mode derivative (what `fit`'s Jacobian takes per parameter) at 480x270 for
several `num_view_steps` x `num_shadow_samples`. `uptime` first: the machine is shared.
"""

import argparse
import dataclasses
import statistics
import subprocess
import sys
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import godrays_jax as gr

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / "references"))
from scenes import BY_NAME  # noqa: E402  (the references' folder joins the path first)


def frame(height: int, width: int) -> tuple[gr.Buffers, jnp.ndarray]:
    scene = BY_NAME["hidden_sun"]
    small = gr.read_buffers(str(scene.clean))
    rows = (np.arange(height) * small.height) // height
    cols = (np.arange(width) * small.width) // width
    pick = lambda a: jnp.asarray(np.asarray(a)[rows][:, cols])  # noqa: E731
    light = jnp.asarray([scene.light_px[0] * width / small.width, scene.light_px[1] * height / small.height])
    return gr.Buffers(color=pick(small.color), depth=pick(small.depth), coverage=pick(small.coverage)), light


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    print(subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip())
    buffers, light = frame(1080, 1920)
    print("| 1920x1080 forward | median seconds |")
    print("|---|---|")
    for factor in (4, 8):
        haze = gr.preset("volumetric_haze")
        effect = type(haze)(**{**{f.name: getattr(haze, f.name) for f in dataclasses.fields(haze)}, "resolution_factor": factor})
        run = eqx.filter_jit(lambda e, b, l: e(b, l))
        run(effect, buffers, light).block_until_ready()
        times = []
        for _ in range(args.repeats):
            start = time.perf_counter()
            run(effect, buffers, light).block_until_ready()
            times.append(time.perf_counter() - start)
        print(f"| resolution_factor {factor} | {statistics.median(times):.3f} |", flush=True)
    buffers, light = frame(270, 480)
    print("| 480x270, resolution_factor 4 | forward MiB | one JVP MiB |")
    print("|---|---|---|")
    for steps, samples in ((8, 16), (16, 32), (32, 32), (16, 128)):
        effect = gr.VolumetricFog(num_view_steps=steps, num_shadow_samples=samples, resolution_factor=4)
        forward = jax.jit(lambda b, l, effect=effect: effect(b, l)).lower(buffers, light).compile()

        def tangent(extinction, effect=effect):
            return jax.jvp(lambda x: eqx.tree_at(lambda e: e.medium.extinction, effect, x)(buffers, light), (extinction,),
                           (jnp.ones_like(extinction),))[1]  # fmt: skip

        derivative = jax.jit(tangent).lower(effect.medium.extinction).compile()
        mib = [c.memory_analysis().temp_size_in_bytes / 2**20 for c in (forward, derivative)]
        print(f"| {steps} view steps x {samples} shadow samples | {mib[0]:.1f} | {mib[1]:.1f} |", flush=True)


if __name__ == "__main__":
    main()
