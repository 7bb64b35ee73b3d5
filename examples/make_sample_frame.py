"""Draw the project's sample frame with NumPy and save it as an EXR with depth.

A 320x180 frame for trying god-ray effects: a dim sky gradient and a bright sun
disc (both depth +inf, i.e. sky), a dark ground plane whose depth grows toward
the horizon, and a colonnade in front of the sun (four pillars and a beam, 12-18
scene units away, plus a slanted brace) with antialiased edges in the coverage
(A) channel, so shafts of light stream through the gaps. Deterministic.

    python examples/make_sample_frame.py [--out examples/data/sample_frame.exr]

The light's pixel position is stored in the file (`godrays_jax.read_light`).
"""

import argparse
from pathlib import Path

import numpy as np

from godrays_jax import Buffers, write_buffers

WIDTH, HEIGHT = 320, 180
SUN_XY = (200.5, 60.25)  # pixels, x right, y down
SUN_RADIUS = 10.0  # pixels
SUN_COLOR = np.array([40.0, 30.0, 18.0], np.float32)
HORIZON_Y = 120.0  # pixels
FOCAL_PX = 343.0  # ~50 degree horizontal field of view at 320 px
CAMERA_HEIGHT = 1.6  # scene units

BEAM_TOP = 43.0  # pixels


def _ground_row(depth: float) -> float:
    """The image row where the ground is `depth` away (where a pillar stands)."""
    return HORIZON_Y + CAMERA_HEIGHT * FOCAL_PX / depth


def _pillar(cx: float, half_width: float, depth: float) -> tuple[float, float, float, float, float]:
    bottom = _ground_row(depth)
    return (cx, (BEAM_TOP + bottom) / 2, half_width, (bottom - BEAM_TOP) / 2, depth)


# (centre x, centre y, half width, half height, depth): boxes in front of the sun.
PILLARS = [_pillar(176.0, 4.0, 17.0), _pillar(193.0, 3.5, 15.0), _pillar(209.5, 3.5, 13.5), _pillar(227.0, 4.5, 12.0)]
BEAM = (201.0, BEAM_TOP + 4.0, 34.0, 4.0, 14.5)
BRACE = ((148.0, _ground_row(18.0)), (170.0, 62.0), 2.0, 18.0)  # from, to, half thickness, depth


def _box_coverage(x: np.ndarray, y: np.ndarray, cx: float, cy: float, hw: float, hh: float) -> np.ndarray:
    """Area of each pixel (1x1 box around its centre) inside an axis-aligned box."""
    ox = np.clip(np.minimum(x + 0.5, cx + hw) - np.maximum(x - 0.5, cx - hw), 0.0, 1.0)
    oy = np.clip(np.minimum(y + 0.5, cy + hh) - np.maximum(y - 0.5, cy - hh), 0.0, 1.0)
    return ox * oy


def _segment_coverage(x: np.ndarray, y: np.ndarray, a, b, half: float) -> np.ndarray:
    """Approximate pixel coverage of a thick line segment (distance ramp of 1 px)."""
    ax, ay = a
    dx, dy = b[0] - ax, b[1] - ay
    t = np.clip(((x - ax) * dx + (y - ay) * dy) / (dx * dx + dy * dy), 0.0, 1.0)
    dist = np.hypot(x - (ax + t * dx), y - (ay + t * dy))
    return np.clip(half + 0.5 - dist, 0.0, 1.0)


def make_sample_frame() -> Buffers:
    """The sample frame's buffers (NumPy float32 arrays inside a `Buffers`)."""
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float64) + 0.5

    # Sky: dim blue overhead to pale at the horizon, a faint halo, the sun disc.
    t = np.clip(y / HORIZON_Y, 0.0, 1.0)[..., None]
    sky = (1 - t) * np.array([0.10, 0.14, 0.28]) + t * np.array([0.45, 0.40, 0.34])
    r = np.hypot(x - SUN_XY[0], y - SUN_XY[1])
    sky = sky + 0.6 * np.exp(-r / 18.0)[..., None] * np.array([1.0, 0.8, 0.5])
    disc = np.clip(SUN_RADIUS + 0.5 - r, 0.0, 1.0)[..., None]
    color = (1 - disc) * sky + disc * SUN_COLOR
    depth = np.full((HEIGHT, WIDTH), np.inf)
    coverage = np.zeros((HEIGHT, WIDTH))

    # Ground: a plane below the camera, depth = height * focal / rows below the horizon.
    ground = _box_coverage(x, y, WIDTH / 2, (HORIZON_Y + HEIGHT) / 2, WIDTH, (HEIGHT - HORIZON_Y) / 2)
    below = np.maximum(y - HORIZON_Y, 0.5)
    ground_depth = CAMERA_HEIGHT * FOCAL_PX / below
    fade = np.exp(-ground_depth / 300.0)[..., None]  # lighter toward the horizon
    ground_color = fade * np.array([0.05, 0.04, 0.03]) + (1 - fade) * np.array([0.25, 0.22, 0.2])
    color = (1 - ground[..., None]) * color + ground[..., None] * ground_color
    depth = np.where(ground > 0, ground_depth, depth)
    coverage = ground

    # Occluders, drawn back to front: each covers what is behind it by its coverage.
    shapes = [(_box_coverage(x, y, *p[:4]), p[4]) for p in PILLARS]
    shapes.append((_box_coverage(x, y, *BEAM[:4]), BEAM[4]))
    shapes.append((_segment_coverage(x, y, *BRACE[:3]), BRACE[3]))
    for cov, dist in sorted(shapes, key=lambda s: -s[1]):
        shade = 0.02 + 0.02 * (y / HEIGHT)  # dark stone, a little lighter lower down
        stone = shade[..., None] * np.array([1.0, 0.9, 0.8])
        color = (1 - cov[..., None]) * color + cov[..., None] * stone
        coverage = cov + (1 - cov) * coverage
        depth = np.where(cov > 0, dist, depth)

    return Buffers(
        color=color.astype(np.float32),
        depth=depth.astype(np.float32),
        coverage=coverage.astype(np.float32),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    default = Path(__file__).resolve().parent / "data" / "sample_frame.exr"
    parser.add_argument("--out", type=Path, default=default, help=f"output EXR (default {default})")
    args = parser.parse_args()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_buffers(
        args.out,
        make_sample_frame(),
        light_xy=SUN_XY,
        light_in_front=True,
        half=True,
        metadata={"godrays:description": "godrays_jax sample frame: sun behind a colonnade"},
    )
    print(f"wrote {args.out} ({args.out.stat().st_size} bytes), light at {SUN_XY}")


if __name__ == "__main__":
    main()
