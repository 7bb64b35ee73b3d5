"""`cli.script`, the `godrays-jax` command's entry: its status, its output and the exit handlers kept, the
interpreter's teardown skipped, and a thread that is not a daemon still waited for."""

import subprocess
import sys
import textwrap

# A process that runs the command as the script does, with a global whose teardown would print and an exit
# handler registered before the command.
_SCRIPT = r"""
import atexit, os, sys, threading, time
class TornDown:
    def __del__(self, write=os.write):
        write(1, b"torn down\n")
kept = TornDown()
atexit.register(print, "exit handler ran")
from godrays_jax.app import cli
if sys.argv[1] == "thread":  # the command leaves a thread running
    run_cache = cli.run_cache
    def run_cache_leaving_a_thread(args):
        threading.Thread(target=lambda: (time.sleep(0.3), print("thread finished", flush=True))).start()
        return run_cache(args)
    cli.run_cache = run_cache_leaving_a_thread
sys.argv = ["godrays-jax", *sys.argv[2:]]
cli.script()
"""


def _run(*args, tmp_path):
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(_SCRIPT), *args], capture_output=True, text=True, timeout=300,
        env={"GODRAYS_JAX_CACHE_DIR": str(tmp_path / "cache"), "PATH": "/usr/bin:/bin"},
    )  # fmt: skip


def test_the_script_keeps_the_status_the_output_and_the_exit_handlers_but_not_the_teardown(tmp_path):
    done = _run("-", "cache", tmp_path=tmp_path)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0].startswith(str(tmp_path / "cache")) and lines[1:] == ["exit handler ran"]

    failed = _run("-", "apply", str(tmp_path / "missing.exr"), "-o", str(tmp_path / "out.exr"), tmp_path=tmp_path)
    assert failed.returncode == 1
    assert failed.stderr.splitlines() == [f"godrays-jax apply: error: image file '{tmp_path / 'missing.exr'}' does not exist"]
    assert failed.stdout.splitlines() == ["exit handler ran"]
    assert not (tmp_path / "out.exr").exists()


def test_a_thread_that_is_not_a_daemon_gets_the_interpreters_own_exit(tmp_path):
    done = _run("thread", "cache", tmp_path=tmp_path)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines()[1:] == ["thread finished", "exit handler ran", "torn down"]
