"""Shared fixtures: float64 mode, random generators; a compilation cache; XLA's code maps kept in bounds."""

import gc
import os
from pathlib import Path

# Compiling is most of the suite's time and its programs are tiny: LLVM's optimisation of the CPU code costs more
# than it saves here (without fast-math it keeps IEEE semantics at every level), and XLA's older fusion emitters
# compile them in about half the time of the MLIR ones (benchmarks/README.md, "The test suite on CI"). What the
# tests check is the library's arithmetic, which any code generator runs (a GPU's is another again); only the
# rounding of float32 sums may differ between programs, and no test compares two programs more closely than that.
# Set before JAX starts its backend; the command lines the tests start inherit it.
SUITE_XLA_FLAGS = "--xla_backend_optimization_level=0 --xla_cpu_use_fusion_emitters=false"
os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {SUITE_XLA_FLAGS}".strip()

# Tracing builds JAX's graphs out of many small objects, and Python's cyclic collector, at its default thresholds,
# walks every object the process holds again and again while a large program is traced: collecting rarely shortens
# the suite's tracing-heavy tests (benchmarks/README.md, "The test suite on CI").
gc.set_threshold(200_000, 50, 1000)

import jax  # noqa: E402 - after XLA_FLAGS
import numpy as np
import pytest

from godrays_jax.pipeline import exported

# Most of the suite's time is XLA compilation, and many tests compile the same
# programs (same kernel, same shapes, another lambda): a persistent cache shared
# by every test and pytest-xdist worker compiles each of them once.
CACHE = Path(__file__).resolve().parents[1] / ".jax_cache"
CACHE.mkdir(mode=0o700, exist_ok=True)  # the command line uses only a cache folder that no other user can write
jax.config.update("jax_compilation_cache_dir", str(CACHE))
# The command line, run in-process by the CLI tests, enables its own cache: the same folder, not the user's.
os.environ.setdefault("GODRAYS_JAX_CACHE_DIR", str(CACHE))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


# XLA's CPU client maps the code of every program it loads into the process (three small maps per kernel at
# this optimisation level) and keeps them while JAX's caches hold the program. A worker that runs hundreds of
# tests reaches Linux's limit on a process's maps (vm.max_map_count, 65530 by default) and the next load dies
# of a fatal signal (a CI run's worker, near the end of the suite). Once a test leaves this many more maps than
# the last clearing did, JAX's caches are cleared: later tests reload what they need from the persistent cache.
NEW_MAPS_BEFORE_CLEARING = 20_000
_maps_after_clearing = 0


def _memory_maps() -> int:
    """How many memory maps this process holds (0 where the system does not say)."""
    try:
        with open("/proc/self/maps", "rb") as maps:
            return sum(1 for _ in maps)
    except OSError:
        return 0


# pytest-xdist (`--dist load`) hands the tests out in their order, so a test of minutes handed out last runs alone
# while the other worker waits: the slow step's longest, each fitting a 320x180 frame twice from an empty cache, go
# first (benchmarks/README.md, "The test suite on CI").
LONGEST_FIRST = ("tests/test_fit_limits.py::test_a_default_fit_of_a_frame_without_a_camera",)


def pytest_collection_modifyitems(items):
    items.sort(key=lambda item: not item.nodeid.startswith(LONGEST_FIRST))  # stable: the rest keep their order


@pytest.fixture(autouse=True)
def _maps_below_the_kernels_limit():
    global _maps_after_clearing
    yield
    if _memory_maps() > _maps_after_clearing + NEW_MAPS_BEFORE_CLEARING:
        jax.clear_caches()
        gc.collect()
        _maps_after_clearing = _memory_maps()


@pytest.fixture(autouse=True)
def _traced_as_the_library_does():
    """The command line, run in-process, stores traced programs (`pipeline.exported`); the next test traces its own."""
    yield
    exported.use_directory(None)


@pytest.fixture
def x64():
    """Run the test with 64-bit JAX floats (for check_grads and 1e-6 comparisons)."""
    with jax.enable_x64(True):
        yield


@pytest.fixture
def rng():
    return np.random.default_rng(20261122)
