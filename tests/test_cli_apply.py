"""`godrays-jax apply` end to end, and its bad-input contract: one line on stderr, non-zero exit, no output file."""

import dataclasses
import json
import math
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import godrays_jax as gr
from godrays_jax.app import fit_command
from godrays_jax.app.cli import main
from godrays_jax.app.options import CommandError

SAMPLE = Path(__file__).resolve().parents[1] / "examples" / "data" / "sample_frame.exr"


def run_cli(*args):
    """The installed entry point in a subprocess, as a user runs it."""
    return subprocess.run(
        [sys.executable, "-m", "godrays_jax", *map(str, args)], capture_output=True, text=True, timeout=600
    )


def small_frame(path, *, depth=True, nan=False):
    color = np.full((6, 8, 3), 0.2, np.float32)
    color[1:3, 2:5] = 5.0
    if nan:
        color[0, 0, 1] = np.nan
    zs = np.full((6, 8), np.inf, np.float32)
    zs[4:, :] = 3.0
    if depth:
        gr.write_buffers(path, gr.Buffers(color=color, depth=zs, coverage=np.isfinite(zs).astype(np.float32)))
    else:
        gr.write_image(path, color)
    return path


def test_apply_writes_the_composited_frame(tmp_path):
    output = tmp_path / "out.exr"
    assert main(["apply", str(SAMPLE), "--preset", "kbengine_flares", "-o", str(output)]) == 0
    frame = gr.read_buffers(SAMPLE)
    (light, _) = gr.read_light(SAMPLE)
    expected = gr.preset("kbengine_flares")(frame, np.asarray(light, np.float32))
    written = gr.read_image(output)
    np.testing.assert_allclose(written[..., :3], expected, rtol=1e-3, atol=1e-5)  # the frame's half colour channels
    np.testing.assert_array_equal(written[..., 3:], gr.read_image(SAMPLE)[..., 3:])  # A, Z, passes as they were
    assert gr.read_light(output) == gr.read_light(SAMPLE)
    assert sorted(os.listdir(tmp_path)) == ["out.exr"]


def test_apply_with_params_file_and_layer_only(tmp_path):
    params = tmp_path / "params.json"
    effect = gr.GodRays(num_samples=16.0, max_samples=16, density=0.9, exposure=0.3, flare_size=12.0, units="px")
    gr.save_effect(params, effect)
    assert json.loads(params.read_text())["effect"] == "GodRays"
    output = tmp_path / "layer.png"
    assert main(["apply", str(SAMPLE), "--params", str(params), "--light", "200.5,60.25", "--layer-only", "-o", str(output)]) == 0
    written = gr.read_image(output)
    assert written.shape == (180, 320, 3) and float(written.max()) > 0.1


@pytest.mark.parametrize(
    "case",
    [
        "missing_file", "not_an_image", "no_depth", "bad_light", "bad_light_side", "nan_colour", "bad_params",
        "overwrite_input", "no_light", "light_tints_for_other_lights", "bad_light_tint", "several_layer_only",
    ],
)
def test_apply_bad_input_is_one_line_and_leaves_no_output(tmp_path, case):
    frame = small_frame(tmp_path / "frame.exr")
    output = tmp_path / "out.png"
    args = ["apply", frame, "--light", "3,2", "-o", output]
    expected = None
    if case == "missing_file":
        args[1], expected = tmp_path / "missing.exr", "does not exist"
    elif case == "not_an_image":
        bogus = tmp_path / "notes.exr"
        bogus.write_text("not an image")
        args[1], expected = bogus, "cannot read image"
    elif case == "no_depth":  # a frame without depth runs the shaft presets, not a medium
        args[1], expected = small_frame(tmp_path / "flat.exr", depth=False), "presets that run without depth"
        args += ["--preset", "participating_media"]
    elif case == "bad_light":
        args[3], expected = "3;2", "--light must be X,Y"
    elif case == "bad_light_side":
        args[3], expected = "3,2,above", "X,Y,behind"
    elif case == "nan_colour":
        args[1], expected = small_frame(tmp_path / "nan.exr", nan=True), "NaN"
    elif case == "bad_params":
        params = tmp_path / "params.json"
        params.write_text('{"effect": "GodRays", "densty": 1}')
        args += ["--params", params]
        expected = "unknown parameter"
    elif case == "overwrite_input":
        shutil.copy(frame, output.with_suffix(".exr"))
        args[1] = args[5] = output.with_suffix(".exr")
        expected = "refusing to overwrite"
    elif case == "no_light":
        del args[2:4]
        expected = "--light"
    elif case == "light_tints_for_other_lights":
        args[3] = "3,2;5,1"
        args += ["--light-tint", "1,1,1;1,1,1;1,1,1"]
        expected = "--light-tint gives 3 values for 2 lights"
    elif case == "bad_light_tint":
        args += ["--light-tint", "1,x,1"]
        expected = "--light-tint must be R,G,B"
    elif case == "several_layer_only":
        args[3] = "3,2;5,1"
        args += ["--layer-only"]
        expected = "--layer-only draws one light as the effect has it"
    before = sorted(os.listdir(tmp_path))
    result = run_cli(*args)
    assert result.returncode != 0
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert expected in lines[0] and "Traceback" not in result.stderr
    assert sorted(os.listdir(tmp_path)) == before, "a failed run must not leave files behind"


@pytest.mark.parametrize("side", ["front", "behind"])
def test_apply_takes_a_light_behind_the_camera(tmp_path, side):
    """`--light X,Y,behind` is the light behind the camera, as a frame's header says it: the effect with
    `light_in_front=False`; `X,Y,front` is plain `X,Y`."""
    frame_path, output = small_frame(tmp_path / "frame.exr"), tmp_path / "out.exr"
    assert main(["apply", str(frame_path), "--preset", "participating_media", "--light", f"3,2,{side}", "-o", str(output)]) == 0
    frame = gr.read_buffers(frame_path)
    effect = gr.preset("participating_media")
    expected = effect(frame, np.asarray([3.0, 2.0], np.float32), light_in_front=side == "front")
    other = effect(frame, np.asarray([3.0, 2.0], np.float32), light_in_front=side != "front")
    assert not np.allclose(expected, other)  # the side matters to this frame
    np.testing.assert_allclose(gr.read_image(output)[..., :3], expected[..., :3], rtol=1e-3, atol=1e-5)


def test_verbose_adds_the_traceback_after_the_one_line(tmp_path):
    """`--verbose` (every command's) keeps the error's one line first and adds its traceback; without it, one line."""
    args = ["apply", tmp_path / "missing.exr", "--light", "3,2", "-o", tmp_path / "out.png"]
    quiet, verbose = run_cli(*args), run_cli(*args, "--verbose")
    assert quiet.returncode == verbose.returncode == 1
    assert len(quiet.stderr.strip().splitlines()) == 1
    lines = verbose.stderr.strip().splitlines()
    assert lines[0] == quiet.stderr.strip() and "Traceback" in verbose.stderr and len(lines) > 3


def test_every_command_has_help(capsys):
    """The program's help lists every command, and each answers `--help` of its own."""
    from godrays_jax.app.cli import COMMANDS

    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    listed = capsys.readouterr().out
    commands = re.findall(r"^ {4}(\w[\w-]*)(?: |$)", listed, re.MULTILINE)  # `    apply     apply an effect ...`
    assert "apply" in commands and len(set(commands)) == len(COMMANDS)
    for name in commands:
        with pytest.raises(SystemExit) as exit_info:
            main([name, "--help"])
        assert exit_info.value.code == 0


def test_a_render_of_several_lights_is_applied_with_every_one(tmp_path, capsys, monkeypatch):
    """`render` of a scene with `lights` writes each one's pixel, side, distance and tint (its colour over the first
    light's, channel by channel) into the frame's header; `apply` without `--light` draws them all, as `--light` with the same
    lights, distances and tints does, and so does `fit` (each tint over the first's); `--layer-only` (one light) and
    `batch` (each frame's first) say what they draw."""
    scene = tmp_path / "scene.json"
    scene.write_text(json.dumps({
        "camera": {"position": [0, 0, 0], "target": [0, 0, -1], "up": [0, 1, 0], "fov_x_deg": 60, "width": 16,
                   "height": 12},
        "lights": [{"type": "directional", "direction": [0.1, 0.1, -1], "color": [2, 1, 1]},
                   {"type": "point", "position": [-2, 0, -6], "color": [1, 0.5, 0.5]}],
        "objects": [{"type": "sphere", "center": [0.4, 0, -5], "radius": 0.7, "material": {"albedo": [0.5, 0.5, 0.5]}}],
    }))  # fmt: skip
    frame, drawn, given = tmp_path / "frame.exr", tmp_path / "drawn.exr", tmp_path / "given.exr"
    assert main(["render", str(scene), "-o", str(frame), "--light"]) == 0
    assert [line.split()[0] for line in capsys.readouterr().out.splitlines()] == ["light", "light", "wrote"]
    stored = gr.read_lights(frame)
    assert [light.in_front for light in stored] == [True, True] and stored[0].depth == np.inf
    assert stored[1].depth == pytest.approx(math.hypot(2, 6)) and stored[1].tint == pytest.approx((0.5, 0.5, 0.5))
    assert main(["apply", str(frame), "--preset", "xna_crepuscular", "-o", str(drawn)]) == 0
    lights = ";".join(f"{light.xy[0]!r},{light.xy[1]!r}" for light in stored)
    assert main(["apply", str(frame), "--preset", "xna_crepuscular", "--light", lights, "--light-depth",
                 f"inf;{stored[1].depth!r}", "--light-tint", "1;0.5", "-o", str(given)]) == 0  # fmt: skip
    np.testing.assert_array_equal(gr.read_image(drawn), gr.read_image(given))
    one = tmp_path / "one.exr"
    first = lights.split(";")[0]
    assert main(["apply", str(frame), "--preset", "xna_crepuscular", "--light", first, "-o", str(one)]) == 0
    assert not np.allclose(gr.read_image(one), gr.read_image(drawn))  # the second light shows
    capsys.readouterr()
    layer = tmp_path / "layer.exr"
    assert main(["apply", str(frame), "--preset", "xna_crepuscular", "--layer-only", "-o", str(layer)]) == 1
    assert "stores 2 lights (godrays:lights) and --layer-only draws one" in capsys.readouterr().err
    assert main(["batch", str(frame), "-o", str(tmp_path / "out"), "--preset", "xna_crepuscular", "--dry-run"]) == 0
    assert "2 lights (godrays:lights): batch draws the first (godrays:light_px)" in capsys.readouterr().err

    # `fit` draws them all too: the header's lights as `--light` with the same distances and tints gives them.
    taken = []

    def stop(*args, **keywords):
        taken.append((args[2], keywords["light_depth"], keywords["other_lights"]))
        raise CommandError("stopped where the fit starts")

    monkeypatch.setattr(fit_command, "fit", stop)
    fit_arguments = ["fit", str(frame), str(drawn), "--preset", "xna_crepuscular", "-o", str(tmp_path / "p.json")]
    assert main(fit_arguments) == 1
    assert main([*fit_arguments, "--light", lights, "--light-depth", f"inf;{stored[1].depth!r}", "--light-tint",
                 "2;1"]) == 1  # fmt: skip
    for (first, depths, others), tint in zip(taken, (0.5, 0.5)):  # a tint over the first's: 0.5 / 1 and 1 / 2
        np.testing.assert_allclose(np.asarray(first[0]), stored[0].xy, rtol=1e-6)
        assert depths == [np.inf] and len(others) == 1 and len(others[0]) == 1
        np.testing.assert_allclose(np.asarray(others[0][0].xy), stored[1].xy, rtol=1e-6)
        assert others[0][0].depth == pytest.approx(stored[1].depth) and others[0][0].in_front
        np.testing.assert_allclose(np.asarray(others[0][0].tint), tint, rtol=1e-6)
    assert "fit draws" not in capsys.readouterr().err


@pytest.mark.slow
def test_fit_of_a_frame_of_two_lights_fits_under_both_and_refuses_what_draws_one(tmp_path, capsys):
    """`fit --light 'A;B'` fits the fields under both lights and the second's tint over the first's, from a wrong
    one, and `apply --params` with the same lights and the tint it prints gives the fitted frame; `--fixed
    light_tints` keeps the tint given; `--fit-light` (one light refined), `--light auto` with tints and a count of
    distances that fits neither one nor every light are one line each, with no file written."""
    frame = tmp_path / "frame.exr"
    zs = np.full((16, 24), np.inf, np.float32)
    zs[10:], zs[3:, 8:10] = 4.0, 3.0  # the ground and a post
    color = np.where(np.isfinite(zs)[..., None], 0.1, 0.3).astype(np.float32) * np.ones(3, np.float32)
    color[2:4, 4:7] = color[1:3, 15:17] = 5.0  # the lights' discs
    gr.write_buffers(frame, gr.Buffers(color=color, depth=zs, coverage=np.isfinite(zs).astype(np.float32)))
    target, params, fitted = tmp_path / "target.exr", tmp_path / "p.json", tmp_path / "fitted.exr"
    lights = ["--light", "5.5,3;16,2", "--light-tint", "1;0.5"]
    start = gr.preset("xna_crepuscular")
    fitted_names = ("density", "decay", "exposure")
    truth = tmp_path / "truth.json"
    gr.save_effect(truth, dataclasses.replace(start, density=0.7, decay=0.9, exposure=0.4))
    assert main(["apply", str(frame), "--params", str(truth), *lights, "-o", str(target)]) == 0
    fixed = ",".join(name for name in gr.parameter_bounds(start) if name not in fitted_names)
    arguments = ["fit", str(frame), str(target), "--preset", "xna_crepuscular", "-o", str(params), "--max-steps", "20"]
    wrong = [*lights[:2], "--light-tint", "1;1"]
    assert main([*arguments, *wrong, "--fixed", fixed]) == 0
    out = capsys.readouterr().out
    assert float(re.search(r"loss before \S+, after (\S+)", out).group(1)) < 1e-6
    tints = re.search(r"light_tints = (\S+) ", out).group(1)
    np.testing.assert_allclose([float(v) for v in tints.split(";")[1].split(",")], 0.5, rtol=0.01)
    # `apply --params` takes the tints from beside the parameters (`p.light.json`), as `--light-tint` gives them.
    assert json.loads((tmp_path / "p.light.json").read_text())["light_tints"] == [pytest.approx([0.5] * 3, rel=0.01)]
    assert main(["apply", str(frame), "--params", str(params), *lights[:2], "-o", str(fitted)]) == 0
    assert f"light tints {tints} from {tmp_path / 'p.light.json'} (fitted by fit)" in capsys.readouterr().out
    np.testing.assert_allclose(gr.read_image(fitted), gr.read_image(target), atol=1e-3)
    given = ["--light-tint", tints]
    assert main(["apply", str(frame), "--params", str(params), *lights[:2], *given, "-o", str(fitted)]) == 0
    np.testing.assert_allclose(gr.read_image(fitted), gr.read_image(target), atol=1e-3)
    assert main([*arguments, *wrong, "--fixed", f"{fixed},light_tints"]) == 0
    out = capsys.readouterr().out
    assert "light_tints =" not in out and float(re.search(r"loss before \S+, after (\S+)", out).group(1)) > 1e-5
    assert not (tmp_path / "p.light.json").exists()  # a fit that fits no tint leaves none for apply to read
    for extra, message in (
        (["--light", "5.5,3;16,2", "--fit-light"], "--fit-light refines one light"),
        (["--light", "auto", "--light-tint", "1;0.5"], "--light auto finds the lights"),
        (["--light", "5.5,3;16,2", "--light-depth", "inf;2;3"], "--light-depth gives 3 values for 2 lights"),
    ):
        output = tmp_path / "refused.json"
        assert main(["fit", str(frame), str(target), "-o", str(output), *extra]) == 1
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1, err
        assert not output.exists() and not (tmp_path / "refused.light.json").exists()


@pytest.mark.slow
def test_apply_adds_several_lights_each_with_its_side_distance_and_tint(tmp_path):
    """`--light 'A;B,behind'` with a distance and a tint per light is `lit_by` of those lights; one tint and one
    distance are every light's."""
    frame_path, output = small_frame(tmp_path / "frame.exr"), tmp_path / "out.exr"
    arguments = ["apply", str(frame_path), "--preset", "physically_based", "--light", "3,2;6.5,1,behind",
                 "--light-depth", "inf;12", "--light-tint", "1,0.5,0.25;2", "-o", str(output)]  # fmt: skip
    assert main(arguments) == 0
    frame, effect = gr.read_buffers(frame_path), gr.preset("physically_based")
    lights = [gr.Light(np.asarray([3.0, 2.0], np.float32), tint=(1.0, 0.5, 0.25)),
              gr.Light(np.asarray([6.5, 1.0], np.float32), in_front=False, depth=12.0, tint=(2.0, 2.0, 2.0))]  # fmt: skip
    expected = np.asarray(gr.lit_by(effect, frame, lights))
    assert not np.allclose(expected, effect(frame, lights[0].xy))  # the second light shows
    at_infinity = [lights[0], dataclasses.replace(lights[1], depth=np.inf)]
    assert not np.allclose(expected, gr.lit_by(effect, frame, at_infinity))  # and its distance
    np.testing.assert_allclose(gr.read_image(output)[..., :3], expected[..., :3], rtol=1e-3, atol=1e-5)
    shared = tmp_path / "shared.exr"
    assert main([*arguments[:-6], "--light-tint", "2", "-o", str(shared)]) == 0
    every = [gr.Light(light.xy, in_front=light.in_front, tint=(2.0, 2.0, 2.0)) for light in lights]
    np.testing.assert_allclose(gr.read_image(shared)[..., :3], np.asarray(gr.lit_by(effect, frame, every))[..., :3],
                               rtol=1e-3, atol=1e-5)  # fmt: skip
