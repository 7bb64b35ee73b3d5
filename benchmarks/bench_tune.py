"""Tuner latency at 960x540: server-side render and PNG time, HTTP round trip, against a bare jitted render.

Run as a script: `python benchmarks/bench_tune.py [--presets xna_crepuscular,kbengine_flares] [--repeats 15]`.
The frame is examples/data/sample_frame.exr upscaled 3x (960x540). Each request
moves a parameter (so nothing is cached), after the compilation (`warm_up`).
Prints medians in ms: `preview` (the tuner's drag render, 1/preview_factor
resolution), `full` (release render), and the peer: the same effect called
under `eqx.filter_jit` at full resolution with its result copied to the host
(no server, no encoding). Then a burst of concurrent requests shows coalescing.
"""

import argparse
import http.client
import json
import os
import statistics
import threading
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import godrays_jax as gr
from godrays_jax.primitives.buffers import Buffers
from godrays_jax.app.server import HOST, TOKEN_HEADER, TuneServer
from godrays_jax.app.tuner import Tuner

SAMPLE = os.path.join(os.path.dirname(__file__), "..", "examples", "data", "sample_frame.exr")


def upscaled_frame(scale: int) -> tuple[Buffers, tuple[float, float]]:
    frame = gr.read_buffers(SAMPLE)
    (x, y), _ = gr.read_light(SAMPLE)
    height, width = frame.height * scale, frame.width * scale
    depth = jnp.repeat(jnp.repeat(frame.depth, scale, axis=0), scale, axis=1)
    return (
        Buffers(
            color=jax.image.resize(frame.color, (height, width, 3), "linear"),
            depth=depth,
            coverage=jax.image.resize(frame.coverage, (height, width), "linear"),
        ),
        (x * scale, y * scale),
    )


def post(server: TuneServer, body: dict) -> tuple[int, dict, float]:
    """One render request as the page sends it (JSON, the server's per-launch token): status, answer, round-trip ms."""
    connection = http.client.HTTPConnection(HOST, server.port, timeout=600)
    started = time.perf_counter()
    headers = {"Content-Type": "application/json", TOKEN_HEADER: server.token}
    connection.request("POST", "/api/render", body=json.dumps(body), headers=headers)
    response = connection.getresponse()
    answer = json.loads(response.read())
    elapsed = (time.perf_counter() - started) * 1000.0
    connection.close()
    return response.status, answer, elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", default="xna_crepuscular,kbengine_flares")
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--preview-pixels", type=int, default=40_000)
    args = parser.parse_args()
    frame, light = upscaled_frame(3)
    print(f"frame {frame.width}x{frame.height}, {jax.devices()[0].device_kind}, {os.cpu_count()} CPU cores")
    for name in args.presets.split(","):
        effect = gr.preset(name)
        field = next(iter(gr.parameter_bounds(effect)))
        low, high = gr.parameter_bounds(effect)[field]
        start = float(gr.field_value(effect, field))
        values = np.linspace(start, (start + high) / 2, args.repeats)
        tuner = Tuner(frame, light, effect=effect, max_preview_pixels=args.preview_pixels)
        with TuneServer(tuner) as server:
            started = time.perf_counter()
            server.warm_up()
            compile_s = time.perf_counter() - started
            rows = {}
            for quality in ("preview", "full"):
                render, encode, trip = [], [], []
                for value in values:
                    status, answer, elapsed = post(server, {"quality": quality, "params": {field: float(value)}})
                    assert status == 200, answer
                    render.append(answer["render_ms"])
                    encode.append(answer["encode_ms"])
                    trip.append(elapsed)
                rows[quality] = (statistics.median(render), statistics.median(encode), statistics.median(trip))
            jitted = eqx.filter_jit(lambda e, b, l: e(b, l))
            light_array = jnp.asarray(light, jnp.float32)
            np.asarray(jitted(effect, frame, light_array))
            bare = []
            for value in values:
                moved = gr.replace_fields(effect, {field: jnp.asarray(value, jnp.float32)})
                t0 = time.perf_counter()
                np.asarray(jitted(moved, frame, light_array))
                bare.append((time.perf_counter() - t0) * 1000.0)
            bare_ms = statistics.median(bare)

            answers = []
            threads = [
                threading.Thread(target=lambda v=v: answers.append(post(server, {"quality": "preview",
                                                                                       "params": {field: float(v)}})[0]))
                for v in values[:8]
            ]  # fmt: skip
            for thread in threads:
                thread.start()
            for thread in threads:
                thread.join()
        print(f"\n{name}: compile (preview + full) {compile_s:.1f} s; preview factor {tuner.factor} "
              f"({-(-frame.width // tuner.factor)}x{-(-frame.height // tuner.factor)}); {args.repeats} requests, medians:")  # fmt: skip
        print(f"  {'':8s} {'render':>9s} {'png':>7s} {'round trip':>11s} {'vs bare full':>13s}")
        for quality, (render, encode, trip) in rows.items():
            print(f"  {quality:8s} {render:7.1f}ms {encode:5.1f}ms {trip:9.1f}ms {trip / bare_ms:12.2f}x")
        print(f"  bare jitted full-resolution render (peer): {bare_ms:.1f} ms")
        print(f"  burst of 8 concurrent requests: {answers.count(200)} rendered, {answers.count(409)} superseded (409)")


if __name__ == "__main__":
    main()
