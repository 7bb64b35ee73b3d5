"""The live tuner's HTTP server: its page and JSON API on 127.0.0.1, answered by a `Tuner`.

The JSON API, `GET_API` and `POST_API` below (every answer is JSON; errors are `{"error": message}`):

| request | body | answer |
|---|---|---|
| `GET /api/state` | | the frame's size, preview factor, light, effect (`effect_to_dict`), slider bounds, presets, views, tonemaps, save path, whether a target is loaded |
| `POST /api/render` | `{"params", "light", "other_lights", "light_in_front", "quality", "view", "tonemap"}`, all optional | `{"image": "data:image/png;base64,...", "width", "height", "quality", "render_ms", "encode_ms"}` |
| `POST /api/preset` | `{"name"}` | the new state (the effect becomes the preset) |
| `POST /api/fit` | `{"params", "light", "light_in_front", "fixed"}` | starts a fit in the background and answers at once with its progress (409 if one is running) |
| `GET /api/fit` | | the fit's progress `{"running", "step", "loss", "result", "error", "cancelled"}`; `result` is `{"effect", "loss_before", "loss_after", "steps", "fitted", "kept_start"}` once it is done (`kept_start`: the fit ended above the start, which it kept) |
| `POST /api/fit/cancel` | `{}` | asks the running fit to stop after its current step; its progress |
| `POST /api/save` | `{"params"}` | `{"path", "effect"}`: writes what `apply --params` reads |

`params` maps fittable field names to numbers (lists for vectors such as
`tint`); fields left out keep the server's current values, static fields
(`max_samples`, `source`, ...) come from the current effect or preset. Values
outside a field's range (`fit.fitted_bounds`: the effect's bounds, counts
capped by their static loop lengths), unknown fields, malformed JSON, unknown
presets, views or tonemaps get a 400 with a message; the server keeps running.

Only the page this server served can drive it; how (host, token, origin, content type, CSP, size checks,
timeouts, the waiting room, the worker pool): docs/tuner.md, "Security".
"""

import functools
import html
import http.server
import io
import json
import secrets
import selectors
import socket
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from importlib import resources
from typing import Any

from godrays_jax.app.tuner import QUALITIES, Superseded, Tuner, TuneRequestError
from godrays_jax.effects.serialization import parse_json_object
from godrays_jax.primitives.checks import error_line

GET_API = {"/api/state": "state", "/api/fit": "fit_progress"}
"""The GET endpoints and the `Tuner` method that answers each (the table above)."""

POST_API = {"/api/render": "render", "/api/preset": "set_preset", "/api/fit": "fit", "/api/fit/cancel": "cancel_fit", "/api/save": "save"}
"""The POST endpoints and the `Tuner` method that answers each with the request's JSON body."""

HOST = "127.0.0.1"
"""The tuner serves this address only: the page can write files, so it is never exposed to a network."""

TOKEN_HEADER = "X-Godrays-Token"
"""The request header that carries the per-launch token (the page reads it from its `<meta name="godrays-token">`)."""

MAX_BODY_BYTES = 1 << 20
"""Request bodies larger than this are refused unread (the page's largest request, a render, is about 1 KiB)."""

SOCKET_TIMEOUT_S = 15.0
"""Seconds a request may stall while its headers or body are read (then 408, or the connection is closed)."""

KEEP_ALIVE_S = 5.0
"""Seconds a new connection may wait before sending the first byte of its request (it holds no worker meanwhile)."""

MAX_WAITING = 1024
"""Connections waiting for their request's head at once; one more is closed at once."""

MAX_HEAD_BYTES = 64 << 10
"""A request's head (request line and headers) larger than this is handed on as it is, and refused there."""

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

    def setup(self):
        super().setup()
        self.connection.settimeout(SOCKET_TIMEOUT_S)  # for the body, and for writing the answer
        # The head the waiting room read comes first, then the rest (a body) from the socket.
        self.rfile.close()
        self.rfile = io.BufferedReader(_Prefixed(self.server.heads.pop(self.connection, b""), self.connection))

    def handle(self):
        self.close_connection = True
        self.handle_one_request()
        self.close_connection = True  # one request per connection: the next one waits in the waiting room again

    def _send(self, status: int, body: bytes, content_type: str, *, nonce: str | None = None) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Frame-Options", "DENY")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.send_header("Referrer-Policy", "no-referrer")
        self.send_header("Content-Security-Policy", content_security_policy(nonce or secrets.token_urlsafe(16)))
        self.close_connection = True
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
            if path not in GET_API:
                raise _RequestRefused(404, f"no such page {path}")
            self._check_token()
            self._answer(getattr(self.server.tuner, GET_API[path]))
        except _RequestRefused as refused:
            self._refuse(refused)

    def do_POST(self):
        try:
            self._check_host()
            length = self._content_length()
            if self.path not in POST_API:
                raise _RequestRefused(404, f"no such endpoint {self.path}")
            self._check_origin()
            self._check_token()
            payload = self._payload(length)
        except _RequestRefused as refused:
            return self._refuse(refused)
        action = getattr(self.server.tuner, POST_API[self.path])
        self._answer(lambda: action(payload))

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


class _Prefixed(io.RawIOBase):
    """A socket's bytes, after `prefix` (what was read from it already)."""

    def __init__(self, prefix: bytes, connection: socket.socket):
        self._prefix, self._connection = memoryview(prefix), connection

    def readable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:
        if self._prefix:
            count = min(len(buffer), len(self._prefix))
            buffer[:count], self._prefix = self._prefix[:count], self._prefix[count:]
            return count
        return self._connection.recv_into(buffer)


class _WaitingRoom:
    """Connections whose request head has not arrived yet, all waited on by one thread (none holds a worker).

    A connection is handed to `ready(connection, head)` once its head is
    complete (or too large, or the client closed its side: the handler answers
    or drops it), and closed if it sends nothing within `KEEP_ALIVE_S` or no
    whole head within `SOCKET_TIMEOUT_S`.
    """

    def __init__(self, ready: Callable[[socket.socket, bytes], None]):
        self._ready = ready
        self._selector = selectors.DefaultSelector()
        self._waiting: dict[socket.socket, tuple[float, float, bytearray]] = {}  # first-byte and head deadlines, head
        self._arrived: list[socket.socket] = []
        self._lock = threading.Lock()
        self._wake, self._waker = socket.socketpair()
        self._selector.register(self._wake, selectors.EVENT_READ)
        self._closing = False
        self._thread = threading.Thread(target=self._run, name="godrays-tune-waiting", daemon=True)
        self._thread.start()

    def add(self, connection: socket.socket) -> None:
        with self._lock:
            self._arrived.append(connection)
        self._waker.send(b"\0")

    def close(self) -> None:
        self._closing = True
        self._waker.send(b"\0")
        self._thread.join()
        for connection in [*self._waiting, *self._arrived]:
            connection.close()
        self._selector.close()
        self._wake.close()
        self._waker.close()

    def _run(self) -> None:
        while not self._closing:
            now = time.monotonic()
            deadlines = [min(first if not head else later, later) for first, later, head in self._waiting.values()]
            for key, _ in self._selector.select(max(0.0, min(deadlines, default=now + 1.0) - now)):
                if key.fileobj is self._wake:
                    self._wake.recv(4096)
                    self._admit()
                else:
                    self._read(key.fileobj)
            self._expire(time.monotonic())

    def _admit(self) -> None:
        with self._lock:
            arrived, self._arrived = self._arrived, []
        now = time.monotonic()
        for connection in arrived:
            if len(self._waiting) >= MAX_WAITING:
                connection.close()
                continue
            try:
                self._selector.register(connection, selectors.EVENT_READ)
            except (OSError, ValueError):  # closed meanwhile: this thread must never stop on one connection
                connection.close()
                continue
            self._waiting[connection] = (now + KEEP_ALIVE_S, now + SOCKET_TIMEOUT_S, bytearray())

    def _read(self, connection: socket.socket) -> None:
        head = self._waiting[connection][2]
        try:
            data = connection.recv(MAX_HEAD_BYTES + 1 - len(head), socket.MSG_DONTWAIT)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        head += data
        if not data or b"\r\n\r\n" in head or len(head) > MAX_HEAD_BYTES:
            self._selector.unregister(connection)
            del self._waiting[connection]
            if head:
                self._ready(connection, bytes(head))
            else:
                connection.close()  # closed before a byte of a request

    def _expire(self, now: float) -> None:
        for connection, (first, later, head) in list(self._waiting.items()):
            if now >= later or (not head and now >= first):
                self._selector.unregister(connection)
                del self._waiting[connection]
                connection.close()


class _HTTPServer(http.server.HTTPServer):
    """At most `MAX_WORKERS` requests handled at once, on a pool of threads, each once its head has arrived
    (`_WaitingRoom`); disconnects are not reported."""

    request_queue_size = LISTEN_BACKLOG
    tuner: Tuner
    token: str

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._pool = ThreadPoolExecutor(MAX_WORKERS, thread_name_prefix="godrays-tune-http")
        self._closing = threading.Event()
        self.heads: dict[socket.socket, bytes] = {}
        self._waiting_room = _WaitingRoom(self._head_arrived)

    def process_request(self, request, client_address):
        self._waiting_room.add(request)

    def _head_arrived(self, request: socket.socket, head: bytes) -> None:
        if self._closing.is_set():
            request.close()
            return
        self.heads[request] = head
        try:
            client_address = request.getpeername()
        except OSError:  # gone meanwhile
            self.heads.pop(request, None)
            request.close()
            return
        self._pool.submit(self._work, request, client_address)

    def _work(self, request, client_address):
        try:
            self.finish_request(request, client_address)
        except Exception:
            self.handle_error(request, client_address)
        finally:
            self.heads.pop(request, None)
            self.shutdown_request(request)

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
        self._waiting_room.close()
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
    def address(self) -> tuple[str, int]:
        """The (host, port) the listening socket is bound to, as the OS reports it, not as it was asked for."""
        return self._http.server_address[:2]

    @property
    def port(self) -> int:
        return self.address[1]

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
