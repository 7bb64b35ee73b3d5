"""The fuzz corpus in tests/fuzz/: bad frames, params files and HTTP requests, each with its expected one-line error.

Each folder holds the cases and `expected.txt` (`NAME: the error`, a
substring of the one line the user sees). A case that once got through (a
traceback, a 500, a dropped connection, an all-NaN frame written with exit
status 0) stays here so it cannot come back.
"""

import http.client
import json
import os
import re
import socket
from pathlib import Path

import numpy as np
import pytest

import godrays_jax as gr
from godrays_jax.app.cli import main
from godrays_jax.app.server import HOST, TuneServer
from godrays_jax.app.tuner import Tuner

FUZZ = Path(__file__).resolve().parent / "fuzz"


def corpus(kind: str) -> list[tuple[str, str]]:
    """`(file name, expected)` for every line of `fuzz/KIND/expected.txt`."""
    lines = (FUZZ / kind / "expected.txt").read_text().splitlines()
    return [tuple(line.split(": ", 1)) for line in lines if line and not line.startswith("#")]


@pytest.mark.parametrize("kind", ["frames", "params", "requests"])
def test_every_case_has_an_expected_error(kind):
    names = {name for name, _ in corpus(kind)}
    assert names == set(os.listdir(FUZZ / kind)) - {"expected.txt"}


def good_frame(path):
    color = np.full((4, 6, 3), 0.2, np.float32)
    depth = np.full((4, 6), np.inf, np.float32)
    depth[3:, :] = 3.0
    frame = gr.Buffers(color=color, depth=depth, coverage=np.isfinite(depth).astype(np.float32))
    gr.write_buffers(path, frame, light_xy=(3.0, 2.0))
    return path


def one_line_error(args, capsys, tmp_path) -> str:
    """Run the CLI: exit status 1, one line on stderr, no file left in `tmp_path`; returns the line."""
    before = sorted(os.listdir(tmp_path))
    assert main([str(a) for a in args]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert sorted(os.listdir(tmp_path)) == before, "a failed run must not leave files behind"
    return err.strip()


@pytest.mark.parametrize(("name", "expected"), corpus("frames"))
def test_bad_frames(name, expected, capsys, tmp_path):
    line = one_line_error(["apply", FUZZ / "frames" / name, "-o", tmp_path / "out.exr"], capsys, tmp_path)
    assert expected in line


@pytest.mark.parametrize(("name", "expected"), corpus("params"))
def test_bad_params_files(name, expected, capsys, tmp_path):
    frame = good_frame(tmp_path / "frame.exr")
    line = one_line_error(["apply", frame, "--params", FUZZ / "params" / name, "-o", tmp_path / "out.exr"], capsys,
                          tmp_path)  # fmt: skip
    assert expected in line
    with pytest.raises(ValueError, match=re.escape(expected)):
        gr.load_effect(FUZZ / "params" / name)


def test_params_files_over_the_size_cap_are_refused_unread(tmp_path):
    params = tmp_path / "params.json"
    params.write_text('{"effect": "GodRays", "x": "' + "a" * gr.MAX_EFFECT_FILE_BYTES + '"}')
    with pytest.raises(ValueError, match="larger than"):
        gr.load_effect(params)


@pytest.fixture(scope="module")
def tune_server():
    color = np.full((6, 8, 3), 0.2, np.float32)
    depth = np.full((6, 8), np.inf, np.float32)
    depth[4:, :] = 3.0
    frame = gr.Buffers(color=color, depth=depth, coverage=np.isfinite(depth).astype(np.float32))
    effect = gr.GodRays(num_samples=4.0, max_samples=4, flare_size=3.0, units="px")
    with TuneServer(Tuner(frame, (4.0, 1.0), effect=effect, target=color), port=0) as server:
        yield server


def send_raw(port: int, data: bytes) -> tuple[int, dict]:
    """Send the bytes, close our side, and read the one answer: the server must answer, never just hang up."""
    with socket.create_connection((HOST, port), timeout=60) as connection:
        try:
            connection.sendall(data)
        except (BrokenPipeError, ConnectionResetError):
            pass  # refused before the body was read: the answer is already waiting
        connection.shutdown(socket.SHUT_WR)
        response = http.client.HTTPResponse(connection)
        response.begin()
        return response.status, json.loads(response.read())


@pytest.mark.parametrize(("name", "expected"), corpus("requests"))
def test_bad_requests(name, expected, tune_server):
    data = (FUZZ / "requests" / name).read_bytes()
    data = data.replace(b"@PORT@", str(tune_server.port).encode()).replace(b"@TOKEN@", tune_server.token.encode())
    status, answer = send_raw(tune_server.port, data)
    expected_status, message = expected.split(" ", 1)
    assert status == int(expected_status) and message in answer["error"], answer
    assert "\n" not in answer["error"]
