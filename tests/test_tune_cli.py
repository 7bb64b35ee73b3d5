"""`godrays-jax tune` from the command line: errors are one line."""


import numpy as np

import godrays_jax as gr
from godrays_jax.app.cli import main
from godrays_jax.app.server import TuneServer
from godrays_jax.app.tuner import Tuner

from tune_support import served_tuners, small_effect, small_frame


def test_cli_tune_errors_are_one_line(tmp_path, capsys):
    frame_path = tmp_path / "frame.exr"
    gr.write_buffers(frame_path, small_frame(), light_xy=(32.0, 6.0))
    wrong_size = tmp_path / "target.exr"
    gr.write_image(wrong_size, np.zeros((10, 10, 3), np.float32))
    assert main(["tune", str(frame_path), "--target", str(wrong_size), "--port", "0"]) == 1
    assert "they must match" in capsys.readouterr().err
    with TuneServer(Tuner(small_frame(), (1.0, 1.0), effect=small_effect())) as busy:
        code = main(["tune", str(frame_path), "--port", str(busy.port), "-o", str(tmp_path / "p.json")])
    err = capsys.readouterr().err
    assert code == 1 and err.count("\n") == 1 and f"cannot listen on 127.0.0.1:{busy.port}" in err
    assert main(["tune", str(tmp_path / "missing.exr"), "--port", "0"]) == 1
    assert "does not exist" in capsys.readouterr().err


def test_cli_tune_takes_every_light_a_frame_stores(tmp_path, monkeypatch):
    """Without `--light`, a frame that stores several lights (`godrays:lights`) is tuned under all of them: the first
    as the tuner's light, the others beside it with their distances and tints; `--light` gives one light alone, or
    several with `--light-depth` and `--light-tint` as `apply` takes them."""
    frame_path = tmp_path / "frame.exr"
    lights = [gr.StoredLight((32.0, 6.0)), gr.StoredLight((10.0, 4.0), True, 12.0, (0.5, 1.0, 2.0))]
    gr.write_buffers(frame_path, small_frame(), light_xy=(32.0, 6.0), metadata=gr.lights_metadata(lights))
    served = served_tuners(monkeypatch)
    arguments = ["tune", str(frame_path), "--preset", "xna_crepuscular", "-o", str(tmp_path / "p.json")]
    assert main(arguments) == 0 and main([*arguments, "--light", "20,5"]) == 0
    given = ["--light", "20,5;40,9,behind", "--light-depth", "inf;7", "--light-tint", "2;1,0.5,0.25"]
    assert main([*arguments, *given]) == 0
    (every, one, both) = served
    assert every.light_xy == (32.0, 6.0) and len(every.other_lights) == 1 and every.light_tint is None
    assert one.light_xy == (20.0, 5.0) and one.other_lights == [] and one.light_tint is None
    lamp = every.other_lights[0]
    np.testing.assert_array_equal(lamp.xy, [10.0, 4.0])
    assert lamp.depth == 12.0 and np.asarray(lamp.tint).tolist() == [0.5, 1.0, 2.0]
    (behind,) = both.other_lights
    assert both.light_xy == (20.0, 5.0) and both.light_depth == np.inf and both.light_tint.tolist() == [2.0, 2.0, 2.0]
    assert behind.in_front is False and behind.depth == 7.0 and np.asarray(behind.tint).tolist() == [1.0, 0.5, 0.25]
