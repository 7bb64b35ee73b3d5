"""Shared fixtures: float64 mode for gradient checks, random generators; a compilation cache."""

import os
from pathlib import Path

# Compiling is most of the suite's time and its programs are tiny: LLVM's optimisation of the CPU code costs more
# than it saves here (without fast-math it keeps IEEE semantics at every level). Set before JAX starts its backend;
# the command lines the tests start inherit it.
os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} --xla_backend_optimization_level=0".strip()

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
