"""The picture scripts run from any directory: paths come from the script's own location, pictures go where told."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest

import godrays_jax as gr

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_gallery_runs_from_another_folder_and_labels_every_preset(tmp_path):
    """On the sample frame every preset gets a tile: without a light pass `apply` draws the light-pass preset's disc."""
    frame = ROOT / "examples" / "data" / "sample_frame.exr"
    work = tmp_path / "elsewhere"
    work.mkdir()
    env = {**os.environ, "PYTHONPATH": str(ROOT), "JAX_PLATFORMS": "cpu"}
    done = subprocess.run(
        [sys.executable, str(ROOT / "examples" / "gallery.py"), "--frame", str(frame), "--out", str(tmp_path / "pictures")],
        cwd=work, env=env, capture_output=True, text=True, timeout=900,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    assert list(work.iterdir()) == []  # nothing written where it ran
    drawn = sorted(p.stem for p in (tmp_path / "pictures").glob("*.png") if p.stem != "gallery")
    assert drawn == sorted(gr.PRESETS)
    assert "has no light pass (light.Y): using the disc emitter" in done.stderr
    sheet = oiio.ImageBuf(str(tmp_path / "pictures" / "gallery.png")).get_pixels(oiio.FLOAT)
    tiles = len(drawn) + 1  # the input frame first
    rows = -(-tiles // 3)
    assert sheet.shape[0] == rows * (270 + 24) and sheet.shape[1] == 3 * 480
    label_strip = sheet[:24, :480]
    assert 0.0 < float(np.mean(label_strip > 0.5)) < 0.5  # white lettering on black
