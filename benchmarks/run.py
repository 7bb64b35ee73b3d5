"""Speed, memory and accuracy of godrays_jax's ray kernels against the peers a user would otherwise use.

    python benchmarks/run.py [--size 1920x1080] [--repeats 3] [--budget 30] [--skip-grad]

Every case renders seed 003's radial rays (128 samples, density .5, decay .95,
weight 1, exposure .15) or kbEngine's flare-outs (20 copies x1.03) of the same
occlusion image (a bright disc behind occluders, RGB float32, light on screen)
and is timed in this one run: median wall time of `--repeats` runs (JAX cases
compiled ahead of time, compilation excluded; peers warmed up by their memory
run; a case stops repeating once it has used `--budget` seconds). PSNR is against the exact JAX loop (peak = its maximum).
Memory: XLA's buffers for the compiled JAX function (arguments + outputs +
temporaries, `memory_analysis()`), Python's tracemalloc peak for the NumPy and
OpenCV peers (their arrays); PyTorch's and CuPy's allocations are not tracked
(n/a). Peers (NumPy, OpenCV, PyTorch CPU, CuPy on
a GPU) are optional: a missing one is skipped with a note.
"""

import argparse
import math
import os
import platform
import statistics
import sys
import time
import tracemalloc

import jax
import jax.numpy as jnp
import numpy as np

import godrays_jax as gr
from godrays_jax.kernels import fast

TRACED_PEERS = ("numpy", "opencv")  # their arrays are NumPy's, which tracemalloc sees
RAYS = dict(num_samples=128, density=0.5, decay=0.95, weight=1.0, exposure=0.15)
FLARES = dict(num_iters=20, scale_step=1.03)


def occlusion_image(height, width, light):
    """A disc of radius width/25 at the light, cut by circular occluders and a ground band."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float32) + 0.5
    radius = width / 25
    disc = 2 * np.clip(1 - np.hypot(x - light[0], y - light[1]) / radius, 0, 1) ** 2
    rng = np.random.default_rng(5)
    for _ in range(25):
        cx, cy, r = light[0] + rng.normal() * 2 * radius, light[1] + rng.normal() * 2 * radius, rng.random() * radius * 0.5
        disc[np.hypot(x - cx, y - cy) < r] = 0
    disc[int(height * 0.75) :] = 0
    return np.repeat(disc[..., None], 3, axis=-1).astype(np.float32)


# ---- peers: each is what a user would write for the same seed-003 loop / kbEngine flares ----


def numpy_rays(image, light, num_samples, density, decay, weight, exposure):
    height, width, _ = image.shape
    flat = image.reshape(-1, image.shape[2])
    y, x = np.mgrid[0:height, 0:width].astype(np.float32) + 0.5
    step_x, step_y = (x - light[0]) * (density / num_samples), (y - light[1]) * (density / num_samples)
    total = image.copy()
    illumination = 1.0
    for i in range(1, num_samples + 1):
        u = np.clip(x - i * step_x - 0.5, 0, width - 1)
        v = np.clip(y - i * step_y - 0.5, 0, height - 1)
        u0, v0 = np.floor(u), np.floor(v)
        fu, fv = (u - u0)[..., None], (v - v0)[..., None]
        u0, v0 = u0.astype(np.int32), v0.astype(np.int32)
        u1, v1 = np.minimum(u0 + 1, width - 1), np.minimum(v0 + 1, height - 1)
        top = flat[v0 * width + u0] * (1 - fu) + flat[v0 * width + u1] * fu
        bottom = flat[v1 * width + u0] * (1 - fu) + flat[v1 * width + u1] * fu
        total += (illumination * weight) * (top * (1 - fv) + bottom * fv)
        illumination *= decay
    return total * exposure


def numpy_flares(masked, light, num_iters, scale_step):
    height, width, channels = masked.shape
    padded = np.pad(masked, ((1, 2), (1, 2), (0, 0)))
    y, x = np.mgrid[0:height, 0:width].astype(np.float32) + 0.5
    total = np.zeros_like(masked)
    for k in range(num_iters):
        shrink = scale_step ** (-k)
        u = np.clip(light[0] + (x - light[0]) * shrink - 0.5, -1, width) + 1
        v = np.clip(light[1] + (y - light[1]) * shrink - 0.5, -1, height) + 1
        u0, v0 = np.floor(u), np.floor(v)
        fu, fv = (u - u0)[..., None], (v - v0)[..., None]
        u0, v0 = u0.astype(np.int32), v0.astype(np.int32)
        top = padded[v0, u0] * (1 - fu) + padded[v0, u0 + 1] * fu
        bottom = padded[v0 + 1, u0] * (1 - fu) + padded[v0 + 1, u0 + 1] * fu
        total += top * (1 - fv) + bottom * fv
    return total


def opencv_peers():
    import cv2

    def rays(image, light, num_samples, density, decay, weight, exposure):
        height, width, _ = image.shape
        y, x = np.mgrid[0:height, 0:width].astype(np.float32)
        # remap reads texel centres at integer coordinates: pixel centre p + 0.5 is texel p.
        offset_x, offset_y = x + 0.5 - light[0], y + 0.5 - light[1]
        total = image.copy()
        illumination = 1.0
        for i in range(1, num_samples + 1):
            scale = 1 - i * density / num_samples
            map_x = (light[0] - 0.5) + offset_x * scale
            map_y = (light[1] - 0.5) + offset_y * scale
            total += (illumination * weight) * cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            illumination *= decay
        return total * exposure

    def flares(masked, light, num_iters, scale_step):
        height, width, _ = masked.shape
        total = np.zeros_like(masked)
        for k in range(num_iters):
            shrink = scale_step ** (-k)
            # dst(p) = src(M p) with WARP_INVERSE_MAP; in texel coordinates the centre is light - 0.5.
            cx, cy = light[0] - 0.5, light[1] - 0.5
            matrix = np.array([[shrink, 0, cx * (1 - shrink)], [0, shrink, cy * (1 - shrink)]], np.float64)
            total += cv2.warpAffine(masked, matrix, (width, height), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                    borderMode=cv2.BORDER_CONSTANT, borderValue=0)  # fmt: skip
        return total

    return rays, flares


def torch_peers():
    import torch

    def grid(height, width, light, scale):
        y, x = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
        return x - light[0], y - light[1]

    def rays(image, light, num_samples, density, decay, weight, exposure):
        height, width, _ = image.shape
        with torch.no_grad():
            source = torch.from_numpy(image).permute(2, 0, 1)[None]
            offset_x, offset_y = grid(height, width, light, 1.0)
            total = source.clone()
            illumination = 1.0
            for i in range(1, num_samples + 1):
                scale = 1 - i * density / num_samples
                points = torch.stack([(light[0] + offset_x * scale) * (2 / width) - 1, (light[1] + offset_y * scale) * (2 / height) - 1], -1)
                total += (illumination * weight) * torch.nn.functional.grid_sample(
                    source, points[None], mode="bilinear", padding_mode="border", align_corners=False
                )
                illumination *= decay
            return (total * exposure)[0].permute(1, 2, 0).numpy()

    def flares(masked, light, num_iters, scale_step):
        height, width, _ = masked.shape
        with torch.no_grad():
            source = torch.from_numpy(masked).permute(2, 0, 1)[None]
            offset_x, offset_y = grid(height, width, light, 1.0)
            total = torch.zeros_like(source)
            for k in range(num_iters):
                shrink = scale_step ** (-k)
                points = torch.stack([(light[0] + offset_x * shrink) * (2 / width) - 1, (light[1] + offset_y * shrink) * (2 / height) - 1], -1)
                total += torch.nn.functional.grid_sample(source, points[None], mode="bilinear", padding_mode="zeros", align_corners=False)
            return total[0].permute(1, 2, 0).numpy()

    return rays, flares, f"torch {torch.__version__}, {torch.get_num_threads()} threads"


CUDA_RAYS = r"""
extern "C" __global__ void rays(const float* image, float* out, int width, int height, int channels,
                                float light_x, float light_y, int num_samples, float density,
                                float decay, float weight, float exposure) {
    int col = blockIdx.x * blockDim.x + threadIdx.x, row = blockIdx.y * blockDim.y + threadIdx.y;
    if (col >= width || row >= height) return;
    float px = col + 0.5f, py = row + 0.5f;
    float dx = (px - light_x) * density / num_samples, dy = (py - light_y) * density / num_samples;
    float colour[4], illumination = 1.0f;
    for (int c = 0; c < channels; ++c) colour[c] = image[(row * width + col) * channels + c];
    for (int i = 0; i < num_samples; ++i) {
        px -= dx; py -= dy;
        float u = fminf(fmaxf(px - 0.5f, 0.0f), width - 1.0f), v = fminf(fmaxf(py - 0.5f, 0.0f), height - 1.0f);
        int u0 = (int)floorf(u), v0 = (int)floorf(v);
        int u1 = min(u0 + 1, width - 1), v1 = min(v0 + 1, height - 1);
        float fu = u - u0, fv = v - v0;
        for (int c = 0; c < channels; ++c) {
            float top = image[(v0 * width + u0) * channels + c] * (1 - fu) + image[(v0 * width + u1) * channels + c] * fu;
            float bottom = image[(v1 * width + u0) * channels + c] * (1 - fu) + image[(v1 * width + u1) * channels + c] * fu;
            colour[c] += (top * (1 - fv) + bottom * fv) * illumination * weight;
        }
        illumination *= decay;
    }
    for (int c = 0; c < channels; ++c) out[(row * width + col) * channels + c] = colour[c] * exposure;
}
"""


def cupy_peer():
    import cupy

    if cupy.cuda.runtime.getDeviceCount() < 1:
        raise ImportError("no CUDA device")
    kernel = cupy.RawKernel(CUDA_RAYS, "rays")
    on_device = {}

    def rays(image, light, num_samples, density, decay, weight, exposure):
        """The kernel alone, like the JAX cases: the image is copied to the GPU once, the result stays there."""
        height, width, channels = image.shape
        if id(image) not in on_device:
            on_device[id(image)] = (image, cupy.asarray(image))
        source = on_device[id(image)][1]
        out = cupy.empty_like(source)
        block = (16, 16)
        grid = ((width + 15) // 16, (height + 15) // 16)
        f32 = np.float32
        kernel(grid, block, (source, out, np.int32(width), np.int32(height), np.int32(channels), f32(light[0]), f32(light[1]),
                             np.int32(num_samples), f32(density), f32(decay), f32(weight), f32(exposure)))  # fmt: skip
        cupy.cuda.Device().synchronize()
        return out

    return rays


# ---- measurement ----


def timed(function, repeats, budget):
    """Median seconds of up to `repeats` calls (JAX cases are compiled ahead, peers warmed by the memory run)."""
    result = None
    times = []
    started = time.perf_counter()
    for _ in range(repeats):
        begin = time.perf_counter()
        result = function()
        times.append(time.perf_counter() - begin)
        if time.perf_counter() - started > budget:
            break
    return statistics.median(times), len(times), result


def psnr(actual, reference):
    actual = actual.get() if hasattr(actual, "get") else actual  # a CuPy array, still on the GPU
    error = np.mean((np.asarray(actual, np.float64) - reference) ** 2)
    return math.inf if error == 0 else 10 * math.log10(reference.max() ** 2 / error)


def jax_case(function, *args):
    compiled = jax.jit(function).lower(*args).compile()
    memory = compiled.memory_analysis()
    peak = memory.temp_size_in_bytes + memory.argument_size_in_bytes + memory.output_size_in_bytes
    return (lambda: jax.block_until_ready(compiled(*args))), peak


def host_case(function, *args):
    tracemalloc.start()
    function(*args)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return (lambda: function(*args)), peak


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", default="1920x1080", help="WIDTHxHEIGHT (default 1920x1080)")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per case after a warm-up (default 3)")
    parser.add_argument("--budget", type=float, default=30.0, help="stop repeating a case after this many seconds (default 30)")
    parser.add_argument("--skip-grad", action="store_true", help="skip the value-and-gradient cases")
    parser.add_argument("--skip-numpy", action="store_true", help="skip the (slowest) NumPy peer")
    options = parser.parse_args(argv)
    width, height = (int(v) for v in options.size.lower().split("x"))
    light = (0.42 * width, 0.33 * height)
    image = occlusion_image(height, width, light)
    image_jax, light_jax = jnp.asarray(image), jnp.asarray(light, jnp.float32)

    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, {platform.system()}; "
          f"python {platform.python_version()}, jax {jax.__version__} on {jax.devices()[0].platform}")  # fmt: skip
    print(f"image {width}x{height}x3 float32, light at ({light[0]:.0f}, {light[1]:.0f}); repeats {options.repeats}, budget {options.budget:.0f} s")

    rows = []  # (group, case, seconds, runs, bytes, psnr)

    def add(group, name, runner, peak, reference):
        seconds, runs, result = timed(runner, options.repeats, options.budget)
        quality = psnr(result, reference) if reference is not None else math.nan
        rows.append((group, name, seconds, runs, peak, quality))
        memory = f"{peak / 2**20:.0f} MiB" if peak is not None else "n/a"
        print(f"  {group:6s} {name:38s} {seconds * 1e3:10.1f} ms  ({runs} runs)  {memory:>9s}  PSNR {quality:6.1f} dB", flush=True)
        return result

    ray_kernel = lambda i, l: gr.radial_rays(i, l, **RAYS)
    runner, peak = jax_case(ray_kernel, image_jax, light_jax)
    exact = np.asarray(runner())
    add("rays", "jax exact loop (radial_rays)", runner, peak, exact)
    variants = {
        "jax fast_radial_rays (1/2 res, 3x8) *": lambda i, l: fast.fast_radial_rays(i, l, **RAYS),
        "jax fast_radial_rays (1/4 res, 3x8)": lambda i, l: fast.fast_radial_rays(i, l, resolution_factor=4, **RAYS),
        "jax radial_rays_multipass (full, 3x8)": lambda i, l: fast.radial_rays_multipass(i, l, **RAYS),
        "jax exact loop at 1/2 res": lambda i, l: fast.at_reduced_resolution(i, l, kernel=gr.radial_rays, resolution_factor=2, **RAYS),
        "jax jittered, 16 samples, 1/2 res": lambda i, l: fast.at_reduced_resolution(
            i, l, kernel=fast.radial_rays_jittered, resolution_factor=2, **{**RAYS, "num_samples": 16}
        ),
        "jax exact loop, 16 samples": lambda i, l: gr.radial_rays(i, l, **{**RAYS, "num_samples": 16}),
    }
    for name, kernel in variants.items():
        add("rays", name, *jax_case(kernel, image_jax, light_jax), exact)
    if not options.skip_grad:
        def loss(image, light, density, decay, exposure):
            rays = gr.radial_rays(image, light, num_samples=128, density=density, decay=decay, weight=1.0, exposure=exposure)
            return jnp.sum(rays**2)

        value_and_grad = jax.value_and_grad(loss, argnums=(0, 1, 2, 3, 4))
        runner, peak = jax_case(value_and_grad, image_jax, light_jax, 0.5, 0.95, 0.15)
        add("grad", "jax exact loop, value+grad (all args)", runner, peak, None)
        fast_loss = lambda i, l, d, dec, e: jnp.sum(fast.fast_radial_rays(i, l, num_samples=128, density=d, decay=dec, weight=1.0, exposure=e) ** 2)
        runner, peak = jax_case(jax.value_and_grad(fast_loss, argnums=(0, 1, 2, 3, 4)), image_jax, light_jax, 0.5, 0.95, 0.15)
        add("grad", "jax fast_radial_rays, value+grad", runner, peak, None)

    peers = {}
    if not options.skip_numpy:
        peers["numpy"] = (numpy_rays, numpy_flares, f"numpy {np.__version__}")
    try:
        import cv2

        peers["opencv"] = (*opencv_peers(), f"opencv {cv2.__version__}")
    except ImportError as error:
        print(f"note: OpenCV peer skipped ({error}); pip install opencv-python-headless")
    try:
        peers["torch"] = torch_peers()
    except ImportError as error:
        print(f"note: PyTorch peer skipped ({error}); pip install torch (CPU build)")
    try:
        peers["cupy"] = (cupy_peer(), None, "cupy RawKernel on the GPU")
    except Exception as error:  # no cupy, no driver, no device: all mean "no GPU peer"
        print(f"note: CUDA peer skipped (no GPU / CuPy: {type(error).__name__}); GPU figures not measured")
    for name, (rays, _, version) in peers.items():
        print(f"peer {name}: {version}")
        runner, peak = host_case(rays, image, light, *RAYS.values())
        add("rays", f"peer {name}", runner, peak if name in TRACED_PEERS else None, exact)

    flare_kernel = lambda m, l: gr.scale_iterated_flares(m, l, **FLARES)
    runner, peak = jax_case(flare_kernel, image_jax, light_jax)
    exact_flares = np.asarray(runner())
    add("flares", "jax scale_iterated_flares", runner, peak, exact_flares)
    add("flares", "jax flares at 1/2 res", *jax_case(
        lambda m, l: fast.at_reduced_resolution(m, l, kernel=gr.scale_iterated_flares, resolution_factor=2, **FLARES), image_jax, light_jax
    ), exact_flares)  # fmt: skip
    for name, (_, flares, _) in peers.items():
        if flares is not None:
            runner, peak = host_case(flares, image, light, *FLARES.values())
            add("flares", f"peer {name}", runner, peak if name in TRACED_PEERS else None, exact_flares)

    print()
    print("| case | resolution | median time | peak memory | PSNR vs exact | " + " | ".join(f"x vs {p}" for p in peers) + " |")
    print("|---|---|---|---|---|" + "---|" * len(peers))
    for group, name, seconds, runs, peak, quality in rows:
        peer_times = {n.removeprefix("peer "): s for g, n, s, _, _, _ in rows if g == group and n.startswith("peer ")}
        ratios = " | ".join(f"{peer_times[p] / seconds:.2f}" if p in peer_times else "-" for p in peers)
        memory = f"{peak / 2**20:.0f} MiB" if peak is not None else "n/a"
        quality_text = "-" if math.isnan(quality) else ("exact" if math.isinf(quality) else f"{quality:.1f} dB")
        milliseconds = f"{seconds * 1e3:.0f}" if seconds >= 0.01 else f"{seconds * 1e3:.2f}"  # GPU cases: under 1 ms
        print(f"| {group}: {name} | {width}x{height} | {milliseconds} ms ({runs}) | {memory} | {quality_text} | {ratios} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
