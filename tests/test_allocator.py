"""`app.allocator`: the command's process keeps the memory it frees, so XLA's next call does not fault it in again."""

import os
import platform
import subprocess
import sys

import pytest

from godrays_jax.app import allocator, cli

# In a fresh process: allocate a block far above glibc's mmap threshold, touch every page, free it, and print how
# many MiB the process still has resident beyond what it had before.
_PROBE = """
import ctypes, ctypes.util, os, sys
from godrays_jax.app import allocator
assert allocator.keep_freed_memory() == (sys.argv[1] == "tuned")
libc = ctypes.CDLL(ctypes.util.find_library("c"))
libc.malloc.restype, libc.malloc.argtypes, libc.free.argtypes = ctypes.c_void_p, [ctypes.c_size_t], [ctypes.c_void_p]
def resident_mib():
    return int(open("/proc/self/statm").read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
before, size = resident_mib(), 256 << 20
block = libc.malloc(size)
ctypes.memset(block, 1, size)
libc.free(block)
print(resident_mib() - before)
"""


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc's mallopt")
def test_freed_memory_stays_with_the_process_only_when_tuned():
    def kept(mode, **env):
        done = subprocess.run([sys.executable, "-c", _PROBE, mode], capture_output=True, text=True, check=True,
                              env={**os.environ, **env})  # fmt: skip
        return float(done.stdout)

    assert kept("plain", **{allocator.OPT_OUT: "0"}) < 64  # glibc unmaps a large block on free: faulted in again
    assert kept("tuned") > 192  # kept mapped: the next allocation of its size reuses it


def test_the_command_tunes_the_allocator_and_a_call_of_main_does_not(monkeypatch):
    calls = []
    monkeypatch.setattr(allocator, "keep_freed_memory", lambda: calls.append("tuned") or True)
    monkeypatch.setattr(sys, "argv", ["godrays-jax", "cache"])
    assert cli.main(["cache"]) == 0
    assert calls == []
    assert cli.console_main() == 0
    assert calls == ["tuned"]
