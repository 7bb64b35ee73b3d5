"""The command's process keeps the memory XLA frees, instead of handing it back to the kernel after every call.

XLA on the CPU allocates each compiled program's large temporaries afresh on
every call, from the threads that run it. glibc serves such blocks from
`mmap` (every block above its threshold, and every block too large for a
thread's own arena) and unmaps them on `free`, so the next call faults the
same memory in again, a 4 KiB page at a time: a fit, whose every step calls
the same program, spent a large share of its time in the kernel doing that.
With one arena (the process's heap, which grows as far as it needs), no
`mmap` for large blocks and no trimming of the heap's free top, a freed
temporary stays mapped and the next call reuses it. The process's peak
memory is still that of its largest call; memory is only handed back when
the process ends, which for a command is soon (benchmarks/README.md, "The
fit as users run it", measures both).

One arena serialises the threads that allocate: XLA's compiler (two code
generator threads and the thread that emits the program) allocates heavily,
and a first fit's compiles waited on that arena's lock for a good share of
their time. So a fit whose programs the compilation cache does not hold yet
(`cli.compiles_first`) takes `COMPILING_ARENAS` arenas instead. Its calls
then fault their largest temporaries in again (glibc maps a block too large
for a thread's own arena apart, whatever `mmap` is allowed, and unmaps it on
`free`), which a single fit's compiles more than pay for; a run whose
programs are read back from the cache, and one that calls them through a
dozen fits and more (placing its light), keep the one arena. glibc fixes
the count once a thread first allocates, so it is chosen before JAX starts.

The price is memory: each compiled program's temporaries stay resident
after its call, so a fit that alternates two programs (the polish: the
effect's render and the stand-in's Jacobian) holds both at once where it
held the larger. So the command keeps them where it repeats its programs
on buffers of bounded size (`cli.repeats_programs`: the tuner, a batch or a
fit up to `KEPT_FIT_PIXELS`), not for one `apply` (nothing to reuse);
`GODRAYS_JAX_KEEP_FREED_MEMORY=0` leaves the allocator as it is, for a
machine where memory is tighter than time.

Compiling is the other large user of the heap: LLVM's many small blocks,
freed when a program is compiled, stay resident in the arenas (their free
pages are not at a heap's top, so no trimming reaches them), and the peak of
a first run was then the compiler's and the program's buffers together. So
the command hands the free pages back to the kernel (`malloc_trim`) after
every compile long enough to have used much, and before every new program it
compiles or reads from the cache, so that the compiler's peak comes on top of
the live buffers alone, not of the temporaries the programs before it freed
and the process kept (`hand_back_after_compiling`).

The heap kept is laid out by the order of its allocations: where smaller
blocks take part of a freed temporary's place, the next call's goes to the
heap's top, and the places left behind stay resident, so the same fit's peak
moved by half a gigabyte between runs. Where the process started with glibc
asking for transparent huge pages (`HUGE_PAGES_TUNABLE`, which only
`GLIBC_TUNABLES` sets, as a process starts: the `godrays-jax` script starts
its interpreter again with it, `godrays_jax_script`) and Linux gives them
(`huge_pages_on`), blocks of `MAPPED_BLOCK_BYTES` and more are mapped apart
instead and handed back on `free`: faulting one in again takes a fault per
huge page instead of one per page, and the heap keeps only the smaller
blocks (benchmarks/README.md, "The fit as users run it", "Large blocks on
huge pages"). Between whole runs of its
programs that a command repeats many times (`fit --light auto`: each of its
search's evaluations, each fit around the light) it also hands back the
heap's free pages (`hand_back_free_memory`), as each run then faults in only
what it uses.

Applied by the `godrays-jax` command (`cli.console_main`) only: a library
must not retune the allocator of the process that imports it. Research code
with the same calling pattern gets the same effect from glibc's tunables in
its environment, set before it starts (docs/fitting.md gives the line).
"""

import ctypes
import ctypes.util
import os
import platform

import jax.monitoring

# mallopt's parameter numbers (glibc's malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_MMAP_MAX, _M_ARENA_MAX = -1, -3, -4, -8
_LARGEST_INT = 2**31 - 1  # mallopt takes a C int

MAPPED_BLOCK_BYTES = 32 << 20
"""Where glibc's huge pages are on (`huge_pages_on`), the kept heap's blocks are those below this size; larger ones
are mapped apart and handed back on `free`. glibc's `mallopt` takes no larger threshold: at most half the size of the
heaps it gives each thread."""

HUGE_PAGES_TUNABLE = "glibc.malloc.hugetlb=1"
"""The glibc tunable (`GLIBC_TUNABLES`, read when the process starts; the `godrays-jax` script sets it,
`godrays_jax_script`) by which glibc asks for transparent huge pages on the blocks it maps and on its heap."""

KEPT_FIT_PIXELS = 1 << 18
"""The largest fit (its frames' pixels in all) or batch frame whose process keeps what it frees
(`cli.repeats_programs`): on larger frames the buffers kept passed the commands' memory bounds (a fit's polish
holds two programs' buffers at once: 3 GB cold at 960x540, 4.3 GB at 1920x1080; a batch of 1920x1080 frames up
to 2.8 GB against 2.0) for a tenth of the time or less."""

OPT_OUT = "GODRAYS_JAX_KEEP_FREED_MEMORY"
"""The environment variable that, set to `0`, leaves the allocator as it is."""


COMPILING_ARENAS = 4
"""The arenas of a process that compiles its programs first (`keep_freed_memory`): its compiler's threads each
allocate from their own. Four kept a first fit's peak near one arena's, where glibc's own count (eight a core)
raised it for no faster compile (benchmarks/README.md, "The fit as users run it")."""


def keep_freed_memory(*, arenas: int = 1) -> bool:
    """Tune glibc's allocator as the module's docstring says, with at most `arenas` malloc arenas (1 for a process
    that mostly calls its programs, `COMPILING_ARENAS` for one that compiles them first); returns whether it was
    (False off glibc, or with `GODRAYS_JAX_KEEP_FREED_MEMORY=0`). Call it before JAX starts its threads.

    Raises:
        ValueError: `arenas` not an int >= 1.
    """
    if not (isinstance(arenas, int) and arenas >= 1):
        raise ValueError(f"arenas must be an int >= 1, got {arenas!r}")
    mallopt = _glibc_function("mallopt")
    if os.environ.get(OPT_OUT, "1") == "0" or mallopt is None:
        return False
    large_blocks = (_M_MMAP_THRESHOLD, MAPPED_BLOCK_BYTES) if huge_pages_on() else (_M_MMAP_MAX, 0)
    settings = ((_M_ARENA_MAX, arenas), large_blocks, (_M_TRIM_THRESHOLD, _LARGEST_INT))
    return all(mallopt(parameter, value) == 1 for parameter, value in settings)


def huge_pages_on() -> bool:
    """Whether glibc in this process asks Linux for transparent huge pages (`HUGE_PAGES_TUNABLE` in `GLIBC_TUNABLES`
    as the process started) and Linux gives them (`huge_pages_given`)."""
    return HUGE_PAGES_TUNABLE in os.environ.get("GLIBC_TUNABLES", "").split(":") and huge_pages_given()


def huge_pages_given() -> bool:
    """Whether Linux gives transparent huge pages to memory that asks for them (its setting `always` or `madvise`)."""
    try:
        with open("/sys/kernel/mm/transparent_hugepage/enabled") as setting:
            return "[never]" not in setting.read()
    except OSError:
        return False


def _glibc_function(name: str):
    """glibc's function `name` (ctypes), or None off glibc."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return None
    try:
        return getattr(ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6"), name)
    except (OSError, AttributeError):
        return None


COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"
"""The `jax.monitoring` event JAX records after every compile by XLA, with its duration."""

COMPILE_REQUEST_EVENT = "/jax/compilation_cache/compile_requests_use_cache"
"""The `jax.monitoring` event JAX records before it looks a new program up in the compilation cache (which the
command enables), then compiles it if it is not there."""

TRIMMED_COMPILE_SECONDS = 0.5
"""Compiles at least this long are followed by a `malloc_trim`: the fit's and the fog's programs (seconds each), not
the many small ones a command compiles in a fraction of a second each, whose memory is small."""

_trimming = []  # the listener, once registered: one per process


def hand_back_free_memory() -> bool:
    """Hand the heap's free pages back to the kernel now (glibc's `malloc_trim(0)`); returns whether it did (False
    off glibc). For a command between whole runs of its programs (`fit --light auto`'s search evaluations and its
    fits around the light): the heap kept (`keep_freed_memory`) grows by whole temporaries where smaller blocks split
    the place of a freed one, and over many runs its free places added up (docs/findings.md, "The fit's cost: what
    did not help")."""
    trim = _glibc_function("malloc_trim")
    if trim is None:
        return False
    trim(0)
    return True


def hand_back_after_compiling() -> bool:
    """After every compile of at least `TRIMMED_COMPILE_SECONDS` and before every new program (`jax.monitoring`'s
    `COMPILE_REQUEST_EVENT`), hand the heap's free pages back to the kernel (glibc's `malloc_trim(0)`), as the
    module's docstring says; returns whether it will (False off glibc). Once per process: later calls change
    nothing."""
    if _trimming:
        return True
    trim = _glibc_function("malloc_trim")
    if trim is None:
        return False

    def after_compile(event: str, duration: float, **_) -> None:
        if event == COMPILE_EVENT and duration >= TRIMMED_COMPILE_SECONDS:
            trim(0)

    def before_compile(event: str, **_) -> None:
        # What the programs before it freed and the process kept (`keep_freed_memory`), handed back before the
        # compiler's own peak comes on top of it: a first run's peak was theirs and the compiler's together.
        if event == COMPILE_REQUEST_EVENT:
            trim(0)

    jax.monitoring.register_event_duration_secs_listener(after_compile)
    jax.monitoring.register_event_listener(before_compile)
    _trimming.append((after_compile, before_compile))
    return True
