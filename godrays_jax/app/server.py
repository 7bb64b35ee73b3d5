"""The live tuner's HTTP server: its page and JSON API on 127.0.0.1, answered by a `Tuner`.

See `tuner` for the API's requests and answers. Only the page this server
served can drive it, not another web page the user has open:

- Every request must name 127.0.0.1 or localhost in its `Host` header (403
  otherwise): a foreign page whose own name resolves to 127.0.0.1 (DNS
  rebinding) sends its own name.
- Every `/api/` request must carry the per-launch token in the header
  `X-Godrays-Token` (403 otherwise). The token is put into the page when it is
  served; other origins cannot read the page (no CORS headers), so they
  cannot learn it.
- `POST` requests must also come from the tuner's own origin (an `Origin`
  header other than `http://127.0.0.1:PORT` or `http://localhost:PORT` is
  403; clients that are not browsers send none) and declare
  `Content-Type: application/json` (415 otherwise), which a cross-site form
  or a "simple" `fetch` cannot send without a preflight, which is refused.
- Every answer carries `X-Frame-Options: DENY` and a Content-Security-Policy
  that lets the page run only its own inline script and style (a per-answer
  nonce), load images only from itself or `data:` URLs, connect only to
  itself, and never be framed.

The body's size is checked before a byte of it is read: a `POST` without a
`Content-Length` (411), with a malformed or negative one (400), or over
`MAX_BODY_BYTES` (413) is answered at once, also for unknown endpoints, and
the connection closed. A stalled request times out after `SOCKET_TIMEOUT_S`
(a body shorter than its `Content-Length` gets 408), an idle kept-alive
connection after `KEEP_ALIVE_S`; at most `MAX_WORKERS` connections are
served at once (the others wait in the listen backlog of `LISTEN_BACKLOG`).
Every malformed body or bad value is a 400 with a message; clients that
disconnect are not reported.
"""

import functools
import html
import http.server
import json
import secrets
import socket
import sys
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from importlib import resources
from typing import Any

from godrays_jax.app.tuner import QUALITIES, Superseded, Tuner, TuneRequestError
from godrays_jax.effects.serialization import parse_json_object
from godrays_jax.primitives.checks import error_line

HOST = "127.0.0.1"
"""The tuner serves this address only: the page can write files, so it is never exposed to a network."""

TOKEN_HEADER = "X-Godrays-Token"
"""The request header that carries the per-launch token (the page reads it from its `<meta name="godrays-token">`)."""

MAX_BODY_BYTES = 1 << 20
"""Request bodies larger than this are refused unread (the page's largest request, a render, is about 1 KiB)."""

SOCKET_TIMEOUT_S = 15.0
"""Seconds a request may stall while its headers or body are read (then 408, or the connection is closed)."""

KEEP_ALIVE_S = 5.0
"""Seconds a kept-alive connection may wait for its next request: an idle connection holds a worker."""

MAX_WORKERS = 32
"""Connections served at once (a browser keeps up to 6 open per tab); renders are coalesced onto one worker anyway."""

LISTEN_BACKLOG = 128
"""Connections the OS queues while every worker is busy (a burst of slider events, many tabs)."""

_TOKEN_PLACEHOLDER = b"@GODRAYS_TOKEN@"
_NONCE_PLACEHOLDER = b"@GODRAYS_NONCE@"


@functools.cache
def page_template() -> bytes:
    """The tuner page (package data `tune_page.html`) with placeholders for the token and the CSP nonce."""
    return resources.files("godrays_jax.app").joinpath("tune_page.html").read_bytes()


def content_security_policy(nonce: str) -> str:
    """The page's policy: its own inline script and style (by `nonce`), images from itself or `data:`, fetches to itself."""
    return (
        f"default-src 'none'; script-src 'nonce-{nonce}'; style-src 'nonce-{nonce}'; img-src 'self' data:; "
        "connect-src 'self'; frame-ancestors 'none'; base-uri 'none'; form-action 'none'"
    )


class _RequestRefused(Exception):
    """A request answered with `status` before (or instead of) reading its body; the connection is then closed."""

    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status = status


class _Handler(http.server.BaseHTTPRequestHandler):
    server: "_HTTPServer"
    protocol_version = "HTTP/1.1"
    timeout = SOCKET_TIMEOUT_S

    def log_message(self, format, *args):  # the page polls; a line per request would flood the terminal
        pass

    def handle_one_request(self):
        self.connection.settimeout(KEEP_ALIVE_S)  # until the request line arrives
        super().handle_one_request()

    def parse_request(self):
        self.connection.settimeout(SOCKET_TIMEOUT_S)  # the request has begun: its headers and body may take longer
        return super().parse_request()

    def _send(self, status: int, body: bytes, content_type: str, *, nonce: str | None = None) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Frame-Options", "DENY")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.send_header("Referrer-Policy", "no-referrer")
        self.send_header("Content-Security-Policy", content_security_policy(nonce or secrets.token_urlsafe(16)))
        if self.close_connection:
            self.send_header("Connection", "close")
        self.end_headers()
        self.wfile.write(body)

    def _json(self, status: int, value: Any) -> None:
        self._send(status, json.dumps(value).encode(), "application/json")

    def _refuse(self, refused: _RequestRefused) -> None:
        self.close_connection = True  # an unread body would be taken for the next request
        self._json(refused.status, {"error": str(refused)})

    def _check_host(self) -> None:
        # DNS rebinding: a foreign page that resolves its own name to 127.0.0.1 sends its own Host header.
        host = (self.headers.get("Host") or "").rsplit(":", 1)[0]
        if host not in ("127.0.0.1", "localhost"):
            raise _RequestRefused(403, "the tuner answers requests to 127.0.0.1 or localhost only")

    def _check_token(self) -> None:
        token = self.headers.get(TOKEN_HEADER) or ""
        if not secrets.compare_digest(token.encode(), self.server.token.encode()):
            raise _RequestRefused(403, f"missing or wrong {TOKEN_HEADER}: use the page the tuner serves")

    def _check_origin(self) -> None:
        origin = self.headers.get("Origin")
        own = {f"http://{name}:{self.server.server_address[1]}" for name in ("127.0.0.1", "localhost")}
        if origin is not None and origin not in own:
            raise _RequestRefused(403, f"requests from {origin} are refused: only the tuner's own page may send them")
        if self.headers.get("Sec-Fetch-Site") == "cross-site":
            raise _RequestRefused(403, "cross-site requests are refused: only the tuner's own page may send them")

    def _content_length(self) -> int:
        """The declared body size, checked before anything is read."""
        if "chunked" in (self.headers.get("Transfer-Encoding") or "").lower():
            raise _RequestRefused(411, "chunked bodies are not accepted: send a Content-Length")
        values = self.headers.get_all("Content-Length") or []
        if not values:
            raise _RequestRefused(411, "a POST needs a Content-Length")
        if len(set(values)) > 1 or not values[0].strip().isdigit() or not values[0].strip().isascii():
            raise _RequestRefused(400, f"malformed Content-Length {', '.join(values)!r}")
        length = int(values[0])
        if length > MAX_BODY_BYTES:
            raise _RequestRefused(413, f"request body too large ({length} bytes, at most {MAX_BODY_BYTES})")
        return length

    def _payload(self, length: int) -> dict:
        content_type = (self.headers.get("Content-Type") or "").split(";", 1)[0].strip().lower()
        if content_type != "application/json":
            raise _RequestRefused(415, f"Content-Type must be application/json, got {content_type or 'none'!r}")
        try:
            data = self.rfile.read(length)
        except TimeoutError:
            raise _RequestRefused(408, f"the body did not arrive within {SOCKET_TIMEOUT_S:g} s") from None
        if len(data) < length:
            raise _RequestRefused(400, f"the body ended after {len(data)} of its {length} bytes")
        try:
            return parse_json_object(data or b"{}")
        except ValueError as error:
            raise _RequestRefused(400, f"the request body {error}") from None

    def _answer(self, action: Callable[[], Any]) -> None:
        try:
            self._json(200, action())
        except (TuneRequestError, ValueError) as error:  # a value the page sent that the tuner or the library refuses
            self._json(400, {"error": error_line(error)})
        except Superseded as error:
            self._json(409, {"error": str(error)})
        except Exception as error:  # a failed render must not take the server down
            self._json(500, {"error": error_line(error)})

    def do_GET(self):
        try:
            self._check_host()
            path = self.path.split("?", 1)[0]
            if path in ("/", "/index.html"):
                nonce = secrets.token_urlsafe(16)
                page = page_template().replace(_TOKEN_PLACEHOLDER, html.escape(self.server.token).encode())
                page = page.replace(_NONCE_PLACEHOLDER, nonce.encode())
                return self._send(200, page, "text/html; charset=utf-8", nonce=nonce)
            tuner = self.server.tuner
            actions = {"/api/state": tuner.state, "/api/fit": tuner.fit_progress}
            if path not in actions:
                raise _RequestRefused(404, f"no such page {path}")
            self._check_token()
            self._answer(actions[path])
        except _RequestRefused as refused:
            self._refuse(refused)

    def do_POST(self):
        tuner = self.server.tuner
        actions = {"/api/render": tuner.render, "/api/preset": tuner.set_preset, "/api/fit": tuner.fit,
                   "/api/fit/cancel": tuner.cancel_fit, "/api/save": tuner.save}  # fmt: skip
        try:
            self._check_host()
            length = self._content_length()
            if self.path not in actions:
                raise _RequestRefused(404, f"no such endpoint {self.path}")
            self._check_origin()
            self._check_token()
            payload = self._payload(length)
        except _RequestRefused as refused:
            return self._refuse(refused)
        self._answer(lambda: actions[self.path](payload))

    def handle_expect_100(self):
        # `Expect: 100-continue` would otherwise invite the body before its size is checked.
        if self.command == "POST":
            try:
                self._content_length()
            except _RequestRefused as refused:
                self._refuse(refused)
                return False
        return super().handle_expect_100()

    def _refuse_method(self):
        self._refuse(_RequestRefused(405, f"method {self.command} is not allowed: the tuner answers GET and POST"))

    do_PUT = do_DELETE = do_PATCH = do_HEAD = do_OPTIONS = _refuse_method


class _HTTPServer(http.server.HTTPServer):
    """At most `MAX_WORKERS` connections handled at once, on a pool of threads; disconnects are not reported."""

    request_queue_size = LISTEN_BACKLOG
    tuner: Tuner
    token: str

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._slots = threading.BoundedSemaphore(MAX_WORKERS)
        self._pool = ThreadPoolExecutor(MAX_WORKERS, thread_name_prefix="godrays-tune-http")
        self._closing = threading.Event()

    def process_request(self, request, client_address):
        # Waiting here (not queueing without bound) leaves further connections in the listen backlog.
        while not self._slots.acquire(timeout=0.25):
            if self._closing.is_set():
                self.shutdown_request(request)
                return
        self._pool.submit(self._work, request, client_address)

    def _work(self, request, client_address):
        try:
            self.finish_request(request, client_address)
        except Exception:
            self.handle_error(request, client_address)
        finally:
            self.shutdown_request(request)
            self._slots.release()

    def handle_error(self, request, client_address):
        error = sys.exc_info()[1]
        if isinstance(error, (ConnectionError, TimeoutError, socket.timeout)):
            return  # the client went away (closed the tab, cancelled a fetch) or stalled: nothing to report
        print(f"godrays-jax tune: request from {client_address[0]} failed: {error_line(error)}", file=sys.stderr)

    def stop(self) -> None:
        """Stop accepting, close the socket, and wait for the requests in progress."""
        self._closing.set()
        self.shutdown()
        self.server_close()
        self._pool.shutdown(wait=True, cancel_futures=True)


class TuneServer:
    """The tuner's HTTP server on 127.0.0.1, serving in a background thread.

    `port=0` lets the OS choose a free port (see `url`). `token` is the
    per-launch secret the page sends with every API request (see the module
    docstring); a fresh random one by default. Use as a context manager, or
    call `close()`: it stops the server, then the tuner (fit and render worker).
    """

    def __init__(self, tuner: Tuner, *, port: int = 0, token: str | None = None):
        if not (isinstance(port, int) and 0 <= port <= 65535):
            raise ValueError(f"port must be an int in [0, 65535], got {port!r}")
        if token is not None and not (isinstance(token, str) and len(token) >= 16 and token.isprintable()):
            raise ValueError("token must be a printable string of at least 16 characters")
        self.tuner = tuner
        self.token = token or secrets.token_urlsafe(32)
        self._http = _HTTPServer((HOST, port), _Handler)
        self._http.tuner = tuner
        self._http.token = self.token
        self._thread = threading.Thread(target=self._http.serve_forever, name="godrays-tune-accept", daemon=True)
        self._thread.start()

    @property
    def port(self) -> int:
        return self._http.server_address[1]

    @property
    def url(self) -> str:
        return f"http://{HOST}:{self.port}/"

    def close(self) -> None:
        self._http.stop()
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
