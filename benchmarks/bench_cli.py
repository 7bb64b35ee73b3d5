"""Whole-command start-up: `godrays-jax apply` and `fit` with a cold and a warm compilation cache, and without it.

Run as a script from the repository root: `python benchmarks/bench_cli.py [--repeats 5]`. Each
command runs as a fresh process (what a render farm or a shell loop pays); the cache lives in a
temporary folder (`GODRAYS_JAX_CACHE_DIR`; with it, `fit` also stores its traced programs,
`pipeline/exported.py`). The sample frame is fitted with the default steps against the `xna_crepuscular`
preset applied to it (written first). Prints per case the median wall and CPU seconds (user +
system of the child) over the repeats, and the load average, since the machine may be shared.
"""

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SAMPLE = ROOT / "examples" / "data" / "sample_frame.exr"
COLONNADE = ROOT / "tests" / "data" / "colonnade_buffers.exr"


def timed(command: list[str], env: dict) -> tuple[float, float]:
    """Wall and CPU seconds of one run of `command` in a fresh process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    done = subprocess.run(command, env=env, cwd=ROOT, capture_output=True, text=True)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        sys.exit(f"{' '.join(command)} failed: {done.stderr.strip().splitlines()[-1:]}")
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    out = tempfile.mkdtemp(prefix="godrays-bench-cli-")
    cli = [sys.executable, "-m", "godrays_jax"]
    target = f"{out}/target.exr"
    timed([*cli, "apply", str(SAMPLE), "--preset", "xna_crepuscular", "-o", target, "--no-cache"], dict(os.environ))
    cases = {
        "apply kbengine_flares": [*cli, "apply", str(SAMPLE), "--preset", "kbengine_flares", "-o", f"{out}/a.png"],
        "apply xna_crepuscular": [*cli, "apply", str(SAMPLE), "--preset", "xna_crepuscular", "-o", f"{out}/b.png"],
        "fit (ScatteringFog, 10 steps)": [*cli, "fit", str(COLONNADE), str(COLONNADE), "--preset", "participating_media",
                                          "--light", "142.84,84.85", "--max-steps", "10", "-o", f"{out}/p.json"],
        "fit sample frame (ScatteringFog, default steps)": [*cli, "fit", str(SAMPLE), target, "--preset",
                                                            "participating_media", "-o", f"{out}/q.json"],
    }
    print(f"load average {os.getloadavg()[0]:.2f}; {args.repeats} runs each, medians (wall s / cpu s)")
    print(f"| command | no cache | cold cache (first run) | warm cache |\n|---|---|---|---|")
    for name, command in cases.items():
        env = dict(os.environ, GODRAYS_JAX_CACHE_DIR=tempfile.mkdtemp(prefix="godrays-cache-"))
        cold = timed(command, env)
        warm = [timed(command, env) for _ in range(args.repeats)]
        none = [timed([*command, "--no-cache"], env) for _ in range(args.repeats)]

        def median(runs):
            return f"{statistics.median(r[0] for r in runs):.2f} / {statistics.median(r[1] for r in runs):.2f}"

        print(f"| {name} | {median(none)} | {cold[0]:.2f} / {cold[1]:.2f} | {median(warm)} |", flush=True)
    print(f"load average {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
