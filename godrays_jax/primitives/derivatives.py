"""Renders whose derivatives are never taken, which kernels may compute a cheaper way."""

import contextlib
import contextvars
from collections.abc import Iterator

_VALUES_ONLY = contextvars.ContextVar("values_only", default=False)


@contextlib.contextmanager
def values_only() -> Iterator[None]:
    """Trace renders whose derivatives nobody takes (`apply`, `batch`, a fit's residuals and losses): a kernel may
    then compute the same values a way no derivative goes through, or none as cheaply (a mask's pixels compacted
    and read in a `while_loop`, which reverse mode cannot transpose and XLA compiled wrong in the fit's vectorised
    forward-mode Jacobian). Read when a function is traced: set it inside the traced function, so that its
    program depends on its own arguments alone."""
    token = _VALUES_ONLY.set(True)
    try:
        yield
    finally:
        _VALUES_ONLY.reset(token)


def values_are_only_needed() -> bool:
    """Whether the caller traces inside `values_only()`."""
    return _VALUES_ONLY.get()
