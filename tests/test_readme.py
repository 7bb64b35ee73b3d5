"""The README runs as written: its Python block, then its shell commands, in a scratch folder that sees the
checkout's examples/, with `godrays-jax` on PATH running this checkout; its presets table names every preset; and
every preset works on the shipped frames. The docs pages' blocks and commands: tests/test_docs.py.

Shell commands are the lines of ```bash blocks (a listing of options is a plain ``` block). Left out: installing
(`python3 -m venv`, `. .venv/bin/activate`, `pip install`), the test suite itself, `godrays-jax tune` (it serves a
browser page until Ctrl-C), the example and benchmark scripts, which render every picture at full size and have
tests of their own, and the fit of a path-traced reference with the `apply` of its output (see LEFT_OUT).
"""

import os
import re
import shlex
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from frames import slow_where

import godrays_jax as gr
from godrays_jax.app.cli import main

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
INSTALL = ("python3 -m venv", ". .venv/bin/activate", "pip install")
LEFT_OUT = (
    "python -m pytest",
    "godrays-jax tune",
    "python examples/",
    "python benchmarks/",
    # A minute at 320x180: tests/test_fit.py runs the command (test_fit_command_fits_two_frames_and_apply_reproduces),
    "godrays-jax fit",
    # and applies what it wrote, as this line applies the fit's params.json.
    "godrays-jax apply benchmarks/references/hidden_sun_clean.exr --params params.json",
)


def blocks(language: str) -> list[str]:
    """The README's fenced blocks in that language, in order, dedented (list items indent theirs)."""
    fence = re.compile(r"^( *)```" + language + r"\n(.*?)^\1```", re.MULTILINE | re.DOTALL)
    return [textwrap.dedent(match.group(2)) for match in fence.finditer(README)]


def commands() -> list[str]:
    """Every shell command the README shows that a test can run, install steps removed."""
    found = []
    for block in blocks("bash"):
        for line in block.splitlines():
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            parts = [part.strip() for part in line.split("&&") if not part.strip().startswith(INSTALL)]
            if parts and not any(part.startswith(LEFT_OUT) for part in parts):
                found.append(" && ".join(parts))
    return found


@pytest.fixture(scope="module")
def scratch(tmp_path_factory):
    """A folder that sees the checkout's examples/ and has an `out/` of its own."""
    folder = tmp_path_factory.mktemp("readme")
    (folder / "examples").symlink_to(ROOT / "examples")
    (folder / "out").mkdir()
    return folder


@pytest.mark.slow
def test_the_python_blocks_run_in_order(scratch, monkeypatch):
    monkeypatch.chdir(scratch)
    code = blocks("python")
    assert len(code) >= 1 and "effect_loss" in code[0]
    namespace = {}
    for block in code:
        exec(compile(block, "README.md", "exec"), namespace)  # noqa: S102 - the README is the code under test
    assert gr.load_effect(scratch / "params.json").decay == np.float32(0.95)
    assert '"decay": 0.95,' in (scratch / "params.json").read_text()
    assert isinstance(namespace["grads"], gr.GodRays)


def test_the_shell_commands_run_in_order(scratch):
    bin_dir = scratch / "bin"
    bin_dir.mkdir()
    shim = bin_dir / "godrays-jax"
    shim.write_text(f'#!/bin/sh\nexec {shlex.quote(sys.executable)} -m godrays_jax "$@"\n')
    shim.chmod(0o755)
    env = {
        **os.environ,
        "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}",
        "PYTHONPATH": str(ROOT),
        "JAX_PLATFORMS": "cpu",  # the compilation cache: GODRAYS_JAX_CACHE_DIR, set by conftest.py
    }
    ran = commands()
    for command in ran:
        done = subprocess.run(["bash", "-c", command], cwd=scratch, env=env, capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, f"{command}\n{done.stderr[-3000:]}"
    assert any(command.startswith("mkdir -p out && godrays-jax apply") for command in ran)  # the install line's job
    assert (scratch / "out" / "forest_rays.png").is_file()
    # The main job installs without the test extras; the tests install them.
    main_job = next(line for block in blocks("bash") for line in block.splitlines() if "forest_rays.png" in line)
    assert "pip install -e . &&" in main_job and "[test]" not in main_job
    assert 'pip install -e ".[test]"' in README and 'python -m pytest -q -n auto -m "not slow"\n' in README


def test_the_presets_table_names_every_preset():
    table = README[README.index("## Presets") :]
    named = set(re.findall(r"^\| `(\w+)` \|", table, re.MULTILINE))
    assert named == set(gr.PRESETS)


@pytest.mark.parametrize("name", slow_where(sorted(gr.PRESETS)))
def test_every_preset_works_on_the_sample_frame(tmp_path, capsys, name):
    frame_path = ROOT / "examples" / "data" / "sample_frame.exr"
    out = tmp_path / f"{name}.png"
    assert main(["apply", str(frame_path), "--preset", name, "-o", str(out)]) == 0
    err = capsys.readouterr().err
    frame = gr.read_buffers(frame_path)
    assert (err == "") != (getattr(gr.preset(name), "source", None) == "light_pass" and frame.light_pass is None)
    written = np.asarray(gr.read_image(out))
    assert np.isfinite(written).all()
    assert float(np.abs(written - np.clip(np.asarray(frame.color), 0.0, 1.0)).max()) > 0.02  # the effect shows


def test_the_hero_frame_has_every_pass_a_preset_reads():
    hero = gr.read_buffers(ROOT / "examples" / "data" / "forest_hero.exr")
    assert hero.light_pass is not None and hero.glow_pass is not None  # galaxy_vls, sun_overcast
    assert np.isposinf(np.asarray(hero.depth)).any()  # open sky for every sky-lit emitter
