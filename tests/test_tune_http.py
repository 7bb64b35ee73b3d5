"""The tuner's HTTP server: loopback only, token, origin and host checks, policy headers, malformed and stalled requests, load."""

import http.client
import json
import os
import re
import socket
import struct
import threading

import pytest

import godrays_jax as gr
import godrays_jax.app.server as server_module
from godrays_jax.app.server import HOST, MAX_WORKERS, TOKEN_HEADER, TuneServer
from godrays_jax.app.tuner import Tuner

from tune_support import Client, server, small_effect, small_frame  # noqa: F401, F811 (server is a fixture)


def test_server_listens_on_loopback_only(server):
    assert server.address[0] == "127.0.0.1"
    assert server.url.startswith("http://127.0.0.1:")


def test_page_is_self_contained(server):
    connection = http.client.HTTPConnection(HOST, server.port, timeout=30)
    connection.request("GET", "/")
    response = connection.getresponse()
    page = response.read().decode()
    connection.close()
    assert response.status == 200 and "text/html" in response.getheader("Content-Type")
    assert "/api/render" in page
    assert "http://" not in page and "https://" not in page  # no CDN, nothing fetched from elsewhere


@pytest.mark.parametrize(
    ("path", "raw", "status", "message"),
    [
        ("/api/render", b"{not json", 400, "is not valid JSON"),
        ("/api/render", b"[1, 2]", 400, "is not a JSON object"),
        ("/api/render", b"\xff\xfe", 400, "is not valid JSON"),
        ("/api/preset", b'{"name": "unreal_engine"}', 400, "unknown preset"),
        ("/api/preset", b'{"name": "galaxy_vls"}', 400, "cannot render this frame"),  # needs a light pass
        ("/api/nowhere", b"{}", 404, "no such endpoint"),
    ],
)
def test_malformed_requests(server, path, raw, status, message):
    client = Client(server)
    got, answer = client.request("POST", path, raw=raw)
    assert got == status and message in answer["error"]
    assert client.request("POST", "/api/render", {"quality": "preview"})[0] == 200


def test_requests_for_other_host_names_are_refused(server):
    status, answer = Client(server).request("GET", "/api/state", host="evil.example:80")
    assert status == 403 and "127.0.0.1" in answer["error"]


def test_page_carries_the_launch_token_and_a_strict_policy(server):
    connection = http.client.HTTPConnection(HOST, server.port, timeout=30)
    connection.request("GET", "/")
    response = connection.getresponse()
    page = response.read().decode()
    connection.close()
    policy = response.getheader("Content-Security-Policy")
    nonce = re.search(r"script-src 'nonce-([^']+)'", policy).group(1)
    assert f'<meta name="godrays-token" content="{server.token}">' in page
    assert page.count(f'nonce="{nonce}"') == 2  # the one <style> and the one <script>
    assert "@GODRAYS_" not in page and len(server.token) >= 32
    for directive in ("default-src 'none'", "connect-src 'self'", "img-src 'self' data:", "frame-ancestors 'none'"):
        assert directive in policy
    assert response.getheader("X-Frame-Options") == "DENY"
    with TuneServer(Tuner(small_frame(), (1.0, 1.0), effect=small_effect())) as other:
        assert other.token != server.token  # one per launch


def test_answers_carry_the_frame_and_policy_headers(server):
    connection = http.client.HTTPConnection(HOST, server.port, timeout=30)
    connection.request("POST", "/api/render", body=b"{}", headers={"Content-Type": "text/plain"})
    response = connection.getresponse()
    response.read()
    connection.close()
    assert response.status == 403 and response.getheader("X-Frame-Options") == "DENY"
    assert "frame-ancestors 'none'" in response.getheader("Content-Security-Policy")


def test_the_pages_own_origin_may_post(server):
    client = Client(server)
    for origin in (f"http://127.0.0.1:{server.port}", f"http://localhost:{server.port}"):
        status, answer = client.request("POST", "/api/render", {"quality": "preview"}, headers={"Origin": origin})
        assert status == 200, answer


@pytest.mark.parametrize(
    ("headers", "status", "message"),
    [
        ({"Origin": "http://evil.example", "Content-Type": "text/plain", TOKEN_HEADER: None}, 403, "evil.example"),
        ({"Content-Type": "text/plain"}, 415, "Content-Type must be application/json"),
        ({TOKEN_HEADER: None}, 403, TOKEN_HEADER),
        ({TOKEN_HEADER: "x" * 43}, 403, TOKEN_HEADER),
    ],
)
def test_cross_site_requests_change_nothing(server, headers, status, message):
    """What any web page the user has open can send: refused before the tuner acts, for every endpoint."""
    client = Client(server)
    saved = server.tuner.save_path
    before = os.path.getmtime(saved) if os.path.exists(saved) else None
    for path, body in (("/api/save", {"params": {"exposure": 4.0}}), ("/api/preset", {"name": "kbengine_flares"}),
                       ("/api/fit", {}), ("/api/render", {}), ("/api/fit/cancel", {})):  # fmt: skip
        got, answer = client.request("POST", path, body, headers=headers)
        assert got == status and message in answer["error"], (path, answer)
    assert (os.path.getmtime(saved) if os.path.exists(saved) else None) == before
    assert isinstance(server.tuner.effect, gr.GodRays) and not server.tuner.fit_progress()["running"]


def test_a_stalled_body_gets_408_and_sockets_time_out(server, monkeypatch):
    monkeypatch.setattr(server_module, "SOCKET_TIMEOUT_S", 0.5)
    monkeypatch.setattr(server_module, "KEEP_ALIVE_S", 0.5)
    with socket.create_connection((HOST, server.port), timeout=30) as connection:
        connection.sendall(
            f"POST /api/render HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
            f"{TOKEN_HEADER}: {server.token}\r\nContent-Length: 100\r\n\r\n{{".encode()
        )  # fmt: skip
        response = http.client.HTTPResponse(connection)
        response.begin()
        assert response.status == 408 and "did not arrive" in json.loads(response.read())["error"]
    # Sends nothing at all: closed by the server, long before this socket's own timeout would raise.
    with socket.create_connection((HOST, server.port), timeout=30) as idle:
        assert idle.recv(1) == b""


def test_idle_connections_beyond_the_pool_delay_a_request_only_until_they_time_out(server, monkeypatch):
    """Tabs keep connections open between requests: idle ones are closed soon, so they never lock the page out."""
    monkeypatch.setattr(server_module, "KEEP_ALIVE_S", 0.5)
    idle = [socket.create_connection((HOST, server.port), timeout=30) for _ in range(MAX_WORKERS + 8)]
    try:
        # Answered once the idle ones time out, long before the request's own timeout would raise.
        assert Client(server).request("GET", "/api/state", timeout=30)[0] == 200
    finally:
        for connection in idle:
            connection.close()


def test_many_concurrent_requests_are_all_answered(server):
    """200 renders at once: no connection reset (listen backlog) and never more than MAX_WORKERS threads."""
    client = Client(server)
    statuses, errors = [], []
    threads_seen = []

    def send():
        try:
            statuses.append(client.request("POST", "/api/render", {"quality": "preview"})[0])
        except Exception as error:  # noqa: BLE001 - collected and asserted on below
            errors.append(repr(error))
        threads_seen.append(sum(t.name.startswith("godrays-tune-http") for t in threading.enumerate()))

    senders = [threading.Thread(target=send) for _ in range(200)]
    for thread in senders:
        thread.start()
    for thread in senders:
        thread.join(120)
    assert errors == [] and len(statuses) == 200 and set(statuses) <= {200, 409} and 200 in statuses
    assert max(threads_seen) <= MAX_WORKERS


def test_client_disconnects_print_nothing(capfd):
    body = json.dumps({"quality": "full"}).encode()
    with TuneServer(Tuner(small_frame(), (32.0, 6.0), effect=small_effect())) as running:
        for _ in range(20):
            with socket.create_connection((HOST, running.port), timeout=30) as connection:
                connection.sendall(
                    f"POST /api/render HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
                    f"{TOKEN_HEADER}: {running.token}\r\nContent-Length: {len(body)}\r\n\r\n".encode() + body
                )  # fmt: skip
                connection.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))  # a reset on close
        assert Client(running).request("GET", "/api/state")[0] == 200
    # Closing the server waits for the requests in progress: anything they print is printed by now.
    captured = capfd.readouterr()
    assert "Traceback" not in captured.err and "Error" not in captured.err, captured.err
