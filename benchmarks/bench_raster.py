"""Rasterizer timing: a 10,000-triangle mesh plus 10 spheres, every buffer.

    python benchmarks/bench_raster.py [--sizes 480x270 1920x1080] [--repeats 5]

Prints the first call (compilation and one run) and the median and best of
`--repeats` runs after it, with and without the glow pass (a second
rasterization, of the tiles near the sun only), per image size, and the
machine's load average (the CPU may be shared) before and after each size.
"""

import argparse
import os
import time

import jax
import numpy as np

from godrays_jax.primitives.camera import Camera
from godrays_jax.raster import DirectionalLight, Material, Mesh, Scene, Sphere, plan_tile_capacity, render, uv_sphere


def benchmark_scene() -> Scene:
    vertices, faces = uv_sphere(segments=100, rings=51)  # 10,000 triangles
    assert len(faces) == 10_000
    rng = np.random.default_rng(0)
    spheres = tuple(
        Sphere(center=rng.uniform([-4, -2, -1.5], [4, 2, 1.5]), radius=rng.uniform(0.2, 0.6), material=Material(albedo=rng.uniform(0, 1, 3)))
        for _ in range(10)
    )
    planet = Mesh(vertices=vertices, faces=faces, normals=vertices, scale=2.0, material=Material(albedo=(0.3, 0.5, 0.8), atmosphere_color=(0.3, 0.6, 1.0)))
    sun = Sphere(center=(3.0, 2.0, -6.0), radius=1.0, material=Material(albedo=(0, 0, 0), emission=(20.0, 16.0, 10.0)))
    return Scene(objects=(planet, sun) + spheres[1:], light=DirectionalLight(direction=(3.0, 2.0, -6.0)), sun=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", default=["480x270", "1920x1080"])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    scene = benchmark_scene()
    print(f"jax {jax.__version__} on {jax.devices()[0].platform}, {len(scene.objects) - 1} spheres + 10,000 triangles")
    for size in args.sizes:
        width, height = (int(v) for v in size.split("x"))
        camera = Camera(position=(0.0, 0.0, 8.0), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov_x_deg=60.0, width=width, height=height)
        capacity = plan_tile_capacity(scene, camera)
        print(f"{size:>10} load average {_load()}", flush=True)
        for glow in (True, False):
            start = time.perf_counter()
            jax.block_until_ready(render(scene, camera, with_glow_pass=glow, tile_capacity=capacity))
            compile_and_run = time.perf_counter() - start
            runs = []
            for _ in range(args.repeats):
                start = time.perf_counter()
                jax.block_until_ready(render(scene, camera, with_glow_pass=glow, tile_capacity=capacity))
                runs.append(time.perf_counter() - start)
            print(
                f"{size:>10} glow pass {'on ' if glow else 'off'}  tile capacity {capacity}:  "
                f"first call {compile_and_run:6.1f} s, then median {np.median(runs):6.3f} s (best {min(runs):.3f} s)",
                flush=True,
            )
        print(f"{size:>10} load average {_load()}", flush=True)


def _load() -> str:
    return " ".join(f"{load:.2f}" for load in os.getloadavg()) + f" (1, 5, 15 min) on {os.cpu_count()} CPUs"


if __name__ == "__main__":
    main()
