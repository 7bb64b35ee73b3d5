"""What the tuner's tests share: a small frame and effect, an HTTP client as the page uses it, the server and browser fixtures."""

import base64
import http.client
import json
import threading
from concurrent.futures import Future
import os

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
from selenium import webdriver

import godrays_jax as gr
from godrays_jax.app import tune_command
from godrays_jax.app.server import HOST, TOKEN_HEADER, TuneServer
from godrays_jax.app.tuner import RenderQueue, Tuner
from godrays_jax.primitives.buffers import Buffers


SAMPLE = os.path.join(os.path.dirname(__file__), "..", "examples", "data", "sample_frame.exr")
CHROMIUM = "/usr/bin/chromium"
CHROMEDRIVER = "/usr/bin/chromedriver"


def served_tuners(monkeypatch) -> list:
    """The tuners that `godrays-jax tune` commands build, in order, each kept where the command would serve it;
    nothing listens, and the command returns at once."""
    served = []

    class Served:
        url = "http://127.0.0.1:0/"

        def __init__(self, tuner, port):
            served.append(tuner)

        def warm_up(self):
            pass

        def wait(self):
            pass

        def close(self):
            served[-1].close()

    monkeypatch.setattr(tune_command, "TuneServer", Served)
    return served


def small_frame(height=36, width=64):
    """A frame with a sky on top, a wall with a gap below: enough structure for shafts."""
    rng = np.random.default_rng(7)
    coverage = np.zeros((height, width), np.float32)
    coverage[height // 2 :, :] = 1.0
    coverage[height // 2 :, width // 2 - 3 : width // 2 + 3] = 0.0
    depth = np.where(coverage > 0, 5.0, np.inf).astype(np.float32)
    color = (rng.uniform(0.0, 0.3, (height, width, 3)) * coverage[..., None] + 0.2).astype(np.float32)
    return Buffers(color=jnp.asarray(color), depth=jnp.asarray(depth), coverage=jnp.asarray(coverage))


def small_effect():
    """Seed 003's rays with 8 samples: cheap to compile and render in tests."""
    return gr.GodRays(num_samples=8.0, max_samples=8, flare_size=6.0, units="px", exposure=0.5, source="disc")


class Client:
    """The API over HTTP as the page uses it: JSON bodies with the server's token (or other headers, to probe)."""

    def __init__(self, server):
        self.port, self.token, self.tuner = server.port, server.token, server.tuner

    def request(self, method, path, body=None, *, raw=None, host=None, headers=None, timeout=120):
        connection = http.client.HTTPConnection(HOST, self.port, timeout=timeout)
        try:
            data = raw if raw is not None else (None if body is None else json.dumps(body).encode())
            sent = {"Content-Type": "application/json", TOKEN_HEADER: self.token}
            if host is not None:
                sent["Host"] = host
            sent.update(headers or {})
            connection.request(method, path, body=data, headers={k: v for k, v in sent.items() if v is not None})
            response = connection.getresponse()
            return response.status, json.loads(response.read())
        finally:
            connection.close()

    def fit(self, body):
        """Start a fit and poll it until it ends: (status of the start, the final progress)."""
        status, answer = self.request("POST", "/api/fit", body)
        if status != 200:
            return status, answer
        self.tuner.wait_fit(300)  # the page polls GET /api/fit; waiting for the fit's thread orders it without sleeps
        return status, self.request("GET", "/api/fit")[1]


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    frame = small_frame()
    truth = gr.GodRays(num_samples=8.0, max_samples=8, flare_size=6.0, units="px", exposure=1.2)
    target = eqx.filter_jit(truth)(frame, jnp.asarray([32.0, 6.0]))
    save_path = tmp_path_factory.mktemp("tune") / "params.json"
    tuner = Tuner(frame, (32.0, 6.0), effect=small_effect(), target=target, save_path=save_path,
                  max_preview_pixels=300, fit_steps=4)  # fmt: skip
    with TuneServer(tuner, port=0) as running:
        yield running


def decode(answer):
    prefix = "data:image/png;base64,"
    assert answer["image"].startswith(prefix)
    return base64.b64decode(answer["image"][len(prefix) :])


@pytest.fixture
def browser():
    if not os.path.exists(CHROMIUM):
        missing = f"{CHROMIUM} is missing: install Debian's chromium and chromium-driver (.ci/run does)"
        # CI installs it: there a missing browser is a failure, not a silent skip.
        pytest.fail(missing) if os.environ.get("CI") else pytest.skip(missing)
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for argument in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--window-size=1400,900"):
        options.add_argument(argument)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})  # CSP violations are reported there
    service = webdriver.ChromeService(executable_path=CHROMEDRIVER if os.path.exists(CHROMEDRIVER) else None)
    driver = webdriver.Chrome(options=options, service=service)
    try:
        yield driver
    finally:
        driver.quit()


def next_waiting(queue: RenderQueue, previous: Future | None = None) -> Future:
    """Block until a render other than `previous` waits in `queue` (while the worker is busy); its future.

    Orders requests from several threads without sleeping: each is known to
    wait before the next is sent.
    """
    waiting = queue.wait_for_request(previous, timeout=60)
    assert waiting is not None, "no render request arrived"
    return waiting


def fit_until_cancelled(tuner: Tuner, stepped: threading.Event | None = None):
    """A stand-in for `fit` that reports one step, then waits for the tuner's cancel and reports again (which stops it)."""

    def endless_fit(*args, progress, **kwargs):
        progress(1, 1.0)
        if stepped is not None:
            stepped.set()
        assert tuner.wait_fit_cancelled(300), "the fit was not cancelled"
        progress(2, 0.5)  # raises: cancelled
        raise AssertionError("a cancelled fit must stop at its next step")

    return endless_fit
