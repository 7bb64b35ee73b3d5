"""How far the lights in view (`gr.seen_lights`) lie from the lights each reference was rendered with.

    python benchmarks/bench_seen_lights.py [FRAME.exr ...]

For every reference's clean frame (`benchmarks/references/*_clean.exr` by default): each light in view (its
centre, whether something hides part of it, its radius, its standard error and its distance) beside the nearest
light the frame's header stores, and the median time of a call over 5 (the frame already read). A frame with no
light in view is listed with its header's light, so that what `--light auto` searches for instead shows.
"""

import argparse
import math
import time
from pathlib import Path

import numpy as np

import godrays_jax as gr
from godrays_jax.primitives.camera_metadata import read_frame_camera

REFERENCES = Path(__file__).resolve().parent / "references"
CALLS = 5


def _stored(path) -> list[tuple[np.ndarray, float]]:
    """The header's lights: each position (pixels) and distance (`inf` for the sun)."""
    lights = gr.read_lights(path)
    if lights:
        return [(np.asarray(light.xy, np.float64), float(light.depth)) for light in lights]
    light = gr.read_light(path)
    if light is None:
        return []
    depth = gr.read_light_depth(path)
    return [(np.asarray(light[0], np.float64), math.inf if depth is None else float(depth))]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("frames", nargs="*", help="frames to read (default: every reference's clean frame)")
    paths = parser.parse_args().frames or sorted(str(path) for path in REFERENCES.glob("*_clean.exr"))
    print("| frame | light in view (px) | hidden in part | radius px | standard error px (x, y) | distance "
          "| the header's light (px), distance | off px | ms a call |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|")
    for path in paths:
        frame = gr.read_buffers(path)
        fov = read_frame_camera(path).fov_x_deg if frame.depth_kind == "planar" else None
        times = []
        for _ in range(CALLS):
            began = time.perf_counter()
            lights = gr.seen_lights(frame, fov_x_deg=fov)
            times.append(time.perf_counter() - began)
        stored = _stored(path)
        name = Path(path).name
        milliseconds = f"{1e3 * float(np.median(times)):.1f}"
        if not lights:
            header = "; ".join(f"{xy[0]:.2f},{xy[1]:.2f}, {depth:.4g}" for xy, depth in stored) or "none"
            print(f"| `{name}` | none | | | | | {header} | | {milliseconds} |")
        for light in lights:
            nearest = min(stored, key=lambda s: np.linalg.norm(s[0] - light.light_xy), default=None)
            header, off = "none", ""
            if nearest is not None:
                header = f"{nearest[0][0]:.2f},{nearest[0][1]:.2f}, {nearest[1]:.4g}"
                off = f"{np.linalg.norm(nearest[0] - light.light_xy):.3f}"
            error = ", ".join(f"{v:.3f}" for v in light.standard_error)
            print(f"| `{name}` | {light.light_xy[0]:.3f},{light.light_xy[1]:.3f} | {'yes' if light.hidden else 'no'} "
                  f"| {light.radius:.2f} | {error} | {light.depth:.4g} | {header} | {off} | {milliseconds} |")  # fmt: skip


if __name__ == "__main__":
    main()
