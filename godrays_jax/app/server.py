"""The live tuner's HTTP server: its page and JSON API on 127.0.0.1, answered by a `Tuner`.

See `tuner` for the API's requests and answers.
"""

import functools
import http.server
import json
import threading
from collections.abc import Callable
from importlib import resources
from typing import Any

from godrays_jax.app.tuner import QUALITIES, Superseded, Tuner, TuneRequestError
from godrays_jax.primitives.checks import error_line

HOST = "127.0.0.1"
"""The tuner serves this address only: the page can write files, so it is never exposed to a network."""


_MAX_BODY_BYTES = 1 << 20


@functools.cache
def page_html() -> bytes:
    """The tuner page (package data `tune_page.html`)."""
    return resources.files("godrays_jax.app").joinpath("tune_page.html").read_bytes()


class _Handler(http.server.BaseHTTPRequestHandler):
    server: "_HTTPServer"
    protocol_version = "HTTP/1.1"

    def log_message(self, format, *args):  # the page polls; a line per request would flood the terminal
        pass

    def _send(self, status: int, body: bytes, content_type: str) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def _json(self, status: int, value: Any) -> None:
        self._send(status, json.dumps(value).encode(), "application/json")

    def _host_allowed(self) -> bool:
        # DNS rebinding: a foreign page that resolves its own name to 127.0.0.1 sends its own Host header.
        host = (self.headers.get("Host") or "").rsplit(":", 1)[0]
        return host in ("127.0.0.1", "localhost")

    def _payload(self) -> dict:
        length = int(self.headers.get("Content-Length") or 0)
        if length > _MAX_BODY_BYTES:
            raise TuneRequestError(f"request body too large ({length} bytes, at most {_MAX_BODY_BYTES})")
        text = self.rfile.read(length) if length else b"{}"
        try:
            payload = json.loads(text)
        except (json.JSONDecodeError, UnicodeDecodeError) as error:
            raise TuneRequestError(f"malformed JSON: {error}") from None
        if not isinstance(payload, dict):
            raise TuneRequestError("the request body must be a JSON object")
        return payload

    def _answer(self, action: Callable[[], Any]) -> None:
        try:
            self._json(200, action())
        except TuneRequestError as error:
            self._json(400, {"error": str(error)})
        except Superseded as error:
            self._json(409, {"error": str(error)})
        except Exception as error:  # a failed render must not take the server down
            self._json(500, {"error": error_line(error)})

    def do_GET(self):
        if not self._host_allowed():
            return self._json(403, {"error": "the tuner answers requests to 127.0.0.1 or localhost only"})
        tuner = self.server.tuner
        path = self.path.split("?", 1)[0]
        if path in ("/", "/index.html"):
            return self._send(200, page_html(), "text/html; charset=utf-8")
        if path == "/api/state":
            return self._answer(tuner.state)
        if path == "/api/fit":
            return self._answer(tuner.fit_progress)
        self._json(404, {"error": f"no such page {path}"})

    def do_POST(self):
        if not self._host_allowed():
            return self._json(403, {"error": "the tuner answers requests to 127.0.0.1 or localhost only"})
        tuner = self.server.tuner
        actions = {"/api/render": tuner.render, "/api/preset": tuner.set_preset, "/api/fit": tuner.fit,
                   "/api/save": tuner.save}  # fmt: skip
        action = actions.get(self.path)
        if action is None:
            # the body is read anyway so the connection stays usable (HTTP/1.1 keep-alive)
            self.rfile.read(int(self.headers.get("Content-Length") or 0))
            return self._json(404, {"error": f"no such endpoint {self.path}"})
        try:
            payload = self._payload()
        except TuneRequestError as error:
            self.close_connection = True
            return self._json(400, {"error": str(error)})
        self._answer(lambda: action(payload))


class _HTTPServer(http.server.ThreadingHTTPServer):
    daemon_threads = True
    tuner: Tuner


class TuneServer:
    """The tuner's HTTP server on 127.0.0.1, serving in a background thread.

    `port=0` lets the OS choose a free port (see `url`). Use as a context
    manager, or call `close()`: it stops the server, then the render worker.
    """

    def __init__(self, tuner: Tuner, *, port: int = 0):
        if not (isinstance(port, int) and 0 <= port <= 65535):
            raise ValueError(f"port must be an int in [0, 65535], got {port!r}")
        self.tuner = tuner
        self._http = _HTTPServer((HOST, port), _Handler)
        self._http.tuner = tuner
        self._thread = threading.Thread(target=self._http.serve_forever, name="godrays-tune-http", daemon=True)
        self._thread.start()

    @property
    def port(self) -> int:
        return self._http.server_address[1]

    @property
    def url(self) -> str:
        return f"http://{HOST}:{self.port}/"

    def close(self) -> None:
        self._http.shutdown()
        self._http.server_close()
        self._thread.join()
        self.tuner.close()

    def __enter__(self) -> "TuneServer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def wait(self) -> None:
        """Block until the server stops (Ctrl-C raises `KeyboardInterrupt` here)."""
        while self._thread.is_alive():
            self._thread.join(0.5)

    def warm_up(self) -> None:
        """Compile the starting effect's preview and full-resolution renders so the first slider move is fast."""
        for quality in QUALITIES:
            self.tuner.render({"quality": quality})


