"""The fuzz corpus in tests/fuzz/: bad frames, params files, HTTP requests and flare textures, each with its expected
one-line error.

Each folder holds the cases and `expected.txt` (`NAME: the error`, a
substring of the one line the user sees). A case that once got through (a
traceback, a 500, a dropped connection, an all-NaN frame written with exit
status 0) stays here so it cannot come back.
"""

import contextlib
import http.client
import json
import os
import re
import select
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


@pytest.mark.parametrize("kind", ["frames", "params", "requests", "textures"])
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


def _render_request(port: int, token: str, light: list[float]) -> bytes:
    """The PNG `POST /api/render` answers for this light."""
    body = json.dumps({"light": light, "view": "layer"}).encode()
    head = (f"POST /api/render HTTP/1.1\r\nHost: {HOST}:{port}\r\nContent-Type: application/json\r\n"
            f"X-Godrays-Token: {token}\r\nContent-Length: {len(body)}\r\n\r\n").encode()  # fmt: skip
    status, answer = send_raw(port, head + body)
    assert status == 200, answer
    return answer["image"]


FAR = "1e39,5"
"""A light beyond float32's range: every command draws it as at `MAX_LIGHT_PX` in its direction."""


def test_a_light_beyond_float32_is_drawn_as_at_the_bound_by_every_command(capsys, tmp_path, tune_server):
    frame = good_frame(tmp_path / "frame.0001.exr")
    for light, out in ((FAR, "far.exr"), ("1e9,5e-30", "bound.exr"), ("1e38,5", "near_max.exr")):
        assert main(["apply", str(frame), f"--light={light}", "-o", str(tmp_path / out), "--preset", "kbengine_flares"]) == 0
        assert capsys.readouterr().err == ""
        assert np.all(np.isfinite(gr.read_image(tmp_path / out)[..., :3])), light
    np.testing.assert_array_equal(gr.read_image(tmp_path / "far.exr"), gr.read_image(tmp_path / "bound.exr"))
    (tmp_path / "track.csv").write_text("frame,x,y\n1,1e39,5\n")
    assert main([str(a) for a in ["batch", tmp_path / "frame.####.exr", "-o", tmp_path / "out", "--light-track",
                                   tmp_path / "track.csv", "--preset", "kbengine_flares", "-q"]]) == 0  # fmt: skip
    assert capsys.readouterr().err == ""
    np.testing.assert_array_equal(gr.read_image(tmp_path / "out" / "frame.0001.exr"), gr.read_image(tmp_path / "far.exr"))
    port, token = tune_server.port, tune_server.token
    assert _render_request(port, token, [1e39, 5.0]) == _render_request(port, token, [1e9, 5e-30])


@pytest.mark.parametrize(("name", "expected"), corpus("textures"))
def test_bad_flare_textures(name, expected, capfd, tmp_path):
    """Read by `--flare-texture`: one line (a C library's own message too), exit status 1, no output."""
    frame = good_frame(tmp_path / "frame.exr")
    texture = FUZZ / "textures" / name
    code = main(["apply", str(frame), "--flare-texture", str(texture), "--preset", "kbengine_flares",
                 "-o", str(tmp_path / "out.exr")])  # fmt: skip
    err = capfd.readouterr().err
    assert code == 1 and err.count("\n") == 1 and expected in err, err
    assert not (tmp_path / "out.exr").exists()


@pytest.mark.parametrize("channels", [1, 2, 3, 4])
def test_flare_textures_of_every_promised_channel_count_draw(channels, tmp_path, capsys):
    """Alpha (channels 2 and 4) is premultiplied into the colour, as EXR and `read_image` hold it, and dropped."""
    rng = np.random.default_rng(channels)
    texture = rng.uniform(0.0, 1.0, (5, 7, channels)).astype(np.float32)
    colour = texture[..., : 1 if channels < 3 else 3]
    frame = gr.Buffers(color=np.full((6, 8, 3), 0.2, np.float32), depth=np.full((6, 8), np.inf, np.float32),
                       coverage=np.zeros((6, 8), np.float32))  # fmt: skip
    for effect_class in (gr.GodRays, gr.FlareOuts):
        drawn = effect_class(flare_texture=texture)(frame, np.asarray([4.0, 3.0]))
        np.testing.assert_array_equal(drawn, effect_class(flare_texture=colour)(frame, np.asarray([4.0, 3.0])))
        assert drawn.shape == (6, 8, 3) and np.all(np.isfinite(drawn))
    if channels != 2:  # PNG holds grey, RGB and RGBA here
        gr.write_image(tmp_path / "texture.png", texture)
        good_frame(tmp_path / "frame.exr")
        assert main(["apply", str(tmp_path / "frame.exr"), "--flare-texture", str(tmp_path / "texture.png"),
                     "--preset", "kbengine_flares", "-o", str(tmp_path / "out.exr")]) == 0  # fmt: skip


def test_a_texture_too_large_is_refused_before_its_values_are_read():
    huge = np.broadcast_to(np.float32(0.5), (10000, 10000, 3))  # no memory behind it
    with pytest.raises(ValueError, match="10000x10000 texels, more than 2048 on a side"):
        gr.GodRays(flare_texture=huge)
    with pytest.raises(ValueError, match="NaN or infinite"):
        gr.FlareOuts(flare_texture=np.full((2, 2), np.inf, np.float32))


def test_the_page_and_state_are_answered_while_one_client_holds_300_idle_connections(tune_server):
    """Connections that send nothing, or half a request head, hold no worker: the page and its state come promptly."""
    port, held = tune_server.port, []
    try:
        for index in range(300):
            connection = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            connection.setblocking(False)  # never waits, also while the server does not accept
            connection.connect_ex((HOST, port))
            held.append(connection)
        for connection in held:  # each connected (writable) before half of them send half a head
            select.select([], [connection], [], 30)
        for connection in held[::2]:
            with contextlib.suppress(OSError):
                connection.send(b"GET /api/state HTTP/1.1\r\nHost: 127.0.0.1\r\n")  # a head never finished
        # Promptly: each answer within its connection's timeout, which raises otherwise.
        for path, headers in (("/api/state", {"X-Godrays-Token": tune_server.token}), ("/", {})):
            client = http.client.HTTPConnection(HOST, port, timeout=3)
            client.request("GET", path, headers=headers)
            assert client.getresponse().status == 200
            client.close()
    finally:
        for connection in held:
            connection.close()
