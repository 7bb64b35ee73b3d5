"""Finding the light from a frame and a target (`find_light`, `halo_starts`) and `godrays-jax fit --light auto` /
`--fit-light`: targets drawn by a known light on a small frame are found again, on screen, near an edge and just off
it, and the command writes the light beside its parameters for `apply --params`."""

import json
import re

import jax.numpy as jnp
import numpy as np
import pytest

import godrays_jax as gr
from godrays_jax.app import allocator, fit_command
from godrays_jax.app.cli import main
from godrays_jax.pipeline.light_profile import LightProfile

HEIGHT, WIDTH = 36, 64
TINT = (0.9, 0.7, 0.45)


def _frame() -> gr.Buffers:
    """Sky above a ground at row 24 and a pillar: the XNA preset's flare and rays shine through the sky."""
    depth = np.full((HEIGHT, WIDTH), np.inf, np.float32)
    depth[24:] = 20.0
    depth[:, 38:42] = 10.0
    coverage = np.isfinite(depth).astype(np.float32)
    color = np.where(coverage[..., None] > 0, 0.05, 0.3).astype(np.float32) * np.ones(3, np.float32)
    return gr.Buffers(color=jnp.asarray(color), depth=jnp.asarray(depth), coverage=jnp.asarray(coverage))


def _effect(tint=(1.0, 0.85, 0.6)) -> gr.GodRays:
    return gr.replace_fields(gr.preset("xna_crepuscular"), {"tint": tint})


def _target(light) -> jnp.ndarray:
    return _effect(TINT)(_frame(), jnp.asarray(light, jnp.float32))


LIGHTS = {"on screen": (22.3, 10.6), "near an edge": (2.2, 8.4), "just off screen": (-3.5, 9.2)}


@pytest.mark.parametrize("case", list(LIGHTS))
def test_a_light_is_found_from_a_start_several_pixels_away(case):
    light = np.asarray(LIGHTS[case])
    start = light + (5.0, 4.0)
    found = gr.find_light(_effect(), _frame(), _target(light), start_xy=start)
    assert np.linalg.norm(found.light_xy - light) < 1.0, (found.light_xy, light)
    np.testing.assert_allclose(np.asarray(gr.field_value(found.effect, "tint")), TINT, atol=0.05)
    np.testing.assert_array_equal(found.start_xy, start)
    assert found.factor == 1 and found.fields == ("tint",)


@pytest.mark.parametrize("case", list(LIGHTS))
def test_a_light_is_found_from_the_targets_halo(case):
    light = np.asarray(LIGHTS[case])
    found = gr.find_light(_effect(), _frame(), _target(light))
    assert np.linalg.norm(found.light_xy - light) < 1.0, (found.light_xy, found.start_xy, light)


@pytest.mark.slow
@pytest.mark.parametrize("light", [(-12.0, 12.0), (30.0, -10.0)])
def test_the_halo_of_a_light_off_screen_gives_starts_past_the_edge_nearest_it(light):
    """The XNA preset's rays reach a few pixels (decay .95 per sample): `gpu_gems`' cross the frame, so its halo
    still shows a light a fifth of the frame off screen, and its peak lies on the edge nearest the light."""
    effect = gr.preset("gpu_gems")
    target = gr.replace_fields(effect, {"tint": (0.5, 0.4, 0.3)})(_frame(), jnp.asarray(light))
    starts = gr.halo_starts(_frame(), target)
    outside = (starts[:, 0] < 0) | (starts[:, 1] < 0)
    assert np.any(outside) and np.all(starts[:, 0] < WIDTH) and np.all(starts[:, 1] < HEIGHT), starts
    assert np.min(np.linalg.norm(starts - light, axis=1)) < 5.0, starts
    found = gr.find_light(effect, _frame(), target)
    assert np.linalg.norm(found.light_xy - light) < 1.0, (found.light_xy, found.start_xy)


def test_the_halo_of_a_light_on_screen_gives_starts_on_screen_near_it():
    light = LIGHTS["on screen"]
    starts = gr.halo_starts(_frame(), _target(light))
    assert np.all((starts >= 0) & (starts <= (WIDTH, HEIGHT))), starts
    assert np.min(np.linalg.norm(starts - light, axis=1)) < 4.0, starts


def test_the_determination_is_small_for_a_sharp_halo_and_large_where_the_target_shows_no_light():
    light = LIGHTS["on screen"]
    found = gr.find_light(_effect(), _frame(), _target(light), start_xy=light)
    assert np.all(np.isfinite(found.standard_error)) and np.all(found.standard_error < 0.1), found.standard_error
    assert np.all(np.isfinite(found.visible_shift)) and np.all(found.visible_shift < 0.5), found.visible_shift
    np.testing.assert_allclose(found.standard_error, np.sqrt(np.diag(found.covariance)))
    unchanged = gr.find_light(_effect(), _frame(), _frame().color, start_xy=light)
    assert np.all(unchanged.visible_shift > 100.0), unchanged.visible_shift
    assert np.all(unchanged.standard_error > 100.0 * found.standard_error), unchanged.standard_error


@pytest.mark.slow
def test_more_fields_race_the_starts_given():
    """Beyond the colours, the light and `fields` descend again, from the effect and from each of `starts`: the
    start that shares the target's decay wins, and the light, decay and tint are the target's. `progress` hears of
    every evaluation of every start in both descents, in order, with the loss there: the search's own lies among
    them."""
    light = np.asarray(LIGHTS["on screen"])
    target = gr.replace_fields(_effect(TINT), {"decay": 0.8})(_frame(), jnp.asarray(light, jnp.float32))
    starts = [gr.replace_fields(_effect(), {"decay": 0.99}), gr.replace_fields(_effect(), {"decay": 0.8})]
    heard = []
    found = gr.find_light(_effect(), _frame(), target, start_xy=light + 3.0, fields=("tint", "decay"), starts=starts,
                          progress=lambda evaluations, loss: heard.append((evaluations, loss)))  # fmt: skip
    assert [evaluations for evaluations, _ in heard] == list(range(1, found.steps + 1)) and found.steps > 3
    assert min(loss for _, loss in heard) == pytest.approx(found.loss, rel=1e-12)
    assert np.linalg.norm(found.light_xy - light) < 0.1, found.light_xy
    assert found.fields == ("decay", "tint") and found.start == 2  # the effect's order; starts[1]
    assert abs(float(gr.field_value(found.effect, "decay")) - 0.8) < 1e-3
    np.testing.assert_allclose(np.asarray(gr.field_value(found.effect, "tint")), TINT, atol=1e-3)


def test_the_fog_finds_the_sun_where_it_finds_a_point_light_far_beyond_the_scene():
    """The search takes the sun as a Python number (its programs without the point light's branches, as `fit`'s)
    and a point light's distance as an array: the light drawn as the sun is found from 3.6 px away, and as a lamp a
    million units away too."""
    effect = gr.VolumetricFog(medium=gr.Medium(extinction=0.05, light_color=(2.0, 2.0, 2.0)), fov_x_deg=60.0,
                              shadows="lines", num_shadow_lines=24, num_shadow_bins=12)  # fmt: skip
    light = np.asarray(LIGHTS["on screen"])
    target = gr.replace_fields(effect, {"medium.light_color": TINT})(_frame(), jnp.asarray(light, jnp.float32))
    found = {
        depth: gr.find_light(effect, _frame(), target, start_xy=light + (3.0, 2.0), light_depth=depth, max_steps=8)
        for depth in (np.inf, 1e6)
    }
    for depth, search in found.items():
        assert np.linalg.norm(search.light_xy - light) < 0.1, (depth, search.light_xy)


@pytest.mark.parametrize(
    ("arguments", "named"),
    [
        ({"target": np.zeros((HEIGHT, WIDTH + 1, 3))}, "target"),
        ({"start_xy": (1.0, np.nan)}, "start_xy"),
        ({"fields": ("tint", "nonsense")}, "fields"),
        ({"starts": [gr.preset("kbengine_flares")]}, "starts"),
        ({"factor": 0}, "factor"),
        ({"max_steps": 0}, "max_steps"),
        ({"light_depth": -1.0}, "light_depth"),
        ({"space": "log"}, "space"),
    ],
)
def test_errors_name_the_argument(arguments, named):
    given = {"target": _target(LIGHTS["on screen"]), **arguments}
    with pytest.raises(ValueError, match=named):
        gr.find_light(_effect(), _frame(), given.pop("target"), **given)


# Every fittable field but the tint held: the command's fit and its search stay short.
HELD = "flare_size,offscreen_fade,fov_x_deg,density,decay,weight,exposure,sun_size,threshold,num_samples"


def _files(tmp_path, light):
    frame, target = tmp_path / "frame.exr", tmp_path / "target.exr"
    gr.write_buffers(frame, _frame())  # no godrays:light_px: the light is not known
    gr.write_image(target, np.asarray(_target(light)))
    return frame, target


def _fit(*arguments) -> list[str]:
    return ["fit", *map(str, arguments), "--preset", "xna_crepuscular", "--fixed", HELD, "--max-steps", "2"]


def test_fit_light_auto_finds_the_light_and_apply_params_uses_it(tmp_path, capsys, monkeypatch):
    light = np.asarray(LIGHTS["on screen"])
    frame, target = _files(tmp_path, light)
    params = tmp_path / "params.json"
    handed_back, searches = [], []  # the heap's free pages: after each search evaluation, the search, each fit
    monkeypatch.setattr(allocator, "hand_back_free_memory", lambda: handed_back.append(1) or True)

    def find_light(*args, **options):
        searches.append(gr.find_light(*args, **options))
        return searches[-1]

    monkeypatch.setattr(fit_command, "find_light", find_light)
    assert main([*_fit(frame, target, "-o", params), "--light", "auto"]) == 0
    out = capsys.readouterr().out
    assert len(handed_back) == searches[0].steps + 1 + out.count("a fit with the light at "), (len(handed_back), out)
    (line,) = [line for line in out.splitlines() if line.startswith("light of")]
    assert "from the target's halo" in line, out
    # Then placed by whole fits around the light found (`light_profile`), each fit's light and loss a line.
    assert out.count("a fit with the light at ") >= 6 and "placed at " in out, out
    (entry,) = json.loads((tmp_path / "params.light.json").read_text())["lights"]
    assert entry["frame"] == "frame.exr" and entry["size"] == [WIDTH, HEIGHT]
    assert np.linalg.norm(np.asarray(entry["light_px"]) - light) < 1.0, entry
    # The search's standard error was its light's: the light the fits placed has the move they see instead.
    assert entry["standard_error_px"] == [None, None], entry
    assert "raises a whole fit's loss by 1e-06" in out, out
    # Where the model is the target's, the fits see the move the search's Jacobian sees.
    searched = re.search(r"a move of ([\d.e-]+) px in x or ([\d.e-]+) px in y changes the frame", out)
    np.testing.assert_allclose(entry["visible_shift_px"], [float(v) for v in searched.groups()], rtol=0.5)

    output = tmp_path / "applied.exr"
    assert main(["apply", str(frame), "--params", str(params), "-o", str(output)]) == 0
    assert "from " + str(tmp_path / "params.light.json") in capsys.readouterr().out
    drawn = gr.load_effect(params)(gr.read_buffers(frame), jnp.asarray(entry["light_px"], jnp.float32))
    np.testing.assert_allclose(np.asarray(gr.read_image(output))[..., :3], np.asarray(drawn)[..., :3], atol=2e-3)


@pytest.mark.parametrize("placed_at_a_fit", [True, False])
def test_fit_light_auto_keeps_the_fit_at_the_light_placed_where_it_ran_one(tmp_path, capsys, monkeypatch, placed_at_a_fit):
    # The command's fit at the light placed is the fit the profile ran there, when it ran one: not run again.
    frame, target = _files(tmp_path, np.asarray(LIGHTS["on screen"]))
    calls = []

    def counted_fit(*arguments, **options):
        calls.append(arguments[2])
        return fit(*arguments, **options)

    def two_fits(fitted_loss, start_xy, *, step, visible_rise):
        tried = np.asarray([start_xy, np.asarray(start_xy) + [step, 0.0]], np.float64)
        losses = np.asarray([fitted_loss(xy) for xy in tried])
        light = tried[np.argmin(losses)] if placed_at_a_fit else tried[0] + [step / 2, 0.0]
        return LightProfile(light, tried, losses, np.full(2, np.nan))

    fit = fit_command.fit
    monkeypatch.setattr(fit_command, "fit", counted_fit)
    monkeypatch.setattr(fit_command, "profile_light", two_fits)
    params = tmp_path / "params.json"
    assert main([*_fit(frame, target, "-o", params), "--light", "auto"]) == 0
    out = capsys.readouterr().out
    losses = [float(v) for v in re.findall(r"a fit with the light at \S+ px: loss (\S+)", out)]
    after = float(re.search(r"loss before \S+, after (\S+) ", out).group(1))
    assert len(losses) == 2 and len(calls) == (2 if placed_at_a_fit else 3), out
    assert ("its result is kept" in out) == placed_at_a_fit, out
    if placed_at_a_fit:
        assert after == pytest.approx(min(losses), rel=1e-5), out  # the rounded counts' loss: the same fields
    (entry,) = json.loads((tmp_path / "params.light.json").read_text())["lights"]
    kept = calls[int(np.argmin(losses))] if placed_at_a_fit else calls[2]
    np.testing.assert_allclose(entry["light_px"], np.asarray(kept[0]), atol=1e-4)


def test_fit_light_refines_the_light_given_and_a_later_fit_without_it_removes_the_file(tmp_path, capsys):
    light = np.asarray(LIGHTS["near an edge"])
    frame, target = _files(tmp_path, light)
    params, lights = tmp_path / "params.json", tmp_path / "params.light.json"
    assert main([*_fit(frame, target, "-o", params), "--light", "5,11", "--fit-light"]) == 0
    assert "refined from 5,11" in capsys.readouterr().out
    (entry,) = json.loads(lights.read_text())["lights"]
    assert np.linalg.norm(np.asarray(entry["light_px"]) - light) < 1.0, entry
    assert main([*_fit(frame, target, "-o", params), "--light", "5,11"]) == 0
    assert not lights.exists()  # its light was another fit's: apply --params must not read it


def test_fit_light_errors_are_one_line_naming_the_argument(tmp_path, capsys):
    frame, target = _files(tmp_path, LIGHTS["on screen"])
    params = tmp_path / "params.json"
    assert main([*_fit(frame, target, "-o", params), "--fit-light"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "--light" in err and "stores no light position" in err, err
    assert main([*_fit(frame, target, "-o", params), "--light", "3,4,behind", "--fit-light"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.endswith("fit without --fit-light") and "--fit-light: " in err, err
    with pytest.raises(SystemExit) as exit_:
        main([*_fit(frame, target, "-o", params), "--light", "somewhere"])
    assert exit_.value.code == 2 and "--light" in capsys.readouterr().err
    assert not params.exists() and not (tmp_path / "params.light.json").exists()
