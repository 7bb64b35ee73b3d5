"""`godrays-jax tune` from the command line: errors are one line."""


import numpy as np

import godrays_jax as gr
from godrays_jax.app.cli import main
from godrays_jax.app.server import TuneServer
from godrays_jax.app.tuner import Tuner

from tune_support import small_effect, small_frame


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
