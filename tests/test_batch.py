"""Tests for godrays_jax.pipeline.batch and `godrays-jax batch`: sequences, bad frames, resume, devices, I/O that keeps the input."""

import io
import json
import os
import re
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import godrays_jax as gr
from godrays_jax.pipeline import batch, sequences
from godrays_jax.app.cli import main
from godrays_jax.app.options import DEFAULT_PRESET
from godrays_jax.primitives import files
from godrays_jax.primitives.frame_files import read_frame, write_frame_like

H, W = 16, 24
ROOT = Path(__file__).resolve().parents[1]


def _frame(seed: int, h: int = H, w: int = W) -> gr.Buffers:
    rng = np.random.default_rng(seed)
    depth = rng.uniform(1.0, 20.0, (h, w)).astype(np.float32)
    depth[: h // 2, : w // 2] = np.inf  # a patch of sky for the light to shine through
    return gr.Buffers(
        color=rng.uniform(0.0, 2.0, (h, w, 3)).astype(np.float32),
        depth=depth,
        coverage=np.isfinite(depth).astype(np.float32),
    )


def _light(number: int) -> tuple[float, float]:
    return (4.5 + 0.25 * number, 3.0 - 0.5 * number)


def _sequence(folder: Path, count: int, first: int = 1, **kwargs) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for number in range(first, first + count):
        path = folder / f"shot.{number:04d}.exr"
        gr.write_buffers(
            path, _frame(number, **kwargs), light_xy=_light(number), light_in_front=number != first + 1,
            half=True, metadata={"shot:note": f"frame {number}"},
        )  # fmt: skip
        paths.append(path)
    return paths


def _visible(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if not p.name.startswith("."))


def _expected(path: Path, light=None) -> np.ndarray:
    """What the batch should write for a frame: the default preset applied directly."""
    buffers = gr.read_buffers(path)
    stored, in_front = gr.read_light(path)
    if light is not None:  # a light given on the command line is in front of the camera
        stored, in_front = light, True
    return np.asarray(_apply(gr.preset(DEFAULT_PRESET), buffers, jnp.asarray(stored, jnp.float32), jnp.asarray(in_front)))


@eqx.filter_jit
def _apply(effect, buffers, light, in_front):
    return effect(buffers, light, light_in_front=in_front)


def _assert_half_close(actual, expected):
    np.testing.assert_allclose(actual, expected, rtol=2e-3, atol=1e-6)  # outputs keep the inputs' half colour


# ------------------------------------------------------------------------------ frames and lights


def test_expand_frames_patterns(tmp_path):
    _sequence(tmp_path, 3, first=9)
    (tmp_path / "shot.10.exr").write_bytes(b"")  # two digits: not a #### frame
    expected = [str(tmp_path / f"shot.{n:04d}.exr") for n in (9, 10, 11)]
    assert sequences.expand_frames(str(tmp_path / "shot.####.exr")) == expected
    assert sequences.expand_frames(str(tmp_path / "shot.%04d.exr")) == expected
    assert sequences.expand_frames(str(tmp_path / "shot.*.exr")) == expected[:2] + [str(tmp_path / "shot.10.exr")] + expected[2:]
    assert sequences.expand_frames(expected[1]) == [expected[1]]
    with pytest.raises(ValueError, match="no frames match"):
        sequences.expand_frames(str(tmp_path / "other.####.exr"))
    assert sequences.frame_number("a/b7/shot.v2.0042.exr") == 42 and sequences.frame_number("plate.exr") is None


def test_light_tracks(tmp_path):
    csv_path = tmp_path / "track.csv"
    csv_path.write_text("frame,x,y,in_front\n1,10.5,20,1\n2, 11.5 ,21,false\n# comment\n\n3,-1e4,5\n")
    assert sequences.read_light_track(csv_path) == {1: ((10.5, 20.0), True), 2: ((11.5, 21.0), False), 3: ((-1e4, 5.0), True)}
    json_path = tmp_path / "track.json"
    json_path.write_text(json.dumps({"1": [1, 2], "2": {"x": 3, "y": 4, "in_front": False}}))
    assert sequences.read_light_track(json_path) == {1: ((1.0, 2.0), True), 2: ((3.0, 4.0), False)}
    json_path.write_text(json.dumps([{"frame": 5, "x": 1.5, "y": 2.5}]))
    assert sequences.read_light_track(json_path) == {5: ((1.5, 2.5), True)}
    for text, message in [("1,2\n", "frame, x, y"), ("1,nan,2\n", "non-finite"), ("a,1,2\n", "integer frame"),
                          ("1,1,2,maybe\n", "in_front"), ("frame,x,y\n", "no frames")]:  # fmt: skip
        csv_path.write_text(text)
        with pytest.raises(ValueError, match=message):
            sequences.read_light_track(csv_path)
    json_path.write_text("{")
    with pytest.raises(ValueError, match="not valid JSON"):
        sequences.read_light_track(json_path)


def test_light_for_each_source(tmp_path):
    (path,) = _sequence(tmp_path, 1, first=7)
    assert sequences.light_for(str(path), (1, 2)) == ((1.0, 2.0), True)
    assert sequences.light_for(str(path), ((1, 2), False)) == ((1.0, 2.0), False)  # `--light 1,2,behind`
    assert sequences.light_for(str(path), sequences.METADATA) == (_light(7), True)
    assert sequences.light_for(str(path), {7: ((3.0, 4.0), False)}) == ((3.0, 4.0), False)
    with pytest.raises(ValueError, match=r"frame 7 is outside the light track \(frames 8-9\)"):
        sequences.light_for(str(path), {8: ((3.0, 4.0), False), 9: ((3.0, 4.0), False)})
    bare = tmp_path / "bare.exr"
    gr.write_buffers(bare, _frame(0))
    with pytest.raises(ValueError, match="no light position"):
        sequences.light_for(str(bare), sequences.METADATA)


def test_sparse_light_track_interpolates_between_keys():
    track = {1: ((10.0, 20.0), True), 5: ((30.0, 0.0), True), 7: ((0.0, 0.0), False), 10: ((6.0, 3.0), False)}

    def at(number):
        return sequences.light_for(f"shot.{number:04d}.exr", track)

    assert at(1) == ((10.0, 20.0), True)
    assert at(2) == ((15.0, 15.0), True)
    assert at(4) == ((25.0, 5.0), True)
    # Across the change of side the nearer key is held (the earlier on a tie).
    assert at(6) == ((30.0, 0.0), True)
    assert at(8) == ((2.0, 1.0), False)
    for outside in (0, 11):
        with pytest.raises(ValueError, match=r"outside the light track \(frames 1-10\)"):
            at(outside)


# ------------------------------------------------------------------------------ io: writing like the input


def test_write_frame_like_keeps_channels_formats_and_metadata(tmp_path):
    source = tmp_path / "in.exr"
    frame = _frame(3)
    frame = gr.Buffers(color=frame.color, depth=frame.depth, coverage=frame.coverage,
                       light_pass=np.full((H, W), 0.5, np.float32))  # fmt: skip
    gr.write_buffers(source, frame, light_xy=(1.5, 2.5), half=True, metadata={"shot:note": "keep me"})
    buffers, stored = read_frame(source)
    np.testing.assert_array_equal(buffers.color, gr.read_buffers(source).color)
    new_color = np.asarray(buffers.color) * 3.0 + 0.25
    write_frame_like(tmp_path / "out.exr", new_color, stored)
    back, written = read_frame(tmp_path / "out.exr")
    assert written.spec.channelnames == stored.spec.channelnames
    assert [str(t) for t in written.spec.channelformats] == [str(t) for t in stored.spec.channelformats]
    assert written.spec.getattribute("shot:note") == "keep me"
    assert written.spec.getattribute("compression") == "zip"
    assert gr.read_light(tmp_path / "out.exr") == ((1.5, 2.5), True)
    _assert_half_close(back.color, new_color)
    np.testing.assert_array_equal(back.depth, buffers.depth)
    np.testing.assert_array_equal(back.light_pass, buffers.light_pass)
    with pytest.raises(ValueError, match="keeps the input's format"):
        write_frame_like(tmp_path / "out.png", new_color, stored)
    with pytest.raises(ValueError, match="color must have shape"):
        write_frame_like(tmp_path / "out2.exr", new_color[:-1], stored)
    assert _visible(tmp_path) == ["in.exr", "out.exr"]


# ------------------------------------------------------------------------------ the run


def test_batch_matches_the_effect_and_compiles_once(tmp_path, capsys):
    inputs = _sequence(tmp_path / "in", 5)
    status = main([
        "batch", str(tmp_path / "in" / "shot.####.exr"), "-o", str(tmp_path / "out"), "--light-from-metadata",
    ])  # fmt: skip
    assert status == 0
    assert "5 written, 0 skipped (already done), 0 failed" in capsys.readouterr().out
    assert _visible(tmp_path / "out") == [p.name for p in inputs]
    for path in inputs:
        out, stored = read_frame(tmp_path / "out" / path.name)
        _assert_half_close(out.color, _expected(path))
        assert stored.spec.getattribute("shot:note") == f"frame {sequences.frame_number(str(path))}"
    # frame 2 has its light behind the camera: no rays, the frame comes back unchanged
    np.testing.assert_array_equal(read_frame(tmp_path / "out" / inputs[1].name)[0].color, gr.read_buffers(inputs[1]).color)

    jobs = batch.plan_batch([str(p) for p in inputs], str(tmp_path / "again"))
    report = batch.run_batch(jobs, gr.GodRays(num_samples=4.0, max_samples=4), (3.5, 2.5), progress=None)
    assert report.compilations == 1 and report.devices == 1 and len(report.written) == 5


def test_bad_frames_are_reported_and_skipped(tmp_path, capsys):
    inputs = _sequence(tmp_path / "in", 8)
    corrupt, no_depth, wrong_size, nan_colour = inputs[2], inputs[4], inputs[5], inputs[6]
    corrupt.write_bytes(corrupt.read_bytes()[:300])  # a truncated file
    gr.write_image(no_depth, np.ones((H, W, 3), np.float32))
    gr.write_buffers(wrong_size, _frame(5, h=H + 2), light_xy=(1.0, 1.0))
    bad = _frame(6)
    bad.color[3, 4, 1] = np.nan
    gr.write_buffers(nan_colour, bad, light_xy=(1.0, 1.0))

    status = main(["batch", str(tmp_path / "in" / "shot.*.exr"), "-o", str(tmp_path / "out"), "-q"])
    assert status == 1
    err = capsys.readouterr().err
    assert "4 written, 0 skipped (already done), 4 failed" in err
    lines = {line.split(": ", 1)[1].split(":")[0]: line for line in err.splitlines() if "failed: " in line}
    assert set(lines) == {str(corrupt), str(no_depth), str(wrong_size), str(nan_colour)}
    assert "no light position" in lines[str(no_depth)]  # read as a frame without depth, it has no light either
    assert "wrong size 24x18 (the run's frames are 24x16)" in lines[str(wrong_size)]
    assert "NaN" in lines[str(nan_colour)]
    good = [p for p in inputs if p not in (corrupt, no_depth, wrong_size, nan_colour)]
    assert sorted(os.listdir(tmp_path / "out")) == [p.name for p in good]  # no partial or hidden temporary files
    for path in good:
        _assert_half_close(gr.read_buffers(tmp_path / "out" / path.name).color, _expected(path))


def test_light_track_fixed_light_and_other_format(tmp_path):
    inputs = _sequence(tmp_path / "in", 3)
    track = tmp_path / "track.csv"
    track.write_text("frame,x,y\n1,2.5,3.5\n2,30.5,-4\n")  # frame 3 is missing from the track
    status = main(["batch", str(tmp_path / "in" / "shot.####.exr"), "-o", str(tmp_path / "t"),
                   "--light-track", str(track), "-q"])  # fmt: skip
    assert status == 1 and _visible(tmp_path / "t") == [inputs[0].name, inputs[1].name]
    for path, light in zip(inputs, [(2.5, 3.5), (30.5, -4.0)]):
        _assert_half_close(gr.read_buffers(tmp_path / "t" / path.name).color, _expected(path, light))

    assert main(["batch", str(inputs[0]), "-o", str(tmp_path / "p"), "--light", "5,6", "--ext", "png", "-q"]) == 0
    png = gr.read_image(tmp_path / "p" / "shot.0001.png")
    np.testing.assert_allclose(png, np.clip(_expected(inputs[0], (5.0, 6.0)), 0.0, 1.0), atol=0.01)  # 8-bit sRGB


def test_safety_checks_and_dry_run(tmp_path, capsys):
    inputs = _sequence(tmp_path / "in", 4)
    pattern = str(tmp_path / "in" / "shot.####.exr")
    assert main(["batch", pattern, "-o", str(tmp_path / "in"), "-q"]) == 1
    assert "refusing to overwrite the input" in capsys.readouterr().err
    assert main(["batch", pattern, "-o", str(tmp_path / "out"), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert not (tmp_path / "out").exists()
    assert f"run  {inputs[1]} -> {tmp_path / 'out' / inputs[1].name}  light (5, 2) behind the camera" in out
    assert "4 frame(s) to run, 0 done" in out

    assert main(["batch", pattern, "-o", str(tmp_path / "out"), "--frames", "2-3", "-q"]) == 0
    assert _visible(tmp_path / "out") == [inputs[1].name, inputs[2].name]
    assert main(["batch", pattern, "-o", str(tmp_path / "out"), "-q"]) == 1
    assert "2 output(s) exist already" in capsys.readouterr().err
    assert main(["batch", pattern, "-o", str(tmp_path / "out"), "--resume", "--dry-run"]) == 0
    assert f"skip {inputs[1]} (done" in capsys.readouterr().out
    before = (tmp_path / "out" / inputs[1].name).stat().st_mtime_ns
    assert main(["batch", pattern, "-o", str(tmp_path / "out"), "--resume", "-q"]) == 0
    assert "2 written, 2 skipped" in capsys.readouterr().out
    assert (tmp_path / "out" / inputs[1].name).stat().st_mtime_ns == before
    assert main(["batch", pattern, "-o", str(tmp_path / "out"), "--overwrite", "-q"]) == 0
    assert "4 written, 0 skipped" in capsys.readouterr().out

    for argv, message in [
        (["--frames", "9-1"], "comes before"),
        (["--shard", "2/2"], "0 <= INDEX < COUNT"),
        (["--shard", "x"], "INDEX/COUNT"),
        (["--preset", "xna_crepuscular", "--params", "p.json"], "not allowed with"),
    ]:
        code = _exit_code(["batch", pattern, "-o", str(tmp_path / "o2"), *argv])
        assert code != 0 and message in capsys.readouterr().err


def _exit_code(argv):
    try:
        return main(argv)
    except SystemExit as exit_:  # argparse usage errors
        return exit_.code


def test_plan_shards_split_the_frames(tmp_path):
    inputs = [str(p) for p in _sequence(tmp_path / "in", 5)]
    shares = [batch.plan_batch(inputs, str(tmp_path / "o"), shard=(i, 2)) for i in range(2)]
    assert [job.input for share in shares for job in share] == inputs
    assert [len(share) for share in shares] == [3, 2]
    with pytest.raises(batch.BatchError, match="would both be written"):
        batch.plan_batch([inputs[0], inputs[0]], str(tmp_path / "o"))


def test_progress_bar_counts_frames_with_a_rate_and_an_eta(tmp_path):
    inputs = _sequence(tmp_path / "in", 3)
    jobs = batch.plan_batch([str(p) for p in inputs], str(tmp_path / "out"))
    stream = io.StringIO()
    report = batch.run_batch(jobs, gr.GodRays(num_samples=4.0, max_samples=4), (3.5, 2.5), progress=stream)
    assert len(report.written) == 3
    last = stream.getvalue().replace("\r", "\n").strip().splitlines()[-1]
    assert re.search(r"3/3 \[[0-9:]+<[0-9:]+, +[0-9.]+ ?(frame/s|s/frame)\]", last), last

def _cli(*args: str, env: dict | None = None) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "godrays_jax", "batch", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, text=True)  # fmt: skip


_KILLED_AFTER_THREE_FRAMES = """
import os, signal, sys, threading
from godrays_jax.app.cli import main
from godrays_jax.pipeline import batch
from godrays_jax.primitives.files import temporary_path

write, lock, finished = batch.write_frame_like, threading.Lock(), []


def write_then_die(path, *args, **kwargs):
    # A hook at a known point: one write at a time; the fourth dies half written, as a kill mid-write leaves it.
    with lock:
        if len(finished) == 3:
            with open(temporary_path(path), "wb") as partial:
                partial.write(b"half a frame")
            os.kill(os.getpid(), signal.SIGKILL)
        write(path, *args, **kwargs)
        finished.append(path)


batch.write_frame_like = write_then_die
sys.exit(main(sys.argv[1:]))
"""


@pytest.mark.slow
def test_killed_run_resumes_to_the_same_files(tmp_path):
    count = 6  # three written, the fourth killed mid-write by the hook, two left
    inputs = _sequence(tmp_path / "in", count)
    pattern = str(tmp_path / "in" / "shot.####.exr")
    killed_dir, reference_dir = tmp_path / "killed", tmp_path / "reference"

    process = subprocess.Popen([sys.executable, "-c", _KILLED_AFTER_THREE_FRAMES, "batch", pattern, "-o", str(killed_dir)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip
    process.communicate(timeout=600)
    assert process.returncode == -signal.SIGKILL
    written = _visible(killed_dir)
    assert len(written) == 3, "the kill lands mid-run, after three whole frames"
    assert len([name for name in os.listdir(killed_dir) if ".tmp-" in name]) == 1, "and a fourth half written"

    assert main(["batch", pattern, "-o", str(reference_dir), "-q"]) == 0
    for name in written:  # what the killed run left visible is complete
        assert (killed_dir / name).read_bytes() == (reference_dir / name).read_bytes()
    resumed = _cli(pattern, "-o", str(killed_dir), "--resume")
    out, err = resumed.communicate(timeout=600)
    assert resumed.returncode == 0, err
    assert f"{count - len(written)} written, {len(written)} skipped" in out
    assert sorted(os.listdir(killed_dir)) == [p.name for p in inputs]  # stale temporaries removed too
    for path in inputs:
        assert (killed_dir / path.name).read_bytes() == (reference_dir / path.name).read_bytes()


def test_frames_spread_over_two_devices(tmp_path):
    inputs = _sequence(tmp_path / "in", 5)
    pattern = str(tmp_path / "in" / "shot.####.exr")
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2", JAX_PLATFORMS="cpu")
    script = (
        "import json, sys, godrays_jax as gr; from godrays_jax.pipeline import batch, sequences\n"
        f"jobs = batch.plan_batch(sequences.expand_frames({pattern!r}), {str(tmp_path / 'two')!r})\n"
        "report = batch.run_batch(jobs, gr.preset('xna_crepuscular'), sequences.METADATA, progress=None)\n"
        "print(json.dumps(dict(devices=report.devices, compilations=report.compilations, written=len(report.written))))\n"
    )
    done = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout.splitlines()[-1]) == {"devices": 2, "compilations": 1, "written": 5}
    assert main(["batch", pattern, "-o", str(tmp_path / "one"), "-q"]) == 0
    for path in inputs:
        np.testing.assert_array_equal(
            gr.read_buffers(tmp_path / "two" / path.name).color, gr.read_buffers(tmp_path / "one" / path.name).color
        )


def test_distributed_options_are_checked(tmp_path, capsys):
    """Two processes through jax.distributed sharing a shot: tests/test_distributed.py."""
    _sequence(tmp_path / "in", 1)
    pattern = str(tmp_path / "in" / "shot.####.exr")
    capsys.readouterr()
    for extra, message in [(["--process-id", "0"], "need --distributed"),
                           (["--distributed", "--coordinator", "127.0.0.1:1"], "give all of"),
                           (["--distributed", "--shard", "0/2"], "not both"),
                           (["--distributed", "--coordinator", "127.0.0.1:1", "--num-processes", "2",
                             "--process-id", "2"], r"--process-id must be in 0\.\.1")]:  # fmt: skip
        assert main(["batch", pattern, "-o", str(tmp_path / "bad"), *extra]) != 0
        assert re.search(message, capsys.readouterr().err)


# ----------------------------------------------------------------------------- overlapping runs


def _hold(script: str) -> subprocess.Popen:
    """A Python process that runs `script`, prints "ready" and then waits to be killed."""
    # It waits on its standard input, which nothing writes to, until it is killed.
    process = subprocess.Popen([sys.executable, "-c", script + "\nprint('ready', flush=True)\nimport sys\nsys.stdin.read()"],
                               stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=ROOT)  # fmt: skip
    assert process.stdout.readline().strip() == "ready"
    return process


def test_a_claim_is_exclusive_between_processes_and_dropped_when_its_process_dies(tmp_path):
    output = tmp_path / "frame.exr"
    holder = _hold(f"from godrays_jax.primitives.files import claim\nheld = claim({str(output)!r})\nassert held")
    try:
        assert files.claim(output) is None
    finally:
        holder.kill()
        holder.wait()
    held = files.claim(output)
    assert held is not None and files.claim(output) is None  # also exclusive within one process
    files.release(held)
    again = files.claim(output)  # released for good: this process (or any other) takes it again
    assert again is not None
    files.release(again)
    assert os.listdir(tmp_path) == []  # the lock file goes with the claim


def test_stale_temporaries_are_those_of_dead_or_ancient_runs_and_are_cleaned_beside_done_frames(tmp_path):
    done, todo = tmp_path / "shot.0001.exr", tmp_path / "shot.0002.exr"
    done.write_bytes(b"finished frame")
    live = _hold("import os")
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    try:
        host = files.temporary_path(done).split(".tmp-")[1].split("-")[0]
        mine = files.temporary_path(todo)
        of_live = tmp_path / f".shot.0002.tmp-{host}-{live.pid}-0123abcd.exr"
        of_dead = tmp_path / f".shot.0002.tmp-{host}-{int(dead.stdout)}-0123abcd.exr"
        beside_done = tmp_path / f".shot.0001.tmp-{host}-{int(dead.stdout)}-4567cdef.exr"
        old_style = tmp_path / ".shot.0002.tmp-89abcdef.exr"  # as earlier versions named them: only age tells
        other_host = tmp_path / f".shot.0002.tmp-elsewhere-{live.pid}-0123abcd.exr"
        for path in (mine, of_live, of_dead, beside_done, old_style, other_host):
            Path(path).write_bytes(b"partial")
        assert not files.is_stale(old_style) and not files.is_stale(other_host)
        ancient = time.time() - files.STALE_AGE_S - 60
        os.utime(old_style, (ancient, ancient))
        jobs = [batch.Job(str(done), str(done), done=True), batch.Job(str(todo), str(todo), done=False)]
        removed = batch.remove_stale_temporaries(jobs)
    finally:
        live.kill()
        live.wait()
    assert sorted(removed) == sorted(map(str, (of_dead, beside_done, old_style)))
    assert sorted(os.listdir(tmp_path)) == sorted(
        p.name for p in map(Path, (done, mine, of_live, other_host))
    )  # a live run's temporaries (this one's and another process's) are kept


def test_a_write_that_must_not_replace_fails_if_the_output_appears_meanwhile(tmp_path):
    output = tmp_path / "frame.exr"
    with pytest.raises(FileExistsError, match="exists already"):
        with files.atomic_write(output, replace=False) as temporary:
            Path(temporary).write_bytes(b"mine")
            output.write_bytes(b"another run's")  # e.g. a second run that started at the same moment
    assert output.read_bytes() == b"another run's" and os.listdir(tmp_path) == ["frame.exr"]
    with files.atomic_write(tmp_path / "new.exr", replace=False) as temporary:
        Path(temporary).write_bytes(b"mine")
    assert (tmp_path / "new.exr").read_bytes() == b"mine"


def test_written_files_get_the_users_normal_permissions(tmp_path):
    previous = os.umask(0o027)
    try:
        gr.save_effect(tmp_path / "params.json", gr.GodRays())
        gr.write_image(tmp_path / "frame.exr", np.zeros((2, 2, 3), np.float32))
    finally:
        os.umask(previous)
    for name in ("params.json", "frame.exr"):
        assert stat.S_IMODE(os.stat(tmp_path / name).st_mode) == 0o640


@pytest.mark.slow
def test_two_runs_on_one_folder_share_the_frames_and_replace_nothing(tmp_path):
    """Two processes started together on one output folder: each frame written once, by one of them, complete."""
    count = 12
    inputs = _sequence(tmp_path / "in", count, h=40, w=56)
    heavy = tmp_path / "heavy.json"  # slow enough per frame that the two runs overlap
    gr.save_effect(heavy, gr.GodRays(num_samples=512.0, max_samples=512))
    pattern = str(tmp_path / "in" / "shot.####.exr")
    out, reference = tmp_path / "out", tmp_path / "reference"
    runs = [_cli(pattern, "-o", str(out), "--params", str(heavy), "--resume") for _ in range(2)]
    answers = [run.communicate(timeout=600) for run in runs]
    assert [run.returncode for run in runs] == [0, 0], answers
    counts = [re.search(r"(\d+) written, (\d+) skipped", text).groups() for text, _ in answers]
    left = [int(m.group(1)) if (m := re.search(r"(\d+) left to another run", text)) else 0 for text, _ in answers]
    assert sum(int(written) for written, _ in counts) == count, answers  # every frame written exactly once
    for (written, skipped), others in zip(counts, left):  # each run accounts for every frame
        assert int(written) + int(skipped) + others == count, answers
    assert sorted(os.listdir(out)) == [p.name for p in inputs]  # no temporaries, no lock files left
    assert main(["batch", pattern, "-o", str(reference), "--params", str(heavy), "-q"]) == 0
    for path in inputs:
        assert (out / path.name).read_bytes() == (reference / path.name).read_bytes()
    # A third run without --resume or --overwrite refuses with a clear message, and replaces nothing.
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    third = _cli(pattern, "-o", str(out), "--params", str(heavy))
    _, err = third.communicate(timeout=600)
    assert third.returncode == 1 and "exist already" in err and "--resume" in err
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before


@pytest.mark.parametrize("ext", ["/../../x.png", "../x.png", "a/b.png", "png/", ".", "..", ".p ng", ""])
def test_ext_takes_an_extension_only_and_outputs_never_leave_the_output_folder(ext, tmp_path, capsys):
    _sequence(tmp_path / "in", 1)
    (tmp_path / "deep" / "er").mkdir(parents=True)
    out = tmp_path / "deep" / "er" / "out"
    code = _exit_code(["batch", str(tmp_path / "in" / "shot.####.exr"), "-o", str(out), f"--ext={ext}", "-q"])
    err = capsys.readouterr().err
    assert code == 1 and err.count("\n") == 1 and "--ext" in err, err
    assert sorted(p.name for p in tmp_path.rglob("*") if p.is_file()) == ["shot.0001.exr"]
    with pytest.raises(batch.BatchError, match="extension"):
        batch.output_path("shot.0001.exr", str(out), ext)


@pytest.mark.parametrize("ext", ["png", ".png", "TIF", "exr"])
def test_ext_with_or_without_its_dot(ext, tmp_path):
    assert batch.output_path("in/shot.0001.exr", str(tmp_path), ext) == str(tmp_path / f"shot.0001.{ext.lstrip('.')}")


def test_an_output_folder_through_a_missing_folder_is_refused_before_any_work(tmp_path, capsys, monkeypatch):
    _sequence(tmp_path / "in", 2)
    monkeypatch.chdir(tmp_path)
    code = main(["batch", "in/shot.####.exr", "-o", "nonexist/../out", "-q"])
    err = capsys.readouterr().err
    assert code == 1 and err.count("\n") == 1 and "nonexist" in err and "does not exist" in err, err
    assert sorted(os.listdir(tmp_path)) == ["in"]
    (tmp_path / "a_file").write_text("mine")
    assert main(["batch", "in/shot.####.exr", "-o", "a_file", "-q"]) == 1
    assert "not a folder" in capsys.readouterr().err
    assert main(["batch", "in/shot.####.exr", "-o", "new/nested/out", "-q"]) == 0  # missing folders are created
    assert _visible(tmp_path / "new" / "nested" / "out") == ["shot.0001.exr", "shot.0002.exr"]
