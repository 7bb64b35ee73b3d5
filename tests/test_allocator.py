"""`app.allocator`: the command's process keeps the memory it frees, so XLA's next call does not fault it in again."""

import os
import platform
import subprocess
import sys

import jax.monitoring
import numpy as np
import pytest

import godrays_jax as gr
import godrays_jax_script
from godrays_jax.app import allocator, cli, fit_command

# In a fresh process: allocate a block of the given MiB (256: far above glibc's mmap threshold), touch every page,
# free it, and print how many MiB the process still has resident beyond what it had before, and how many MiB of huge
# pages it held while the block was live.
_PROBE = """
import ctypes, ctypes.util, os, sys
from godrays_jax.app import allocator
assert allocator.keep_freed_memory() == (sys.argv[1] == "tuned")
libc = ctypes.CDLL(ctypes.util.find_library("c"))
libc.malloc.restype, libc.malloc.argtypes, libc.free.argtypes = ctypes.c_void_p, [ctypes.c_size_t], [ctypes.c_void_p]
def resident_mib():
    return int(open("/proc/self/statm").read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
def huge_mib():
    lines = open("/proc/self/smaps_rollup").read().splitlines()
    return sum(int(line.split()[1]) for line in lines if line.startswith("AnonHugePages:")) / 1024
before, size = resident_mib(), int(sys.argv[2]) << 20
block = libc.malloc(size)
ctypes.memset(block, 1, size)
huge = huge_mib()
libc.free(block)
print(resident_mib() - before, huge)
"""


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="the allocator is tuned through glibc's mallopt; on other C libraries (macOS, musl) "
                    "keep_freed_memory leaves it as it is and returns False")
@pytest.mark.slow
def test_freed_memory_stays_with_the_process_only_when_tuned():
    """Kept where tuned; where glibc asks for huge pages (the `godrays-jax` script's restart), only blocks below
    `MAPPED_BLOCK_BYTES`, the larger ones mapped on huge pages and handed back."""

    def kept(mode, mib=256, **env):
        environ = {name: value for name, value in os.environ.items() if name != "GLIBC_TUNABLES"}
        done = subprocess.run([sys.executable, "-c", _PROBE, mode, str(mib)], capture_output=True, text=True,
                              check=True, env={**environ, **env})  # fmt: skip
        return tuple(map(float, done.stdout.split()))

    assert kept("plain", **{allocator.OPT_OUT: "0"})[0] < 64  # glibc unmaps a large block on free: faulted in again
    assert kept("tuned")[0] > 192  # kept mapped: the next allocation of its size reuses it
    if not allocator.huge_pages_given():
        return  # Linux gives no huge pages: the tuned process keeps every block, as above
    huge_pages = {"GLIBC_TUNABLES": allocator.HUGE_PAGES_TUNABLE}
    resident, huge = kept("tuned", **huge_pages)
    assert resident < 64 and huge >= 2, (resident, huge)  # on huge pages while live, handed back on free
    assert kept("tuned", mib=16, **huge_pages)[0] > 12  # below the threshold: kept


def test_the_command_keeps_freed_memory_where_it_repeats_its_programs(monkeypatch, tmp_path):
    """`godrays-jax` tunes the allocator for the tuner and a batch or fit up to `KEPT_FIT_PIXELS` pixels, not for
    `apply` or larger frames; a call of `main` from a user's process never does. Each command here then stops at
    its own argument check, after the choice."""
    calls = []
    monkeypatch.setattr(allocator, "keep_freed_memory", lambda *, arenas: calls.append("tuned") or True)
    monkeypatch.setenv("GODRAYS_JAX_CACHE_DIR", str(tmp_path / "cache"))
    small, large = tmp_path / "small.exr", tmp_path / "large.exr"
    gr.write_image(small, np.zeros((36, 64, 3), np.float32))
    gr.write_image(large, np.zeros((520, 520, 3), np.float32))  # just above 2^18 pixels
    fit = ["fit", "TARGET", "-o", str(tmp_path / "p.json"), "--max-steps", "-1"]

    def tuned(argv, **options):
        calls.clear()
        cli.main(argv, **options)
        return calls == ["tuned"]

    assert not tuned([fit[0], str(small), *fit[1:]])  # a call of main: the user's process is left alone
    assert tuned([fit[0], str(small), *fit[1:]], keep_freed_memory=True)
    assert not tuned([fit[0], str(large), *fit[1:]], keep_freed_memory=True)
    assert not tuned([fit[0], str(small), "--frames", str(large), "T", *fit[1:]], keep_freed_memory=True)
    assert not tuned([fit[0], str(tmp_path / "missing.exr"), *fit[1:]], keep_freed_memory=True)
    assert not tuned(["batch", str(tmp_path / "none_####.exr"), "-o", str(tmp_path)], keep_freed_memory=True)
    for name, frame in (("small", small), ("large", large)):
        (tmp_path / name).mkdir()
        os.link(frame, tmp_path / name / "shot_0001.exr")
    batch = ["-o", str(tmp_path / "out"), "--coordinator", "host:1"]  # refused: it needs --distributed
    assert tuned(["batch", str(tmp_path / "small" / "shot_####.exr"), *batch], keep_freed_memory=True)
    assert not tuned(["batch", str(tmp_path / "large" / "shot_####.exr"), *batch], keep_freed_memory=True)
    assert not tuned(["apply", str(tmp_path / "missing.exr"), "-o", str(tmp_path / "out.exr")], keep_freed_memory=True)
    assert not tuned(["cache"], keep_freed_memory=True)


def test_the_command_line_entry_points_keep_freed_memory(monkeypatch):
    chosen = []
    monkeypatch.setattr(cli, "main", lambda argv=None, **options: chosen.append(options) or 0)
    assert cli.console_main() == 0
    assert chosen == [{"keep_freed_memory": True}]


def test_the_script_restarts_with_huge_pages_for_the_commands_that_repeat_their_programs():
    """`godrays_jax_script.restart_with_huge_pages`: for `fit`, `batch` and `tune` on Linux, the environment with
    glibc's huge pages added to the tunables given; not for another command, nor where they are set already or the
    allocator is to be left alone."""
    assert godrays_jax_script.HUGE_PAGES_TUNABLE == allocator.HUGE_PAGES_TUNABLE
    restart = godrays_jax_script.restart_with_huge_pages
    if sys.platform != "linux":
        assert restart(["godrays-jax", "fit"], {}) is None
        return
    huge = allocator.HUGE_PAGES_TUNABLE
    for command in ("fit", "batch", "tune"):
        assert restart(["godrays-jax", command, "x"], {"A": "1"}) == {"A": "1", "GLIBC_TUNABLES": huge}
    given = {"GLIBC_TUNABLES": "glibc.malloc.arena_max=2"}
    assert restart(["godrays-jax", "fit"], given) == {"GLIBC_TUNABLES": f"glibc.malloc.arena_max=2:{huge}"}
    assert restart(["godrays-jax", "apply", "x"], {}) is None
    assert restart(["godrays-jax"], {}) is None
    assert restart(["godrays-jax", "fit"], {"GLIBC_TUNABLES": "glibc.malloc.hugetlb=0"}) is None
    assert restart(["godrays-jax", "fit"], {allocator.OPT_OUT: "0"}) is None


@pytest.mark.skipif(sys.platform != "linux", reason="the script restarts only on Linux, where glibc's huge pages are; "
                    "elsewhere it runs the command at once (the test above checks that it asks for no restart)")
def test_the_script_restarts_once_in_the_same_process_then_runs_the_command():
    """The `godrays-jax` script's entry run as `fit --help`: the interpreter starts again once (the same process, its
    command line as it was) with the tunable set, then the command runs."""
    code = ("import os, sys, godrays_jax_script; print(os.getpid(), os.environ.get('GLIBC_TUNABLES'), flush=True); "
            "sys.argv[1:] = ['fit', '--help']; godrays_jax_script.script()")  # fmt: skip
    environ = {name: value for name, value in os.environ.items() if name not in ("GLIBC_TUNABLES", allocator.OPT_OUT)}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=environ, timeout=120)
    assert done.returncode == 0, done.stderr
    (pid, before), (restarted_pid, after), *help_text = (line.split(maxsplit=1) for line in done.stdout.splitlines())
    assert (before, restarted_pid, after) == ("None", pid, allocator.HUGE_PAGES_TUNABLE)
    help_text = [" ".join(words) for words in help_text]
    assert any("usage: godrays-jax fit" in line for line in help_text), help_text[:3]


# In a fresh process: fill the heap with small blocks (as a compiler or a program's temporaries do), keep one block
# above them so the freed ones are not the heap's top, free the rest, record a compile of the given seconds (or the
# request for a new program, "request"), and print the MiB still resident beyond what the process had before.
_COMPILE_PROBE = """
import ctypes, ctypes.util, os, sys
import jax.monitoring
from godrays_jax.app import allocator
assert allocator.hand_back_after_compiling()
libc = ctypes.CDLL(ctypes.util.find_library("c"))
libc.malloc.restype, libc.malloc.argtypes, libc.free.argtypes = ctypes.c_void_p, [ctypes.c_size_t], [ctypes.c_void_p]
def resident_mib():
    return int(open("/proc/self/statm").read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
before = resident_mib()
blocks = [libc.malloc(1024) for _ in range(200_000)]
for block in blocks:
    ctypes.memset(block, 1, 1024)
above = libc.malloc(1024)
for block in blocks:
    libc.free(block)
if sys.argv[1] == "request":
    jax.monitoring.record_event(allocator.COMPILE_REQUEST_EVENT)
else:
    jax.monitoring.record_event_duration_secs(allocator.COMPILE_EVENT, float(sys.argv[1]))
print(resident_mib() - before)
"""


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc",
                    reason="the heap is trimmed by glibc's malloc_trim; off glibc nothing is registered")  # fmt: skip
@pytest.mark.slow
def test_a_long_compile_hands_the_memory_it_freed_back():
    """What a compile of at least `TRIMMED_COMPILE_SECONDS` freed leaves the process, and what the process kept
    leaves it before a new program is compiled; after a short compile it stays."""

    def resident_after(seconds):
        done = subprocess.run([sys.executable, "-c", _COMPILE_PROBE, str(seconds)], capture_output=True, text=True,
                              check=True)  # fmt: skip
        return float(done.stdout)

    assert resident_after(0.1 * allocator.TRIMMED_COMPILE_SECONDS) > 150  # 200 MiB of small blocks, still resident
    assert resident_after(allocator.TRIMMED_COMPILE_SECONDS) < 50
    # Before a new program is compiled (or read from the cache), what the process kept is handed back as well: the
    # compiler's peak does not come on top of it.
    assert resident_after("request") < 50


def test_the_command_hands_back_what_compiling_frees(monkeypatch, tmp_path):
    """`godrays-jax` (`main(keep_freed_memory=True)`) trims after long compiles for every command; a call of `main`
    from a user's process leaves the allocator alone."""
    calls = []
    monkeypatch.setattr(allocator, "hand_back_after_compiling", lambda: calls.append("trim") or True)
    cli.main(["apply", str(tmp_path / "missing.exr"), "-o", str(tmp_path / "out.exr")])
    assert calls == []
    cli.main(["apply", str(tmp_path / "missing.exr"), "-o", str(tmp_path / "out.exr")], keep_freed_memory=True)
    assert calls == ["trim"]


def test_off_glibc_the_allocator_is_left_as_it_is(monkeypatch):
    """Where glibc's functions are missing (macOS, musl: the two tests above skip there), neither tuning nor
    trimming happens, each says so, and no compile listener is registered."""
    monkeypatch.setattr(allocator, "_glibc_function", lambda name: None)
    monkeypatch.setattr(allocator, "_trimming", [])
    registered = []
    monkeypatch.setattr(jax.monitoring, "register_event_duration_secs_listener", registered.append)
    monkeypatch.setattr(jax.monitoring, "register_event_listener", registered.append)
    assert allocator.keep_freed_memory() is False
    assert allocator.hand_back_after_compiling() is False
    assert registered == [] and allocator._trimming == []


def test_a_fit_the_cache_has_not_seen_finish_compiles_with_several_arenas(monkeypatch, tmp_path):
    """`godrays-jax fit` takes `COMPILING_ARENAS` arenas until a fit of the same frame sizes and options has
    finished with the cache (then one), and always without the cache, but one where it places its light by whole
    fits; a fit that fails is not remembered, and another frame of the same size shares what the first one
    compiled."""
    monkeypatch.setenv("GODRAYS_JAX_CACHE_DIR", str(tmp_path / "cache"))
    keep_freed_memory, chosen_arenas = allocator.keep_freed_memory, []
    monkeypatch.setattr(allocator, "keep_freed_memory", lambda *, arenas: chosen_arenas.append(arenas) or True)
    statuses = iter([1, 0, 0, 0, 0, 0, 0, 0, 0])
    monkeypatch.setattr(fit_command, "run", lambda args: next(statuses))
    frame, other, larger = tmp_path / "frame.exr", tmp_path / "other.exr", tmp_path / "larger.exr"
    for path, height in ((frame, 36), (other, 36), (larger, 72)):
        gr.write_image(path, np.zeros((height, 64, 3), np.float32))

    def chosen(*argv):
        chosen_arenas.clear()
        status = cli.main(["fit", *map(str, argv), "-o", str(tmp_path / "p.json")], keep_freed_memory=True)
        return chosen_arenas, status

    assert chosen(frame, frame) == ([allocator.COMPILING_ARENAS], 1)  # failed: nothing remembered
    assert chosen(frame, frame) == ([allocator.COMPILING_ARENAS], 0)
    assert chosen(other, frame) == ([1], 0)  # the same size and options: its programs are in the cache
    assert chosen(larger, larger) == ([allocator.COMPILING_ARENAS], 0)
    assert chosen(frame, frame, "--no-cache") == ([allocator.COMPILING_ARENAS], 0)
    assert chosen(frame, frame, "--loss", "l1") == ([allocator.COMPILING_ARENAS], 0)
    # Placing the light by whole fits calls the programs of a dozen fits: one arena even on a first run.
    assert chosen(larger, frame, "--light", "auto", "--loss", "charbonnier") == ([1], 0)
    assert chosen(larger, frame, "--light", "3,4", "--fit-light", "--loss", "charbonnier") == ([1], 0)
    assert chosen(larger, frame, "--light", "3,4", "--loss", "charbonnier") == ([allocator.COMPILING_ARENAS], 0)
    with pytest.raises(ValueError, match="arenas"):
        keep_freed_memory(arenas=0)
