"""The command line's persistent compilation cache: where it lives, what it stores, `--no-cache`, `cache --clear`."""

import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import pytest

import godrays_jax as gr
from godrays_jax.app import compile_cache
from godrays_jax.primitives.checks import checked_count, ranges_guaranteed

ROOT = Path(__file__).resolve().parent.parent
SAMPLE = ROOT / "examples" / "data" / "sample_frame.exr"


def _cli(*args, cache: Path):
    env = dict(os.environ, GODRAYS_JAX_CACHE_DIR=str(cache))
    return subprocess.run([sys.executable, "-m", "godrays_jax", *map(str, args)], capture_output=True, text=True,
                          timeout=600, env=env, cwd=ROOT)  # fmt: skip


def _programs(cache: Path, name: str) -> list[str]:
    return sorted(p.name for p in cache.glob(f"jit_{name}-*-cache")) if cache.exists() else []


def test_cache_folder_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv(compile_cache.ENVIRONMENT_VARIABLE, str(tmp_path / "mine"))
    assert compile_cache.cache_dir() == str(tmp_path / "mine")
    monkeypatch.delenv(compile_cache.ENVIRONMENT_VARIABLE)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert compile_cache.cache_dir() == str(tmp_path / "xdg" / "godrays_jax")


def test_apply_stores_its_program_and_a_second_run_reuses_it(tmp_path):
    """The effect's program is stored traced and compiled (no host callback keeps it out) and found by the next
    process, which neither traces nor compiles it."""
    cache = tmp_path / "cache"
    first = _cli("apply", SAMPLE, "--preset", "kbengine_flares", "-o", tmp_path / "a.png", cache=cache)
    assert first.returncode == 0, first.stderr
    stored = sorted(p.name for p in (cache / compile_cache.EXPORTED_FOLDER).iterdir())
    assert [name.rsplit("-", 1)[0] for name in stored] == ["frames"]
    files = sorted(p.name for p in cache.iterdir() if not p.name.endswith("-atime"))
    assert _programs(cache, "call")
    second = _cli("apply", SAMPLE, "--preset", "kbengine_flares", "-o", tmp_path / "b.png", cache=cache)
    assert second.returncode == 0, second.stderr
    assert sorted(p.name for p in cache.iterdir() if not p.name.endswith("-atime")) == files, "compiled again"
    assert sorted(p.name for p in (cache / compile_cache.EXPORTED_FOLDER).iterdir()) == stored, "traced again"
    assert (tmp_path / "a.png").read_bytes() == (tmp_path / "b.png").read_bytes()
    plain = _cli("apply", SAMPLE, "--preset", "kbengine_flares", "-o", tmp_path / "c.png", "--no-cache", cache=cache)
    assert plain.returncode == 0, plain.stderr
    assert (tmp_path / "a.png").read_bytes() == (tmp_path / "c.png").read_bytes()


def test_a_repeated_fit_reads_its_traced_programs_back(tmp_path):
    """`fit` stores its solver's programs traced (`pipeline.exported`); the next process traces and stores nothing."""
    cache = tmp_path / "cache"
    command = ["fit", SAMPLE, SAMPLE, "--preset", "xna_crepuscular", "--max-steps", "2"]
    first = _cli(*command, "-o", tmp_path / "a.json", cache=cache)
    assert first.returncode == 0, first.stderr
    stored = sorted(p.name for p in (cache / compile_cache.EXPORTED_FOLDER).iterdir())
    assert {name.rsplit("-", 1)[0] for name in stored} == {
        "fit_loss", "fit_init", "fit_step", "determination_jacobian", "render"
    }
    programs = _programs(cache, "call")
    assert len(programs) >= len(stored)
    second = _cli(*command, "-o", tmp_path / "b.json", cache=cache)
    assert second.returncode == 0, second.stderr
    assert sorted(p.name for p in (cache / compile_cache.EXPORTED_FOLDER).iterdir()) == stored
    assert _programs(cache, "call") == programs, "the second run compiled a stored program again"
    assert (tmp_path / "a.json").read_bytes() == (tmp_path / "b.json").read_bytes()
    assert second.stdout.replace("b.json", "a.json") == first.stdout


def test_no_cache_writes_nothing_and_cache_clear_empties_it(tmp_path):
    cache = tmp_path / "cache"
    done = _cli("apply", SAMPLE, "--preset", "sun_overcast", "-o", tmp_path / "a.png", "--no-cache", cache=cache)
    assert done.returncode == 0, done.stderr
    assert not cache.exists()
    assert _cli("apply", SAMPLE, "--preset", "sun_overcast", "-o", tmp_path / "a.png", cache=cache).returncode == 0
    shown = _cli("cache", cache=cache)
    assert shown.returncode == 0 and str(cache) in shown.stdout and "file(s)" in shown.stdout
    cleared = _cli("cache", "--clear", cache=cache)
    assert cleared.returncode == 0 and not cache.exists()


def test_known_counts_are_checked_on_the_host_and_traced_ones_at_run_time():
    with pytest.raises(ValueError, match=r"num_samples must lie in \[0, max_samples=4\]"):
        checked_count(5.0, 4, "num_samples", "max_samples", jnp.float32)
    rays = gr.GodRays(num_samples=3.0, max_samples=4)
    frame = gr.Buffers(color=jnp.ones((6, 8, 3)), depth=jnp.full((6, 8), jnp.inf), coverage=jnp.zeros((6, 8)))
    assert jnp.all(jnp.isfinite(rays(frame, jnp.asarray([4.0, 3.0]))))
    traced = jax.jit(lambda n: checked_count(n, 4, "num_samples", "max_samples", jnp.float32))
    with pytest.raises(Exception, match=r"num_samples must lie in \[0, max_samples=4\]"):
        jax.block_until_ready(traced(5.0))
    with ranges_guaranteed():
        assert float(jax.jit(lambda n: checked_count(n, 4, "n", "m", jnp.float32))(2.0)) == 2.0
