"""Does a preset give the same picture at any resolution? (issue 17, part 2)

Renders shipped scenes with the library's own rasterizer at a small and a 3x
larger size, applies every preset to both (with the camera's field of view and clip planes, as
`apply` reads them from a frame `render` wrote), box-downsamples the large results
3x and prints the PSNR between them, next to the PSNR of the two inputs (the
frames themselves, rendered at both sizes and compared the same way). The
requirement: each preset agrees to at least 35 dB, or within 3 dB of its
inputs' own agreement. Values are compared after the display transform
`x / (1 + x)` (HDR frames: a sun at 40 would dominate a linear PSNR), peak 1.

    python benchmarks/bench_resolution.py                    # 320x180 vs 960x540
    python benchmarks/bench_resolution.py --small 160x90     # any small size; the large one is 3x
"""

import argparse
import math
import os
import sys

import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import godrays_jax as gr  # noqa: E402
from godrays_jax.primitives.resample import downsample_box  # noqa: E402
from godrays_jax.raster import light_distance, light_pixel, load_scene, render  # noqa: E402
from bench_shimmer import with_camera  # noqa: E402  (this script's folder is on the path)

SCENES = ("examples/scenes/crepuscular_003.json", "examples/scenes/occluders_002.json")
FACTOR = 3
REQUIRED_DB = 35.0
SLACK_DB = 3.0


def frame_at(path: str, width: int, height: int):
    """The scene rendered at `width x height`, with its light's pixel position, depth and side."""
    scene, camera = load_scene(path)
    camera = type(camera)(
        position=camera.position, target=camera.target, up=camera.up, fov_x_deg=camera.fov_x_deg, width=width,
        height=height, near=camera.near, far=camera.far,
    )  # fmt: skip
    buffers = render(scene, camera)
    xy, _, in_front = light_pixel(scene, camera)
    return buffers, jnp.asarray(xy, jnp.float32), bool(in_front), light_distance(scene, camera)


def display(image) -> np.ndarray:
    rgb = np.maximum(np.asarray(image, np.float64)[..., :3], 0.0)
    return rgb / (1.0 + rgb)


def psnr(a, b) -> float:
    mse = float(np.mean((display(a) - display(b)) ** 2))
    return math.inf if mse == 0 else 10.0 * math.log10(1.0 / mse)


def agreement(small, large) -> float:
    return psnr(small, downsample_box(jnp.asarray(large), FACTOR))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--small", default="320x180", help="the small size WxH; the large one is 3x (default 320x180)")
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.small.lower().split("x"))
    failures = 0
    print(f"{width}x{height} vs {FACTOR * width}x{FACTOR * height} box-downsampled {FACTOR}x, PSNR of x / (1 + x)")
    print("| scene | preset | inputs (dB) | result (dB) | ok |")
    print("|---|---|---|---|---|")
    for path in SCENES:
        small = frame_at(path, width, height)
        large = frame_at(path, FACTOR * width, FACTOR * height)
        inputs = agreement(small[0].color, large[0].color)
        camera = load_scene(path)[1]
        for name in sorted(gr.PRESETS):
            effect = with_camera(gr.preset(name), camera)  # the frame's field of view and clip planes, as `apply`
            results = []
            for buffers, light, in_front, depth in (small, large):
                results.append(effect(buffers, light, light_in_front=in_front, light_depth=depth))
            result = agreement(*results)
            ok = result >= REQUIRED_DB or result >= inputs - SLACK_DB
            failures += not ok
            print(f"| {os.path.basename(path)} | {name} | {inputs:.1f} | {result:.1f} | {'yes' if ok else 'NO'} |")
    return 1 if failures else 0


if __name__ == "__main__":
    raise SystemExit(main())
