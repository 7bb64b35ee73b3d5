"""More than one machine: `batch --distributed` with two local processes through jax.distributed on the CPU, and
the render-farm examples (a shell fan-out of `--frames A-B` chunks, an OpenCue job), each against one process."""

import os
import random
import shlex
import signal
import socket
import subprocess
import sys
import time
import xml.dom.minidom
from pathlib import Path

import numpy as np
import pytest

import godrays_jax as gr
from godrays_jax.app.cli import build_parser, main

ROOT = Path(__file__).resolve().parents[1]
FRAMES = range(1001, 1006)


@pytest.fixture(scope="module")
def shot(tmp_path_factory):
    """Five small frames with their lights in the metadata, and one process's outputs for them."""
    folder = tmp_path_factory.mktemp("shot")
    (folder / "in").mkdir()
    rng = np.random.default_rng(7)
    for number in FRAMES:
        color = rng.uniform(0.0, 1.0, (12, 16, 3)).astype(np.float32)
        depth = np.full((12, 16), 5.0, np.float32)
        depth[:5] = np.inf
        frame = gr.Buffers(color=color, depth=depth, coverage=np.isfinite(depth).astype(np.float32))
        gr.write_buffers(folder / "in" / f"shot.{number}.exr", frame, light_xy=(4.0 + number - 1001, 3.0))
    pattern = str(folder / "in" / "shot.####.exr")
    assert main(["batch", pattern, "-o", str(folder / "one"), "--preset", "kbengine_flares", "-q"]) == 0
    return folder, pattern


def environment(folder):
    """The command line as a user has it: `godrays-jax` on PATH running this checkout, JAX on the CPU."""
    bin_dir = folder / "bin"
    bin_dir.mkdir(exist_ok=True)
    shim = bin_dir / "godrays-jax"
    shim.write_text(f'#!/bin/sh\nexec {shlex.quote(sys.executable)} -m godrays_jax "$@"\n')
    shim.chmod(0o755)
    return {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}", "PYTHONPATH": str(ROOT),
            "JAX_PLATFORMS": "cpu"}  # fmt: skip


def assert_same_outputs(folder, name):
    for number in FRAMES:
        ours = gr.read_image(folder / name / f"shot.{number}.exr")
        np.testing.assert_array_equal(ours, gr.read_image(folder / "one" / f"shot.{number}.exr"))
    assert sorted(os.listdir(folder / name)) == [f"shot.{number}.exr" for number in FRAMES]


def free_port():
    """A port no socket holds, below Linux's range for the local ends of outgoing connections (32768-60999 by
    default): a port from that range, free when probed, can be taken by another process's connection before the
    coordinator binds it, and the other process then waits for a coordinator that never starts."""
    ports = random.Random()
    for _ in range(100):
        port = ports.randrange(20000, 32768)
        with socket.socket() as probe:
            try:
                probe.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise RuntimeError("no free port in 20000-32767")


ENDS_WITHIN = 120.0
"""Seconds the two processes get to end (five frames of 12x16 each: seconds, under load)."""


def test_two_processes_through_jax_distributed_write_what_one_process_writes(shot):
    folder, pattern = shot
    coordinator = f"127.0.0.1:{free_port()}"
    # Should a process not end, its stderr says where: the coordination service's own log lines (connected, at
    # the shutdown barrier, shut down) and, on the SIGABRT that then stops it, the stacks of its Python threads.
    traced = {**environment(folder), "TF_CPP_MIN_LOG_LEVEL": "0", "PYTHONFAULTHANDLER": "1"}
    processes = [
        subprocess.Popen(
            ["godrays-jax", "batch", pattern, "-o", str(folder / "two"), "--preset", "kbengine_flares", "-q",
             "--distributed", "--coordinator", coordinator, "--num-processes", "2", "--process-id", str(index)],
            env=traced, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        for index in range(2)
    ]
    deadline = time.monotonic() + ENDS_WITHIN
    answers = []
    try:
        for process in processes:
            answers.append(process.communicate(timeout=max(deadline - time.monotonic(), 1.0)))
    except subprocess.TimeoutExpired:
        for process in processes[len(answers):]:
            process.send_signal(signal.SIGABRT)  # the Python stacks of its threads (faulthandler), then its end
            try:
                answers.append(process.communicate(timeout=30))
            except subprocess.TimeoutExpired:
                process.kill()
                answers.append(process.communicate())
        written = sorted(os.listdir(folder / "two")) if (folder / "two").exists() else []
        pytest.fail(f"the two processes did not end within {ENDS_WITHIN:g} s: exit statuses "
                    f"{[process.returncode for process in processes]}, frames written {written}, stdout "
                    f"{[out for out, _ in answers]}, stderr {[err[-4000:] for _, err in answers]}")  # fmt: skip
    for process, (out, err) in zip(processes, answers):
        assert process.returncode == 0, err[-2000:]
    assert answers[0][0].startswith("3 written") and answers[1][0].startswith("2 written")  # contiguous shares
    assert_same_outputs(folder, "two")


@pytest.mark.slow
def test_a_shell_fan_out_of_frame_chunks_writes_what_one_process_writes(shot):
    folder, pattern = shot
    done = subprocess.run(
        [str(ROOT / "examples" / "farm" / "fanout.sh"), pattern, str(folder / "farm"), "1001", "1005", "2", "2",
         "--preset", "kbengine_flares"],
        env=environment(folder), capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.count("written") == 3  # chunks 1001-1002, 1003-1004, 1005
    assert_same_outputs(folder, "farm")
    usage = subprocess.run([str(ROOT / "examples" / "farm" / "fanout.sh"), pattern], capture_output=True, text=True)
    assert usage.returncode == 2 and usage.stderr.startswith("usage:")


def test_the_opencue_job_runs_a_valid_batch_command_per_chunk():
    spec = xml.dom.minidom.parse(str(ROOT / "examples" / "farm" / "opencue_job.xml"))
    layer = spec.getElementsByTagName("layer")[0]
    text = {name: layer.getElementsByTagName(name)[0].firstChild.data for name in ("cmd", "range", "chunk")}
    assert (text["range"], text["chunk"]) == ("1001-1100", "10")
    command = text["cmd"].replace("#FRAME_START#", "1011").replace("#FRAME_END#", "1020")
    arguments = shlex.split(command)
    assert arguments[0] == "godrays-jax"
    args = build_parser().parse_args(arguments[1:])
    assert args.command == "batch" and args.frames == "1011-1020" and args.resume and "%04d" in args.pattern
