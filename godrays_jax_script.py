"""The `godrays-jax` script: the process's memory set up before anything is imported, then `godrays_jax.app.cli`.

A fit, a batch and the tuner call the same large programs over and over. Their largest temporaries (a fit's
Jacobian's among them) are best mapped apart and handed back after each call (`godrays_jax.app.allocator`), which
costs a fault per page on every call, unless the pages are huge. glibc asks the kernel for huge pages for the blocks
it maps only where `GLIBC_TUNABLES` says so when the process starts (`glibc.malloc.hugetlb=1`). So for those
commands the script starts its interpreter once more with that set, before the package is imported: importing it
loads JAX, which would then be loaded twice (what each costs: benchmarks/README.md, "Large blocks on huge pages").
`python -m godrays_jax` has imported the package before its first line runs, and does not; nor does a process whose
`GLIBC_TUNABLES` sets `glibc.malloc.hugetlb` already, or that asks the command to leave its allocator as it is
(`GODRAYS_JAX_KEEP_FREED_MEMORY=0`).

This module is outside the package so that importing it imports nothing but the standard library.
"""

import os
import sys

HUGE_PAGES_TUNABLE = "glibc.malloc.hugetlb=1"
"""`godrays_jax.app.allocator.HUGE_PAGES_TUNABLE`, which this module cannot import without the package: the glibc
tunable (2.35 and later) by which its allocator asks Linux for transparent huge pages on the blocks it maps. The
allocator maps large blocks apart only where Linux gives them (`allocator.huge_pages_on`)."""

REPEATING_COMMANDS = frozenset({"fit", "batch", "tune"})
"""The commands whose process may repeat its programs (`godrays_jax.app.cli.repeats_programs`)."""


def restart_with_huge_pages(argv: list[str], environ: dict[str, str]) -> dict[str, str] | None:
    """The environment to start the interpreter again in for the command line `argv` (as `sys.argv` gives it):
    `environ` asking glibc for huge pages; None where the process is to run as it is."""
    command = argv[1] if len(argv) > 1 else ""
    tunables = environ.get("GLIBC_TUNABLES", "")
    if (
        sys.platform != "linux"
        or command not in REPEATING_COMMANDS
        or environ.get("GODRAYS_JAX_KEEP_FREED_MEMORY", "1") == "0"
        or "glibc.malloc.hugetlb" in tunables
    ):
        return None
    return {**environ, "GLIBC_TUNABLES": f"{tunables}:{HUGE_PAGES_TUNABLE}" if tunables else HUGE_PAGES_TUNABLE}


def script() -> None:
    """The `godrays-jax` script: the interpreter started again with huge pages where `restart_with_huge_pages`
    says (the same process, its command line as it was), then `godrays_jax.app.cli.script`. A restart that fails
    leaves the process as it is."""
    environ = restart_with_huge_pages(sys.argv, dict(os.environ))
    if environ is not None:
        try:
            os.execve(sys.executable, sys.orig_argv, environ)
        except OSError:
            pass
    # Imported once the process will not start again, so that JAX is loaded once.
    from godrays_jax.app.cli import script as command_script

    command_script()
