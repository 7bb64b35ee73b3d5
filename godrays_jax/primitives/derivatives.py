"""Renders whose derivatives are never taken, which kernels may compute a cheaper way (`values_only`)."""

import contextlib
import contextvars
from collections.abc import Iterator

_VALUES_ONLY = contextvars.ContextVar("values_only", default=False)


@contextlib.contextmanager
def values_only() -> Iterator[None]:
    """Trace renders whose derivatives nobody takes, as `torch.no_grad` marks a forward pass: a kernel may then
    compute the same values (to float rounding) a way that no derivative goes through, or none as cheaply.

    `VolumetricFog` then reads a silhouette's other side only at the partly covered pixels, compacted in a
    `while_loop` (which reverse mode cannot go through, and which XLA compiled wrong in a vectorised forward-mode
    Jacobian), and each march ray only through the piece that holds a pixel's depth. The command line renders
    this way (`apply`, `batch`, a fit's residuals and losses); a plain call of an effect, or one under
    `jax.jit`, `jax.grad` or `jax.jvp`, is differentiable as ever.

    It is read when a function is traced: set it inside the function that `jax.jit` compiles, so that its
    program depends on its own arguments alone::

        @jax.jit
        def frame(buffers, light_xy):
            with gr.values_only():
                return effect(buffers, light_xy)
    """
    token = _VALUES_ONLY.set(True)
    try:
        yield
    finally:
        _VALUES_ONLY.reset(token)


def values_are_only_needed() -> bool:
    """Whether the caller traces inside `values_only()`."""
    return _VALUES_ONLY.get()
