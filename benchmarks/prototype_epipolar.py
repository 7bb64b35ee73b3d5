"""A prototype, not the library's kernel: `VolumetricFog`'s shadows read per screen line through the light, and its shimmer.

    python benchmarks/prototype_epipolar.py [--cache FILE] [--converged DIR] [--lines 512] [--bins 192]
        [--radial-step 1] [--window 8] [--timing]

Why (benchmarks/README.md, "`volumetric_haze`'s three sources of shimmer"): the kernel reads each view
segment's shadow at one point, from a few samples of the depth buffer toward the light, on march rays
a few pixels apart, and each of the three samplings alone shimmers on a pan about as much as
`volumetric_haze` is allowed in all. This prototype replaces the three at once for the sun.

The model. Shadow rays toward the sun are parallel to its direction `d_L`, so along one the distance
from the camera's axis toward the sun is constant: with unit camera rays `d` and `g(d) = |d x d_L|`, the
point `t * d_p` of pixel `p`'s view ray and the surface point `D * d_q` of pixel `q` lie on one shadow ray
only where `t * g(d_p) = D * g(d_q)`, with `q` on the screen between `p` and the light. So along each
screen line through the light, every texel's slab `[D, D * (1 + thickness)]` (the kernel's) is an
interval of the one coordinate `s = D * g`, and a point at `s = t * g(d_p)` is in shadow where the
intervals of the texels from the light out to `p` cover `s`: the same test the kernel makes at each of
its samples, here for every texel along the line and every distance along the view ray.

Discretised: `--lines` lines through the light's position at even angles (they ride with the light
under a pan), each cut into cells `--radial-step` pixels long from the light outward (the step scales
with the frame's larger side over 320, so the look does not change with the size); in each cell the
four texels around its centre by bilinear weights, each texel's interval spanning the cell's range of
`g` (so that consecutive cells meet, as the kernel's consecutive samples' crossings do), soft over
`edge_softness` of `s` at both faces; their blend's maximum outward along the line is the coverage, on
`--bins` bins of `s` spaced evenly in `log s` (each texel touching the `--window` bins around its
interval; in the 16 cells nearest the light, where an interval spans many bins, every bin). Texels whose
slab reaches the light (the emitter) and sky block nothing. A pixel reads its two nearest lines up to its
own cell, and each segment of its own view ray (`resolution_factor` 1: every pixel marches) takes the
mean coverage over the segment's range of `s` (from a prefix sum over the bins), so a shadow's edge
inside a segment counts in proportion. Limits:
the light in front and on or near the screen; a light at a finite distance read as a sun in its
direction (the forest's sun is 5000 units away).

The script patches `godrays_jax.kernels.volumetric`'s `irradiance_median` (to keep each segment's
bounds) and `segment_visibility` (the read above) while it runs, and measures on `bench_shimmer.py`'s
sequence (`--cache` its file): the prototype at `volumetric_haze`'s fields and view steps, against its
own converged version (4x the lines and view steps, 2x the bins, half the radial step) and against the
kernel's converged version of the preset (`bench_shimmer.converged`, `--converged` its folder).
`--timing`: the forward pass at 320x180 and 1920x1080 on `bench_volumetric.py`'s frame, beside the
preset's.
"""

import argparse
import contextlib
import dataclasses
import math
import statistics
import sys
import time
from pathlib import Path
from unittest import mock

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_shimmer  # noqa: E402  (a sibling script)
import godrays_jax as gr  # noqa: E402
from godrays_jax.effects.presets import PRESETS  # noqa: E402
from godrays_jax.kernels import volumetric  # noqa: E402
from godrays_jax.kernels.bounded_medium import light_geometry  # noqa: E402
from godrays_jax.primitives.camera import focal_length_px  # noqa: E402

S_RANGE = (0.01, 200.0)  # the bins' span of `s` (scene units): the haze reaches 100 units, `g` is at most 1
NEAR_LIGHT = 16  # cells from the light in which every bin is tested (an interval there spans many); beyond, `--window`


def _off_axis(x, y, toward, height, width, focal):
    """`g`: the sine of the angle between each pixel position's camera ray and the light's direction."""
    rays = volumetric._rays_at(x, y, height, width, focal)
    return jnp.linalg.norm(jnp.cross(rays / jnp.linalg.norm(rays, axis=-1, keepdims=True), toward), axis=-1)


def coverage(depth, light_xy, toward, inverse, focal, thickness, softness, setting):
    """The prefix sum of each line's coverage at `s` = 0 and the bins' centres: `(lines, cells, bins + 1)`."""
    height, width = depth.shape
    lines, step, bins, window = setting["lines"], setting["radial_step"], setting["bins"], setting["window"]
    cells = int(math.ceil(math.hypot(width, height) / step)) + 2
    angle = 2 * math.pi * jnp.arange(lines) / lines
    radius = (jnp.arange(cells) + 0.5) * step
    cos, sin = jnp.cos(angle)[:, None], jnp.sin(angle)[:, None]
    x, y = light_xy[0] + radius * cos, light_xy[1] + radius * sin
    ends = []
    for end in (-0.5, 0.5):
        reach = jnp.maximum(radius + end * step, 0)
        ends.append(_off_axis(light_xy[0] + reach * cos, light_xy[1] + reach * sin, toward, height, width, focal))
    g, g_low, g_high = _off_axis(x, y, toward, height, width, focal), jnp.minimum(*ends), jnp.maximum(*ends)
    row, col, weight = volumetric._bilinear(x - 0.5, y - 0.5, height, width)
    front = depth[row, col]
    on_screen = (x >= 0) & (x <= width) & (y >= 0) & (y <= height)
    blocks = jnp.isfinite(front) & on_screen & (front * (1 + thickness) * inverse < 1.0)
    front = jnp.where(blocks, front, 1.0)
    log_low, log_step = math.log(S_RANGE[0]), (math.log(S_RANGE[1]) - math.log(S_RANGE[0])) / (bins - 1)
    centres = jnp.exp(log_low + log_step * jnp.arange(bins))
    line_index = jnp.broadcast_to(jnp.arange(lines)[None, :, None], (4, lines, window))

    def inside(s, middle, low, high):
        soft = softness * middle
        return volumetric._ramp((s - low) / soft) * volumetric._ramp((high * (1 + thickness) - s) / soft)

    def near(covered, cell):
        # Near the light `g` changes fast along a cell: its interval spans many bins, so every bin is tested.
        middle, low, high, w, b = (a[..., None] for a in cell)
        blend = jnp.sum(jnp.where(b, w * inside(centres, middle, low, high), 0.0), axis=0)
        covered = jnp.maximum(covered, blend)
        return covered, covered

    def far(covered, cell):
        middle, low, high, w, b = cell  # each (4, lines)
        first = jnp.floor((jnp.log(jnp.maximum(low, 1e-30)) - log_low) / log_step).astype(jnp.int32) - 1
        index = jnp.clip(first[..., None] + jnp.arange(window), 0, bins - 1)
        blocked = jnp.where(b[..., None], w[..., None] * inside(centres[index], *(a[..., None] for a in (middle, low, high))), 0.0)
        blend = jnp.zeros((lines, bins), depth.dtype).at[line_index, index].add(blocked)
        covered = jnp.maximum(covered, blend)
        return covered, covered

    per_cell = [jnp.moveaxis(a, -1, 0) for a in (front * g, front * g_low, front * g_high, weight, blocks)]
    split = min(NEAR_LIGHT, cells)
    covered, inner = jax.lax.scan(near, jnp.zeros((lines, bins), depth.dtype), [a[:split] for a in per_cell])
    _, outer = jax.lax.scan(far, covered, [a[split:] for a in per_cell])
    covered = jnp.moveaxis(jnp.concatenate([inner, outer]), 0, 1)
    # The prefix sum from s = 0 through the bins' centres, the coverage below the lowest bin taken as that bin's:
    # a view point there (near the light's own direction, where the phase function peaks) reads the first bin's.
    centres = jnp.concatenate([jnp.zeros(1), centres])
    covered = jnp.concatenate([covered[..., :1], covered], axis=-1)
    steps = 0.5 * (covered[..., 1:] + covered[..., :-1]) * jnp.diff(centres)
    return jnp.concatenate([jnp.zeros_like(covered[..., :1]), jnp.cumsum(steps, axis=-1)], axis=-1)


def _prefix_at(prefix, light_xy, pixel_xy, s, setting):
    """The coverage's prefix sum at `s` (`(h, w, M)`) for the pixels `pixel_xy`, trilinear in line, cell and bin."""
    lines, cells, bins = prefix.shape
    step = setting["radial_step"]
    dx, dy = pixel_xy[..., 0] - light_xy[0], pixel_xy[..., 1] - light_xy[1]
    a = jnp.mod(jnp.arctan2(dy, dx) / (2 * math.pi) * lines, lines)
    a0 = jnp.floor(a)
    fa = a - a0
    # Up to the pixel's own cell: the haze in front of a surface that hides the light lies in that surface's shadow.
    k = jnp.clip(jnp.sqrt(dx * dx + dy * dy) / step - 0.5, 0, cells - 1.001)
    k0 = jnp.floor(k)
    fk = k - k0
    log_low, log_step = math.log(S_RANGE[0]), (math.log(S_RANGE[1]) - math.log(S_RANGE[0])) / (bins - 2)
    above = 1 + (jnp.log(jnp.maximum(s, S_RANGE[0])) - log_low) / log_step
    b = jnp.clip(jnp.where(s < S_RANGE[0], s / S_RANGE[0], above), 0, bins - 1.001)
    b0 = jnp.floor(b)
    fb = b - b0
    a0, k0, b0 = a0.astype(jnp.int32), k0.astype(jnp.int32), b0.astype(jnp.int32)
    total = 0.0
    for ai, wa in ((a0 % lines, 1 - fa), ((a0 + 1) % lines, fa)):
        for ki, wk in ((k0, 1 - fk), (k0 + 1, fk)):
            for bi, wb in ((b0, 1 - fb), (b0 + 1, fb)):
                total = total + (wa * wk)[..., None] * wb * prefix[ai[..., None], ki[..., None], bi]
    return total


@contextlib.contextmanager
def epipolar(setting):
    """Within: `kernels.volumetric` reads each view segment's shadow from the lines' coverage (the module's docstring)."""
    bounds = {}
    median = volumetric.irradiance_median

    def keep_bounds(lower, upper, *rest):
        bounds["lower"], bounds["upper"] = lower, upper
        return median(lower, upper, *rest)

    def visibility(depth, light_xy, pixel_xy, distances, *, fov_x_deg, light_depth=math.inf, light_in_front=True,
                   thickness, edge_softness, num_shadow_samples):  # fmt: skip
        height, width = depth.shape
        dtype = depth.dtype
        light_xy = jnp.asarray(light_xy, dtype)
        toward, inverse = light_geometry(light_xy, height, width, fov_x_deg, light_depth, light_in_front, dtype)
        focal = focal_length_px(width, fov_x_deg, dtype)
        softness = jnp.maximum(jnp.asarray(edge_softness, dtype), 1e-6)
        prefix = coverage(depth, light_xy, toward, inverse, focal, jnp.asarray(thickness, dtype), softness, setting)
        g = _off_axis(pixel_xy[..., 0], pixel_xy[..., 1], toward, height, width, focal)[..., None]
        low, high = (jnp.clip(bounds[name] * g, 0.0, S_RANGE[1]) for name in ("lower", "upper"))
        span = high - low
        wide = span > 1e-6 * high
        mean = (_prefix_at(prefix, light_xy, pixel_xy, high, setting) - _prefix_at(prefix, light_xy, pixel_xy, low, setting))
        return 1.0 - jnp.clip(jnp.where(wide, mean / jnp.where(wide, span, 1.0), 0.0), 0.0, 1.0)

    with (
        mock.patch.object(volumetric, "irradiance_median", keep_bounds),
        mock.patch.object(volumetric, "segment_visibility", visibility),
    ):
        yield


def _with_counts(effect, **counts):
    with mock.patch("godrays_jax.effects.fields._check_static"), mock.patch("godrays_jax.effects.fields._check_fittable"):
        return dataclasses.replace(effect, **counts)


def _runner(effect):
    return jax.jit(lambda b, xy, front, depth: effect(b, xy, light_in_front=front, light_depth=depth), static_argnums=(2, 3))


def _codes(effect, frames, setting=None):
    run = _runner(effect)
    with epipolar(setting) if setting else contextlib.nullcontext():
        return [bench_shimmer.display_codes(run(b, xy, front, depth)) for b, xy, front, depth in frames]


def _timing(setting, repeats=3):
    from bench_volumetric import frame  # noqa: PLC0415  (a sibling script, only for --timing)

    for height, width in ((180, 320), (1080, 1920)):
        buffers, light = frame(height, width)
        scale = max(height, width) / 320
        scaled = dict(setting, radial_step=setting["radial_step"] * scale)
        prototype = _with_counts(gr.preset("volumetric_haze"), resolution_factor=1)
        cases = [("preset", gr.preset("volumetric_haze"), None, None), ("prototype, every pixel", prototype, scaled, None)]
        if scale > 1:
            # Its shadows on the kernel's march rays one pixel of a 320-wide frame apart, read by the chained read.
            cases.append(("prototype on march rays 1 px apart at 320 wide", _with_counts(prototype, resolution_factor=2),
                          scaled, scale))  # fmt: skip
        for label, candidate, patch, spacing in cases:
            spaced = mock.patch("godrays_jax.effects.volumetric.march_factor", lambda h, w, f, s=spacing: s)
            with epipolar(patch) if patch else contextlib.nullcontext(), spaced if spacing else contextlib.nullcontext():
                run = jax.jit(lambda b, l, e=candidate: e(b, l))
                run(buffers, light).block_until_ready()
                times = []
                for _ in range(repeats):
                    start = time.perf_counter()
                    run(buffers, light).block_until_ready()
                    times.append(time.perf_counter() - start)
            print(f"| {width}x{height} | {label} | {statistics.median(times):.3f} s |", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cache", default=None, help="bench_shimmer.py's frames file (made if missing)")
    parser.add_argument("--converged", default=None, help="bench_shimmer.py's folder of converged versions")
    parser.add_argument("--lines", type=int, default=512)
    parser.add_argument("--bins", type=int, default=192)
    parser.add_argument("--radial-step", type=float, default=1.0, help="pixels at 320 wide")
    parser.add_argument("--window", type=int, default=8)
    parser.add_argument("--timing", action="store_true")
    args = parser.parse_args()
    setting = dict(lines=args.lines, bins=args.bins, radial_step=args.radial_step, window=args.window)
    started = time.perf_counter()
    key = (320, 180, 12, 0.35)
    frames = bench_shimmer.cached_pan(args.cache, key)
    camera = gr.load_scene(bench_shimmer.SCENE)[1]
    preset = bench_shimmer.with_camera(PRESETS["volumetric_haze"](), camera)
    kernels_reference = bench_shimmer.converged(preset, 32)
    kernels = bench_shimmer.converged_codes(args.converged, key, kernels_reference, _runner(kernels_reference), frames)
    effect = _with_counts(preset, resolution_factor=1)
    own = _codes(effect, frames, setting)
    finer = dict(lines=4 * args.lines, bins=2 * args.bins, radial_step=args.radial_step / 2, window=2 * args.window)
    own_reference = _codes(_with_counts(effect, num_view_steps=4 * effect.num_view_steps), frames, finer)
    print(f"prototype {setting}, volumetric_haze's fields at resolution_factor 1 and {effect.num_view_steps} view steps")
    print("| against | change RMS | change p99 | error RMS |")
    print("|---|---|---|---|")
    for label, reference in ((f"its own converged version {finer}, {4 * effect.num_view_steps} view steps", own_reference),
                             ("the kernel's converged version of volumetric_haze (bench_shimmer.py)", kernels)):  # fmt: skip
        rms, p99, error = bench_shimmer.shimmer([a - b for a, b in zip(own, reference)])
        print(f"| {label} | {rms:.2f} | {p99:.2f} | {error:.2f} |", flush=True)
    rms, p99, error = bench_shimmer.shimmer([a - b for a, b in zip(own_reference, kernels)])
    print(f"| (its converged version against the kernel's) | {rms:.2f} | {p99:.2f} | {error:.2f} |")
    print(f"total {time.perf_counter() - started:.0f} s")
    if args.timing:
        print("| frame | forward | median of 3 |")
        print("|---|---|---|")
        _timing(setting)


if __name__ == "__main__":
    main()
