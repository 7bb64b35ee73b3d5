"""`godrays-jax fit` at its limits, as a user's shell runs it: degenerate frames, far lights and shadows in frames
without a camera under a memory limit, and a fit interrupted or killed while it finishes, which leaves its parameters
and report both or neither."""

import json
import math
import os
import resource
import signal
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np
import pytest
from frames import slow_where

import godrays_jax as gr

RESIDENT_LIMIT = 2 << 30
"""The most memory a fit of `FRAME_SIZE` may hold resident at once (its peak RSS), what a user's machine must have."""

DATA_LIMIT = 4 << 30
"""The limit set on the command's data (`RLIMIT_DATA`: its heap and private mappings, where XLA's buffers live), so
that a runaway buffer fails the fit at once instead of filling the machine. Not the claim itself: the command's heap
keeps what it frees and only grows (`app.allocator`), so its extent, which the limit counts, runs past its resident
peak by what the order of its allocations leaves unused, which varies with what the other kind's fit has put in the
cache meanwhile (benchmarks/README.md, "Memory as a function of the frame"). Not its address space either: JAX
alone reserves addresses it never touches."""


def _finished(*arguments, env, data_limit, timeout):
    """`godrays-jax ARGUMENTS` in a fresh interpreter, its data limited to `data_limit` bytes, run to its end (killed
    after `timeout` seconds): its exit code, its stderr and its peak resident memory in bytes (`os.wait4`, this
    process's own)."""
    with tempfile.TemporaryFile("w+") as err:
        process = subprocess.Popen(
            [sys.executable, "-m", "godrays_jax", *arguments], env=env, text=True, stdout=subprocess.DEVNULL,
            stderr=err, preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_DATA, (data_limit, data_limit)),
        )  # fmt: skip
        timer = threading.Timer(timeout, process.kill)
        timer.start()
        try:
            _, status, usage = os.wait4(process.pid, 0)
        finally:
            timer.cancel()
        process.returncode = os.waitstatus_to_exitcode(status)
        err.seek(0)
        return process.returncode, err.read(), usage.ru_maxrss << 10


def _command(*arguments, env, **options):
    """`godrays-jax ARGUMENTS` started in a fresh interpreter, its stdout and stderr piped."""
    return subprocess.Popen(
        [sys.executable, "-m", "godrays_jax", *arguments], env=env, text=True, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, **options,
    )  # fmt: skip


@pytest.fixture(scope="module")
def environment(tmp_path_factory):
    """The commands' environment: one compilation cache for the module's commands, as a user's shell has, shared by
    the suite's workers (the folder above each worker's own), empty when the suite starts."""
    run = tmp_path_factory.getbasetemp()  # a worker's own folder is in the run's (pytest-xdist)
    cache = (run.parent if "PYTEST_XDIST_WORKER" in os.environ else run) / "fit_limits_cache"
    cache.mkdir(mode=0o700, exist_ok=True)
    return {**os.environ, "GODRAYS_JAX_CACHE_DIR": str(cache)}


def _frame(depth: np.ndarray) -> gr.Buffers:
    height, width = depth.shape
    return gr.Buffers(color=np.full((height, width, 3), 0.2, np.float32), depth=depth.astype(np.float32),
                      coverage=np.isfinite(depth).astype(np.float32))  # fmt: skip


def _ground(height, width):
    depth = np.full((height, width), np.inf, np.float32)
    depth[height // 3 :] = 40.0
    return depth


def _pillar(height, width):
    depth = _ground(height, width)
    depth[height // 5 :, width // 2 - width // 40 : width // 2 + width // 40] = 12.0  # a pillar in the light
    return depth


FRAME_SIZE = (90, 160)
"""The frames without a camera, height and width. A table of shadows held once per forward-mode lane (one 11.6 GB
buffer at 320x180) would still take more than `DATA_LIMIT` here: the table's cells run along the frame's
diagonal, half as long. At this size the compiler sets the command's peak, as at 320x180, and the two kinds' fits take
less time under the suite's options (benchmarks/README.md, "The test suite on CI")."""


WITHOUT_A_CAMERA = {  # the frames' depth and their lights, by whether anything in them casts a shadow
    "no shadows": {
        "all sky": (lambda h, w: np.full((h, w), np.inf), "80,20"),
        "all zero": (lambda h, w: np.zeros((h, w)), "80,20"),
    },
    "shadows": {
        "a pillar in the light": (_pillar, "80,20"),
        "a light 1e12 pixels away": (_ground, "1e12,1e12"),
    },
}


@pytest.mark.slow
@pytest.mark.parametrize("kind", list(WITHOUT_A_CAMERA))
def test_a_default_fit_of_a_frame_without_a_camera_stays_within_two_gigabytes(kind, tmp_path, environment):
    """The default fit (`volumetric_haze`) of a `FRAME_SIZE` frame without a field of view (which the fit then fits too)
    holds at most `RESIDENT_LIMIT` resident (and runs under `DATA_LIMIT`), for each frame of `WITHOUT_A_CAMERA` in
    turn: frames whose depth is all sky or all zero (nothing casts a shadow: `Effect.same_on`, no shadows' table), and
    those with shadows: a pillar casting its shadow across the ground, and a ground lit from far off screen. The first
    of each kind compiles from an empty cache and the other reads its programs back, as a user's second fit does: in
    turn, where two workers at once compiled the same programs twice. Each fits, to finite parameters: the field of
    view's column is a difference of two renders (`Effect.DIFFERENCED_STAGES`), where its forward-mode lanes held the
    lines' table once per lane. The commands inherit the suite's XLA options (`conftest.SUITE_XLA_FLAGS`); under the
    command's own the pillar's first fit holds more (benchmarks/README.md, "Memory as a function of the frame")."""
    target = tmp_path / "target.exr"
    gr.write_image(target, np.full((*FRAME_SIZE, 3), 0.3, np.float32))
    for case, (make_depth, light) in WITHOUT_A_CAMERA[kind].items():
        frame, params = tmp_path / f"{case}.exr", tmp_path / f"{case}.json"
        gr.write_buffers(frame, _frame(make_depth(*FRAME_SIZE)))
        code, err, peak = _finished("fit", str(frame), str(target), "--light", light, "-o", str(params),
                                    "--max-steps", "1", env=environment, data_limit=DATA_LIMIT, timeout=900)  # fmt: skip
        assert code == 0, (case, err)
        assert peak <= RESIDENT_LIMIT, (case, peak >> 20)
        values = json.loads(params.read_text())  # the effect's name and its fields, as `apply --params` reads them
        flat = [v for value in values.values() for v in np.ravel(value).tolist() if isinstance(v, (int, float))]
        assert flat and all(math.isfinite(v) for v in flat), (case, values)


def _small_fit(tmp_path, environment, *extra):
    """A quick fit of a small frame with a report, started: the process, the params and report paths."""
    depth = _ground(36, 64)
    depth[:, 30:34] = 10.0  # a pillar in the light
    frame, target = tmp_path / "frame.exr", tmp_path / "target.exr"
    gr.write_buffers(frame, _frame(depth), light_xy=(32.5, 6.0))
    gr.write_image(target, np.asarray(gr.preset("xna_crepuscular")(_frame(depth), np.asarray([32.5, 6.0], np.float32))))
    params, report = tmp_path / "params.json", tmp_path / "report.png"
    process = _command("fit", str(frame), str(target), "--preset", "xna_crepuscular", "-o", str(params),
                       "--report", str(report), "--max-steps", "6", *extra, env=environment)  # fmt: skip
    return process, params, report


def _wait_for_line(process, text, timeout=600):
    """Read the process's stdout until a line containing `text`; the lines read."""
    lines, start = [], time.monotonic()
    while time.monotonic() - start < timeout:
        line = process.stdout.readline()
        if not line:
            break
        lines.append(line)
        if text in line:
            return lines
    raise AssertionError(f"no line with {text!r} in {lines}")


@pytest.mark.parametrize(
    "stop", slow_where([signal.SIGINT, signal.SIGKILL], {signal.SIGINT}), ids=["interrupted", "killed"]
)
@pytest.mark.parametrize("delay", slow_where([0.0, 0.5], {0.0}))
def test_a_fit_stopped_after_it_converged_leaves_both_files_or_neither(stop, delay, tmp_path, environment):
    """Stopped once it has printed its result (while it checks the fit, renders the report and writes): the params
    file and the report exist both (each whole) or neither; an interrupt exits 130 with one line."""
    process, params, report = _small_fit(tmp_path, environment)
    _wait_for_line(process, "fitted ")
    time.sleep(delay)
    process.send_signal(stop)
    out, err = process.communicate(timeout=600)
    assert params.exists() == report.exists(), (out, err)
    if params.exists():
        assert json.loads(params.read_text())["effect"] == type(gr.preset("xna_crepuscular")).__name__
        assert gr.read_image(report).ndim == 3
    if stop == signal.SIGINT and process.returncode != 0:
        # Interrupted in its work: 130 and one line. Interrupted while the interpreter exits (Python's handler gone):
        # killed by the signal, its work done.
        exiting = process.returncode == -signal.SIGINT and params.exists()
        assert exiting or (process.returncode == 130 and err.strip().splitlines()[-1].endswith("interrupted")), err
    leftovers = sorted(path.name for path in tmp_path.iterdir()) if not params.exists() else []
    assert not [name for name in leftovers if name.startswith(("params", "report"))], leftovers
