"""The command line's persistent compilation cache: where it lives, what it stores, `--no-cache`, `cache --clear`."""

import os
import subprocess
import sys
import threading
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import godrays_jax as gr
from godrays_jax.app import compile_cache
from godrays_jax.app.cli import main
from godrays_jax.pipeline import exported
from godrays_jax.primitives.checks import checked_count, ranges_are_guaranteed, ranges_guaranteed

ROOT = Path(__file__).resolve().parent.parent
SAMPLE = ROOT / "examples" / "data" / "sample_frame.exr"
CONFTEST_CACHE = jax.config.jax_compilation_cache_dir


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


@pytest.mark.slow
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


def _sample_at_a_quarter(path: Path) -> Path:
    """The shipped sample frame, every fourth pixel of every fourth row, with its light: a frame that a fit's steps
    run through in a fraction of a second at the suite's optimisation level."""
    frame = gr.read_buffers(SAMPLE)
    (x, y), in_front = gr.read_light(SAMPLE)
    small = gr.Buffers(color=frame.color[::4, ::4], depth=frame.depth[::4, ::4], coverage=frame.coverage[::4, ::4])
    gr.write_buffers(path, small, light_xy=(x / 4, y / 4), light_in_front=in_front)
    return path


@pytest.mark.slow
def test_a_repeated_fit_reads_its_traced_programs_back(tmp_path):
    """`fit` stores its solver's programs traced (`pipeline.exported`); the next process traces and stores nothing."""
    cache = tmp_path / "cache"
    frame = _sample_at_a_quarter(tmp_path / "frame.exr")
    command = ["fit", frame, frame, "--preset", "xna_crepuscular", "--max-steps", "2"]
    first = _cli(*command, "-o", tmp_path / "a.json", cache=cache)
    assert first.returncode == 0, first.stderr
    stored = sorted(p.name for p in (cache / compile_cache.EXPORTED_FOLDER).iterdir())
    assert {name.rsplit("-", 1)[0] for name in stored} == {"fit_jacobian", "fit_image_loss", "render"}
    programs = _programs(cache, "call")
    assert len(programs) >= len(stored)
    second = _cli(*command, "-o", tmp_path / "b.json", cache=cache)
    assert second.returncode == 0, second.stderr
    assert sorted(p.name for p in (cache / compile_cache.EXPORTED_FOLDER).iterdir()) == stored
    assert _programs(cache, "call") == programs, "the second run compiled a stored program again"
    assert len(list((cache / compile_cache.FITS_FOLDER).iterdir())) == 1  # the fit remembered once, by what it compiles
    assert (tmp_path / "a.json").read_bytes() == (tmp_path / "b.json").read_bytes()
    assert second.stdout.replace("b.json", "a.json") == first.stdout


@pytest.mark.slow
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


JAX_ENTRY = "jit_call-" + "0" * 64


def _filled(cache: Path) -> list[Path]:
    """A cache folder with entries of JAX, of `pipeline.exported` and a fit remembered; returns them."""
    (cache / compile_cache.EXPORTED_FOLDER).mkdir(parents=True)
    (cache / compile_cache.FITS_FOLDER).mkdir()
    entries = [cache / f"{JAX_ENTRY}-cache", cache / f"{JAX_ENTRY}-atime", cache / ".lockfile",
               cache / compile_cache.EXPORTED_FOLDER / "frames-abc.jaxexport"]  # fmt: skip
    for entry in entries:
        entry.write_bytes(b"x")
    compile_cache.remember_fit("a fit", str(cache))
    return [*entries, *(cache / compile_cache.FITS_FOLDER).iterdir()]


def test_clear_removes_only_what_the_library_wrote(tmp_path, capsys, monkeypatch):
    """Pointed at a folder that holds other things, `cache --clear` removes its entries and nothing else."""
    cache = tmp_path / "project"
    entries = _filled(cache)
    kept = [cache / "notes.txt", cache / "scene-cache", cache / "shots" / f"{JAX_ENTRY}-cache",
            cache / compile_cache.EXPORTED_FOLDER / "readme.txt"]  # fmt: skip
    for path in kept:
        path.parent.mkdir(exist_ok=True)
        path.write_text("mine")
    outside = tmp_path / "precious.txt"
    outside.write_text("mine")
    linked = cache / f"{'jit_f-' + '1' * 64}-cache"
    linked.symlink_to(outside)
    monkeypatch.setenv(compile_cache.ENVIRONMENT_VARIABLE, str(cache))
    assert main(["cache", "--clear"]) == 0
    out = capsys.readouterr().out
    assert out.count("\n") == 1 and "kept" in out and "6 cached program file(s)" in out, out
    assert not any(os.path.lexists(p) for p in [*entries, linked])
    assert all(p.read_text() == "mine" for p in [*kept, outside])
    assert compile_cache.cache_size(str(cache)) == (0, 0)
    (cache / compile_cache.EXPORTED_FOLDER / "readme.txt").unlink()
    (cache / compile_cache.EXPORTED_FOLDER).rmdir()
    (cache / compile_cache.EXPORTED_FOLDER).symlink_to(tmp_path / "elsewhere")
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "elsewhere" / "report.jaxexport").write_text("mine")
    compile_cache.clear(str(cache))  # a link where the programs' folder should be is not followed
    assert (tmp_path / "elsewhere" / "report.jaxexport").read_text() == "mine"


def test_clear_through_a_linked_folder_clears_its_target_and_keeps_the_link(tmp_path):
    target = tmp_path / "target"
    entries = _filled(target)
    cache = tmp_path / "cache"
    cache.symlink_to(target)
    assert compile_cache.cache_size(str(cache))[0] == len(entries)
    assert compile_cache.clear(str(cache)) == (len(entries), False)
    assert not any(os.path.lexists(p) for p in entries) and cache.is_symlink() and target.is_dir()


def _small_frame(path: Path) -> Path:
    depth = np.full((4, 6), np.inf, np.float32)
    depth[3:] = 3.0
    frame = gr.Buffers(color=np.full((4, 6, 3), 0.2, np.float32), depth=depth, coverage=np.isfinite(depth) * 1.0)
    gr.write_buffers(path, frame, light_xy=(3.0, 2.0))
    return path


def _apply_warns_and_runs(cache: Path, tmp_path: Path, capsys, monkeypatch, reason: str):
    """`apply` with the cache at `cache`: one warning line naming `reason`, exit 0, and nothing stored there."""
    monkeypatch.setenv(compile_cache.ENVIRONMENT_VARIABLE, str(cache))
    frame = _small_frame(tmp_path / "frame.exr")
    before = jax.config.jax_compilation_cache_dir
    assert main(["apply", str(frame), "--preset", "kbengine_flares", "-o", str(tmp_path / "out.png")]) == 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "warning" in err and reason in err and "without a cache" in err, err
    assert jax.config.jax_compilation_cache_dir == before
    assert (tmp_path / "out.png").exists()


def test_a_folder_other_users_can_write_is_not_used(tmp_path, capsys, monkeypatch):
    shared = tmp_path / "shared"
    shared.mkdir()
    os.chmod(shared, 0o777)
    _apply_warns_and_runs(shared, tmp_path, capsys, monkeypatch, "other users can write to it")
    assert not list(shared.iterdir())
    with pytest.raises(compile_cache.CacheUnavailable, match="mode 777"):
        compile_cache.enable(str(shared))


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() != 0, reason="giving a folder away takes root")
def test_a_folder_of_another_user_is_not_used(tmp_path, capsys, monkeypatch):
    theirs = tmp_path / "theirs"
    theirs.mkdir(mode=0o700)
    os.chown(theirs, 65534, 65534)
    _apply_warns_and_runs(theirs, tmp_path, capsys, monkeypatch, "belongs to another user")


def test_the_folder_is_created_private(tmp_path):
    old = os.umask(0o002)  # a umask that lets the group write
    try:
        compile_cache.enable(str(tmp_path / "new" / "cache"))
    finally:
        os.umask(old)
        exported.use_directory(None)
        jax.config.update("jax_compilation_cache_dir", CONFTEST_CACHE)
    for folder in (tmp_path / "new" / "cache", tmp_path / "new" / "cache" / compile_cache.EXPORTED_FOLDER):
        assert folder.stat().st_mode & 0o777 == 0o700


@pytest.mark.parametrize("where", ["a file", "under a file"])
def test_a_path_that_cannot_be_a_folder_means_no_cache(where, tmp_path, capsys, monkeypatch):
    (tmp_path / "file").write_text("mine")
    cache = tmp_path / "file" if where == "a file" else tmp_path / "file" / "cache"
    _apply_warns_and_runs(cache, tmp_path, capsys, monkeypatch, "not used")
    assert (tmp_path / "file").read_text() == "mine"


def test_a_read_only_parent_means_no_cache(tmp_path, capsys, monkeypatch):
    """Root writes anywhere, so the refusal of a read-only parent is what `os.makedirs` is made to raise."""
    parent = tmp_path / "read_only"
    parent.mkdir()
    makedirs = os.makedirs

    def refused(path, *args, **kwargs):
        if str(path).startswith(str(parent)):
            raise PermissionError(13, "Permission denied", str(path))
        return makedirs(path, *args, **kwargs)

    monkeypatch.setattr(os, "makedirs", refused)
    _apply_warns_and_runs(parent / "cache", tmp_path, capsys, monkeypatch, "Permission denied")


def test_a_function_carried_to_another_thread_runs_in_the_settings_that_change_a_trace():
    """JAX keeps its settings per thread: `exported.carried` takes this thread's into another (else a stored
    program's key, and the program, would be another settings')."""

    def seen():
        return exported._settings(), ranges_are_guaranteed()

    def on_a_thread(function):
        found = []
        thread = threading.Thread(target=lambda: found.append(function()))
        thread.start()
        thread.join()
        return found[0]

    with jax.default_matmul_precision("highest"), jax.numpy_rank_promotion("raise"), jax.enable_x64(True), \
            ranges_guaranteed():  # fmt: skip
        here = seen()
        carried = exported.carried(seen)
        assert on_a_thread(seen) != here  # the thread's own: JAX's defaults
    assert here[1] and "highest" in here[0] and "raise" in here[0] and "x64=True" in here[0]
    assert on_a_thread(carried) == here and on_a_thread(carried) == here  # and again, from a fresh copy
