"""Shared fixtures: float64 mode for gradient checks, random generators."""

import jax
import numpy as np
import pytest


@pytest.fixture
def x64():
    """Run the test with 64-bit JAX floats (for check_grads and 1e-6 comparisons)."""
    with jax.enable_x64(True):
        yield


@pytest.fixture
def rng():
    return np.random.default_rng(20261122)
