"""How the checklists compare two results (a helper module, not a test file)."""

import jax
import numpy as np


def assert_trees_close(actual, expected, *, rtol: float, scale=None) -> None:
    """Two pytrees of arrays leaf by leaf: the same structure and shapes, `actual` finite, within `rtol` of the
    largest magnitude of each expected leaf (a relative tolerance per leaf, not per element: gradients that sum
    over a frame in another order differ most where they are nearly zero), or of the same leaf of `scale` where
    that is larger (a pytree like `expected`: the size of the terms a leaf sums, where the sum may cancel)."""
    actual_leaves, expected_leaves = jax.tree_util.tree_leaves(actual), jax.tree_util.tree_leaves(expected)
    assert len(actual_leaves) == len(expected_leaves), (len(actual_leaves), len(expected_leaves))
    scale_leaves = expected_leaves if scale is None else jax.tree_util.tree_leaves(scale)
    for a, e, s in zip(actual_leaves, expected_leaves, scale_leaves):
        a, e = np.asarray(a), np.asarray(e)
        assert a.shape == e.shape, (a.shape, e.shape)
        assert np.all(np.isfinite(a)), "non-finite values"
        size = max(float(np.max(np.abs(e))), float(np.max(np.abs(np.asarray(s)))), 1e-6)
        assert np.max(np.abs(a - e)) <= rtol * size, (np.max(np.abs(a - e)), size)
