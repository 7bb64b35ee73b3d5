"""Cost of value and gradient against the forward pass, for the exact kernels.

    python benchmarks/bench_grad.py [--sizes 480x270,1920x1080] [--repeats 5]

Seed 003's radial rays (128 samples, density .5, decay .95, weight 1,
exposure .15) and kbEngine's flare-outs (20 copies x1.03, decay 1) of the
occlusion image of `run.py` (RGB float32, light on screen), loss
`sum(output ** 2)`. Per kernel and size: the forward pass; value and gradient
in the image alone, in every scalar argument alone (light, density, decay,
weight, exposure; scale step and decay), and in the image and every scalar;
each as a ratio to the forward pass. All cases of a size are compiled first,
then run in turns (`--repeats` rounds, every case once a round) so that a
busy machine slows them alike; medians. Also XLA's temporaries of each
compiled function (`memory_analysis()`).
"""

import argparse
import os
import platform
import statistics
import sys
import time

import jax
import jax.numpy as jnp

import godrays_jax as gr

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from run import FLARES, RAYS, occlusion_image  # noqa: E402


def rays(image, light, density, decay, weight, exposure):
    return gr.radial_rays(image, light, num_samples=RAYS["num_samples"], density=density, decay=decay,
                          weight=weight, exposure=exposure)  # fmt: skip


def flares(image, light, scale_step, decay):
    return gr.scale_iterated_flares(image, light, num_iters=FLARES["num_iters"], scale_step=scale_step, decay=decay)


def cases(height, width):
    """`{(kernel, case): (function, args)}` for one size."""
    light = (width * 0.6, height * 0.35)
    image = jnp.asarray(occlusion_image(height, width, light))
    light = jnp.asarray(light, jnp.float32)
    kernels = {
        "radial_rays": (rays, (image, light, RAYS["density"], RAYS["decay"], RAYS["weight"], RAYS["exposure"])),
        "scale_iterated_flares": (flares, (image, light, FLARES["scale_step"], 1.0)),
    }
    result = {}
    for name, (kernel, args) in kernels.items():
        loss = lambda *args, kernel=kernel: jnp.sum(kernel(*args) ** 2)  # noqa: E731
        scalars = tuple(range(1, len(args)))
        result[name, "forward"] = (kernel, args)
        result[name, "value+grad image"] = (jax.value_and_grad(loss, argnums=0), args)
        result[name, "value+grad scalars"] = (jax.value_and_grad(loss, argnums=scalars), args)
        result[name, "value+grad all"] = (jax.value_and_grad(loss, argnums=(0, *scalars)), args)
    return result


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="480x270,1920x1080", help="comma-separated WIDTHxHEIGHT")
    parser.add_argument("--repeats", type=int, default=5, help="rounds of every case (median)")
    options = parser.parse_args(argv)
    print(f"# {platform.machine()} x{os.cpu_count()} CPUs, jax {jax.__version__} ({jax.default_backend()}), "
          f"load {os.getloadavg()[0]:.1f}")  # fmt: skip
    print("| kernel | size | case | median | x forward | temporaries |")
    print("|---|---|---|---|---|---|")
    for size in options.sizes.split(","):
        width, height = (int(part) for part in size.split("x"))
        compiled = {}
        for key, (function, args) in cases(height, width).items():
            executable = jax.jit(function).lower(*args).compile()
            jax.block_until_ready(executable(*args))
            compiled[key] = (executable, args, executable.memory_analysis().temp_size_in_bytes)
        times = {key: [] for key in compiled}
        for _ in range(options.repeats):
            for key, (executable, args, _) in compiled.items():
                started = time.perf_counter()
                jax.block_until_ready(executable(*args))
                times[key].append(time.perf_counter() - started)
        for (kernel, case), (_, _, temporaries) in compiled.items():
            median = statistics.median(times[kernel, case])
            ratio = median / statistics.median(times[kernel, "forward"])
            print(f"| {kernel} | {width}x{height} | {case} | {median * 1e3:.0f} ms | {ratio:.2f} | "
                  f"{temporaries / 2**20:.0f} MiB |", flush=True)  # fmt: skip
    print(f"# load after: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
