"""Batch throughput: frames/s of `run_batch` on a shot of half-float EXR frames, and where the time goes.

Run as a script (timings are never taken in unit tests):

    python benchmarks/bench_batch.py                       # 100 frames, 1920x1080, the CLI's default preset
    python benchmarks/bench_batch.py --frames 20 --width 960 --height 540

The frames are the sample frame scaled up (nearest) to the requested size,
the light moving a little each frame, written as the renderer would: R, G, B, A
as half floats, Z as float, zip, the light in the metadata. Measured in the
same run, on the same frames:

- io_only: read + write of every frame with the batch's own thread layout
  (reads on `io_threads` threads, writes on `io_threads` others), no effect:
  the ceiling any effect can reach on this disk and CPU.
- effect_only: the jitted effect on one frame already in memory, repeated
  (median per frame).
- batch: `run_batch` over all the frames (reads and writes overlapping the
  effect), with its thread-time split between reading, computing and writing.
- sequential: read, effect, write, one frame after the other, no overlap, on
  the first `--sequential-frames` frames (median per frame).

Prints one JSON object; `batch_vs_io_only` is the batch's frames/s over the
I/O-only frames/s (1 = the effect costs nothing; the goal is >= 0.5).
"""

import argparse
import concurrent.futures
import json
import os
import statistics
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

import godrays_jax as gr
from godrays_jax.pipeline import batch, sequences
from godrays_jax.app.options import DEFAULT_PRESET
from godrays_jax.primitives.frame_files import read_frame, write_frame_like

SAMPLE = os.path.join(os.path.dirname(__file__), "..", "examples", "data", "sample_frame.exr")


def make_shot(folder: str, count: int, height: int, width: int) -> list[str]:
    sample = gr.read_buffers(SAMPLE)
    (light_x, light_y), _ = gr.read_light(SAMPLE)
    rows = (np.arange(height) * sample.height) // height
    cols = (np.arange(width) * sample.width) // width
    frame = gr.Buffers(
        color=np.asarray(sample.color)[rows][:, cols],
        depth=np.asarray(sample.depth)[rows][:, cols],
        coverage=np.asarray(sample.coverage)[rows][:, cols],
    )
    scale = width / sample.width
    paths = []
    for number in range(1, count + 1):
        path = os.path.join(folder, f"shot.{number:04d}.exr")
        gr.write_buffers(path, frame, light_xy=((light_x + number) * scale, light_y * scale), half=True)
        paths.append(path)
    return paths


def io_only(paths: list[str], out_dir: str, io_threads: int) -> float:
    """Seconds to read and write every frame with the batch's thread layout and no effect."""
    start = time.perf_counter()
    with (
        concurrent.futures.ThreadPoolExecutor(io_threads) as readers,
        concurrent.futures.ThreadPoolExecutor(io_threads) as writers,
    ):
        writes = []
        for path, (buffers, stored) in zip(paths, readers.map(read_frame, paths)):
            out = os.path.join(out_dir, os.path.basename(path))
            writes.append(writers.submit(write_frame_like, out, np.asarray(buffers.color), stored))
        for write in writes:
            write.result()
    return time.perf_counter() - start


def effect_only(effect, path: str, repeats: int) -> list[float]:
    buffers = gr.read_buffers(path)
    light, in_front = gr.read_light(path)
    apply = jax.jit(lambda b, l: effect(b, l, light_in_front=in_front))
    light = jnp.asarray(light, jnp.float32)
    apply(buffers, light).block_until_ready()  # compile
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        apply(buffers, light).block_until_ready()
        times.append(time.perf_counter() - start)
    return times


def sequential(effect, paths: list[str], out_dir: str) -> list[float]:
    apply = jax.jit(lambda b, l, f: effect(b, l, light_in_front=f))
    times = []
    for index, path in enumerate(paths):
        start = time.perf_counter()
        buffers, stored = read_frame(path)
        light, in_front = gr.read_light(path)
        image = np.asarray(apply(buffers, jnp.asarray(light, jnp.float32), jnp.asarray(in_front)))
        write_frame_like(os.path.join(out_dir, os.path.basename(path)), image, stored)
        if index > 0:  # the first one compiles
            times.append(time.perf_counter() - start)
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--width", type=int, default=1920)
    parser.add_argument("--height", type=int, default=1080)
    parser.add_argument("--preset", default=DEFAULT_PRESET)
    parser.add_argument("--io-threads", type=int, default=2)
    parser.add_argument("--effect-repeats", type=int, default=5)
    parser.add_argument("--sequential-frames", type=int, default=6)
    args = parser.parse_args()
    effect = gr.preset(args.preset)

    with tempfile.TemporaryDirectory(prefix="bench_batch_") as folder:
        shot = os.path.join(folder, "in")
        os.makedirs(shot)
        paths = make_shot(shot, args.frames, args.height, args.width)
        frame_mb = sum(os.path.getsize(p) for p in paths) / len(paths) / 2**20

        io_dir = os.path.join(folder, "io_only")
        os.makedirs(io_dir)
        io_s = io_only(paths, io_dir, args.io_threads)

        effect_times = effect_only(effect, paths[0], args.effect_repeats)

        jobs = batch.plan_batch(paths, os.path.join(folder, "batch"))
        os.makedirs(os.path.join(folder, "batch"))
        report = batch.run_batch(jobs, effect, sequences.METADATA, io_threads=args.io_threads, progress=None)
        assert not report.failures, report.failures

        sequential_dir = os.path.join(folder, "sequential")
        os.makedirs(sequential_dir)
        sequential_times = sequential(effect, paths[: args.sequential_frames], sequential_dir)

    thread_total = report.read_s + report.compute_s + report.write_s
    io_fps = args.frames / io_s
    batch_fps = len(report.written) / report.wall_s
    print(json.dumps({
        "frames": args.frames, "size": f"{args.width}x{args.height}", "preset": args.preset,
        "devices": [str(d) for d in jax.local_devices()], "cpu_count": os.cpu_count(),
        "frame_file_mb": round(frame_mb, 2),
        "io_only_frames_per_s": round(io_fps, 3),
        "effect_only_median_s": round(statistics.median(effect_times), 4),
        "batch_frames_per_s": round(batch_fps, 3),
        "batch_wall_s": round(report.wall_s, 2),
        "batch_compilations": report.compilations,
        "batch_thread_s": {"read": round(report.read_s, 2), "compute": round(report.compute_s, 2),
                           "write": round(report.write_s, 2)},
        "batch_io_share": round((report.read_s + report.write_s) / thread_total, 3),
        "sequential_median_s_per_frame": round(statistics.median(sequential_times), 4),
        "batch_vs_io_only": round(batch_fps / io_fps, 3),
        "batch_vs_sequential": round(batch_fps * statistics.median(sequential_times), 3),
    }, indent=2))  # fmt: skip


if __name__ == "__main__":
    main()
