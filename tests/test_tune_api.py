"""The tuner's JSON API over real HTTP: state, renders, views, coalescing, saves, presets and fits."""

import json
import os
import stat
import threading

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import OpenImageIO as oiio
import pytest

import godrays_jax as gr
import godrays_jax.app.tuner as tuner_module
from godrays_jax.app.cli import main
from godrays_jax.app.server import TuneServer
from godrays_jax.app.tuner import Tuner, display_encode

from tune_support import Client, decode, fit_until_cancelled, next_waiting, server, small_effect, small_frame  # noqa: F401, F811 (server is a fixture)


def test_state_lists_sliders_with_the_effects_bounds(server):
    status, state = Client(server).request("GET", "/api/state")
    assert status == 200
    assert (state["width"], state["height"], state["preview_factor"]) == (64, 36, 3)
    assert state["bounds"]["decay"] == list(gr.parameter_bounds(gr.GodRays)["decay"])
    assert state["bounds"]["num_samples"] == [1.0, 8.0]  # capped by the static loop length max_samples
    assert state["effect"]["effect"] == "GodRays" and state["has_target"]
    assert sorted(state["presets"]) == sorted(gr.PRESETS)


def test_render_returns_png_frames_at_both_qualities(server, tmp_path):
    client = Client(server)
    status, full = client.request("POST", "/api/render", {"quality": "full", "params": {"exposure": 2.0}})
    assert status == 200, full
    assert (full["width"], full["height"], full["quality"]) == (64, 36, "full")
    status, preview = client.request("POST", "/api/render", {"quality": "preview", "params": {"exposure": 2.0}})
    assert status == 200 and (preview["width"], preview["height"]) == (22, 12)
    path = tmp_path / "full.png"
    path.write_bytes(decode(full))
    shown = oiio.ImageBuf(str(path)).get_pixels(oiio.UINT8)
    brighter = eqx.tree_at(lambda e: e.exposure, small_effect(), jnp.asarray(2.0))
    expected = eqx.filter_jit(lambda e, f, l: display_encode(e(f, l)))(brighter, server.tuner.buffers, jnp.asarray([32.0, 6.0]))
    assert np.max(np.abs(shown.astype(int) - np.asarray(expected).astype(int))) <= 1


def test_every_view_renders_and_views_differ(server):
    client = Client(server)
    images = {}
    for view in ("after", "before", "layer", "difference", "target"):
        status, answer = client.request("POST", "/api/render", {"view": view, "quality": "preview"})
        assert status == 200, (view, answer)
        images[view] = decode(answer)
    assert len(set(images.values())) == len(images)


def test_moving_a_parameter_or_the_light_changes_the_frame(server):
    client = Client(server)
    frames = [
        client.request("POST", "/api/render", body)[1]["image"]
        for body in ({}, {"params": {"density": 0.9}}, {"light": [10.0, 3.0]}, {"light_in_front": False})
    ]
    assert len(set(frames)) == 4


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ({"params": {"density": 2.5}}, "density = 2.5 lies outside its range"),
        ({"params": {"num_samples": 9}}, "num_samples = 9.0 lies outside its range [1.0, 8.0]"),
        ({"params": {"tint": [1, 1]}}, "tint must have shape [3]"),
        ({"params": {"tint": [1, "a", 1]}}, "tint must be a finite number"),
        ({"params": {"decay": None}}, "decay must be a finite number"),
        ({"params": {"density": True}}, "density must be a finite number"),
        ({"params": {"max_samples": 4}}, "unknown parameter 'max_samples'"),
        ({"params": [1, 2]}, "params must be a JSON object"),
        ({"light": [1]}, "light must be [x, y]"),
        ({"light": [1, float("nan")]}, "light must be a finite number"),
        ({"light_in_front": "yes"}, "light_in_front must be true or false"),
        ({"view": "sideways"}, "view must be one of"),
        ({"tonemap": "aces"}, "tonemap must be one of"),
        ({"quality": "best"}, "quality must be one of"),
    ],
)
def test_bad_render_requests_get_400_and_the_server_keeps_running(server, body, message):
    client = Client(server)
    status, answer = client.request("POST", "/api/render", raw=json.dumps(body).encode())
    assert status == 400 and message in answer["error"], answer
    assert client.request("GET", "/api/state")[0] == 200


def test_concurrent_renders_are_coalesced_over_http(server):
    """A burst of requests while one renders: the newest is rendered, the waiting ones get 409."""
    client = Client(server)
    release = threading.Event()
    blocked = threading.Event()

    def blocking_job():
        blocked.set()
        release.wait(10)
        return "done"

    holder = threading.Thread(target=server.tuner.queue.submit, args=(blocking_job,))
    holder.start()
    assert blocked.wait(10)
    statuses = {}

    def send(value):
        statuses[value] = client.request("POST", "/api/render", {"quality": "preview", "params": {"exposure": value}})[0]

    senders, waiting = [], None
    for value in (0.1, 0.2, 0.3):
        senders.append(threading.Thread(target=send, args=(value,)))
        senders[-1].start()
        waiting = next_waiting(server.tuner.queue, waiting)  # each waits before the next is sent
    release.set()
    for thread in [holder, *senders]:
        thread.join(60)
    assert statuses == {0.1: 409, 0.2: 409, 0.3: 200}


def test_saved_params_get_the_users_normal_permissions(server):
    previous = os.umask(0o027)
    try:
        status, answer = Client(server).request("POST", "/api/save", {"params": {}})
    finally:
        os.umask(previous)
    assert status == 200 and stat.S_IMODE(os.stat(answer["path"]).st_mode) == 0o640


def test_save_writes_what_apply_reads(server, tmp_path):
    client = Client(server)
    status, answer = client.request("POST", "/api/save", {"params": {"exposure": 0.75, "tint": [1.0, 0.5, 0.25]}})
    assert status == 200, answer
    saved = gr.load_effect(answer["path"])
    assert isinstance(saved, gr.GodRays) and saved.max_samples == 8
    np.testing.assert_allclose(saved.exposure, 0.75)
    np.testing.assert_allclose(saved.tint, [1.0, 0.5, 0.25])
    frame_path = tmp_path / "frame.exr"
    gr.write_buffers(frame_path, server.tuner.buffers, light_xy=(32.0, 6.0))
    out = tmp_path / "out.exr"
    assert main(["apply", str(frame_path), "--params", answer["path"], "-o", str(out)]) == 0
    np.testing.assert_allclose(
        gr.read_image(out)[..., :3], saved(server.tuner.buffers, jnp.asarray([32.0, 6.0])), rtol=1e-5, atol=1e-6
    )


def test_fit_moves_the_free_parameters_toward_the_target(server):
    client = Client(server)
    locked = [name for name in server.tuner.bounds() if name != "exposure"]
    status, progress = client.fit({"params": {"exposure": 0.5}, "fixed": locked})
    assert status == 200 and progress["error"] is None and not progress["cancelled"], progress
    answer = progress["result"]
    assert answer["fitted"] == ["exposure"] and answer["loss_after"] < answer["loss_before"] and not answer["kept_start"]
    assert abs(answer["effect"]["exposure"] - 1.2) < abs(0.5 - 1.2)
    assert answer["effect"]["flare_size"] == pytest.approx(6.0)  # locked, and scaled back to full resolution
    assert client.request("GET", "/api/fit")[1]["running"] is False
    status, answer = client.request("POST", "/api/fit", {"fixed": list(server.tuner.bounds())})
    assert status == 400 and "every parameter is locked" in answer["error"]
    server.tuner.effect = small_effect()


def test_fit_runs_off_the_request_thread_and_can_be_cancelled(server, monkeypatch):
    """While a fit runs, renders are answered; a second fit is 409; cancelling stops it and keeps the effect."""
    client = Client(server)
    before = server.tuner.effect
    stepping = threading.Event()

    monkeypatch.setattr(tuner_module, "fit", fit_until_cancelled(server.tuner, stepping))
    status, started = client.request("POST", "/api/fit", {})
    assert status == 200 and started["running"] is True
    assert stepping.wait(30)
    assert client.request("POST", "/api/render", {"quality": "preview"})[0] == 200
    status, answer = client.request("POST", "/api/fit", {})
    assert status == 409 and "already running" in answer["error"]
    assert client.request("POST", "/api/fit/cancel", {})[0] == 200
    progress = server.tuner.wait_fit(30)
    assert progress["running"] is False and progress["cancelled"] is True and progress["result"] is None
    assert progress["step"] >= 1 and server.tuner.effect is before


def test_fit_without_a_target_is_a_400():
    tuner = Tuner(small_frame(), (32.0, 6.0), effect=small_effect())
    with TuneServer(tuner) as running:
        status, answer = Client(running).request("POST", "/api/fit", {})
    assert status == 400 and "--target" in answer["error"]


def test_preset_replaces_the_effect(server):
    client = Client(server)
    status, state = client.request("POST", "/api/preset", {"name": "kbengine_flares"})
    try:
        assert status == 200 and state["effect"]["effect"] == "FlareOuts"
        assert "scale_step" in state["bounds"] and "density" not in state["bounds"]
    finally:
        server.tuner.effect = small_effect()


def test_fit_rounds_counts_as_the_cli_does_unless_fractional_counts_are_asked(server):
    client = Client(server)
    locked = [name for name in server.tuner.bounds() if name not in ("exposure", "num_samples")]
    start = {"params": {"exposure": 0.5, "num_samples": 6.4}, "fixed": locked}
    status, progress = client.fit(start)
    assert status == 200 and progress["result"], progress
    answer = progress["result"]
    assert answer["effect"]["num_samples"] == round(answer["effect"]["num_samples"])
    status, progress = client.fit({**start, "fractional_counts": True})
    assert status == 200 and progress["result"], progress
    answer = progress["result"]
    assert answer["effect"]["num_samples"] != round(answer["effect"]["num_samples"])
    status, answer = client.request("POST", "/api/fit", {**start, "fractional_counts": "yes"})
    assert status == 400 and "fractional_counts" in answer["error"]


def test_a_frame_of_several_lights_is_tuned_under_all_and_each_is_dragged(tmp_path, monkeypatch):
    """`other_lights` (a frame's several lights): the after view adds their light (`lit_by`, each with its tint),
    each moves to the page's position, the fit takes them at the preview's scale, and the layer view, which draws
    one light, refuses them; the fit refuses a tint of the first light (it fits that light's colour)."""
    frame, effect = small_frame(), small_effect()
    lamp = gr.Light(np.asarray([10.0, 4.0], np.float32), tint=np.asarray([0.5, 1.0, 2.0], np.float32))
    tuner = Tuner(frame, (32.0, 6.0), effect=effect, target=frame.color, other_lights=[lamp],
                  save_path=tmp_path / "params.json")  # fmt: skip

    def shown(**payload):
        path = tmp_path / "shown.png"
        path.write_bytes(decode(tuner.render({"quality": "full", **payload})))
        return oiio.ImageBuf(str(path)).get_pixels(oiio.UINT8).astype(int)

    def expected(xy):
        lights = [gr.Light(jnp.asarray([32.0, 6.0])), eqx.tree_at(lambda light: light.xy, lamp, jnp.asarray(xy))]
        return np.asarray(display_encode(gr.lit_by(effect, frame, lights))).astype(int)

    try:
        assert tuner.state()["other_lights"] == [[10.0, 4.0]]
        there, moved = shown(), shown(other_lights=[[50.0, 20.0]])
        assert np.abs(there - expected([10.0, 4.0])).max() <= 1 and np.abs(moved - expected([50.0, 20.0])).max() <= 1
        alone = np.asarray(display_encode(effect(frame, jnp.asarray([32.0, 6.0])))).astype(int)
        assert np.abs(there - alone).max() > 10 and np.abs(there - moved).max() > 10  # the lamp shows, and moves
        with pytest.raises(tuner_module.TuneRequestError, match="other_lights must be 1"):
            tuner.render({"other_lights": [[1.0, 2.0], [3.0, 4.0]]})
        with pytest.raises(tuner_module.TuneRequestError, match="layer view draws one untinted light"):
            tuner.render({"view": "layer"})
        taken = []

        def fit_stopped(*args, **keywords):
            taken.append(keywords["other_lights"])
            assert keywords["fit_light_tints"] is False  # the tints the page draws with
            raise RuntimeError("stopped where the fit starts")

        monkeypatch.setattr(tuner_module, "fit", fit_stopped)
        tuner.fit({"other_lights": [[50.0, 20.0]]})
        assert "stopped where the fit starts" in tuner.wait_fit(30)["error"]
        (lamp_fitted,) = taken[0]
        np.testing.assert_allclose(np.asarray(lamp_fitted.xy), np.asarray([50.0, 20.0]) / tuner.factor)
        np.testing.assert_array_equal(np.asarray(lamp_fitted.tint), lamp.tint)
    finally:
        tuner.close()
    tinted = Tuner(frame, (32.0, 6.0), effect=effect, target=frame.color, light_tint=(2.0, 1.0, 1.0))
    try:
        with pytest.raises(tuner_module.TuneRequestError, match="fits the first light's colour, untinted"):
            tinted.fit({})
    finally:
        tinted.close()
    with pytest.raises(ValueError, match="other_lights must be a sequence of Light"):
        Tuner(frame, (32.0, 6.0), effect=effect, other_lights=[(10.0, 4.0)])
