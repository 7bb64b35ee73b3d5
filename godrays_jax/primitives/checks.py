"""Trace-time argument checks (each error names the argument), and the one line that reports any error."""

import contextlib
import contextvars
import numbers
from collections.abc import Iterator

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


def check_image(image, name: str = "image") -> None:
    shape = jnp.shape(image)
    if len(shape) != 3 or shape[-1] not in (1, 2, 3, 4):
        raise ValueError(f"{name} must have shape (H, W, C) with C in 1..4, got shape {shape}")
    if shape[0] < 1 or shape[1] < 1:
        raise ValueError(f"{name} must be at least 1x1, got shape {shape}")


def check_plane(plane, name: str, height: int, width: int) -> None:
    shape = jnp.shape(plane)
    if shape != (height, width):
        raise ValueError(f"{name} must have shape ({height}, {width}) to match the image, got {shape}")


def check_light(light_xy, name: str = "light_xy") -> None:
    if jnp.shape(light_xy) != (2,):
        raise ValueError(f"{name} must be a pixel position (x, y) of shape (2,), got shape {jnp.shape(light_xy)}")


def check_scalar(value, name: str) -> None:
    if jnp.ndim(value) != 0:
        raise ValueError(f"{name} must be a scalar, got shape {jnp.shape(value)}")


def is_static_int(value) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def resolve_count(count, upper, name: str, upper_name: str, *, minimum: int = 1) -> tuple[int, bool]:
    """The static loop length for an integer count or its continuous relaxation.

    Returns `(static_upper, relaxed)`. A Python int count needs no upper bound; a
    float or traced count (the relaxation) needs a static Python-int `upper`.
    """
    if upper is not None and (not is_static_int(upper) or upper < minimum):
        raise ValueError(f"{upper_name} must be a Python int >= {minimum}, got {upper!r}")
    if is_static_int(count):
        if count < minimum:
            raise ValueError(f"{name} must be >= {minimum}, got {count}")
        if upper is not None and count > upper:
            raise ValueError(f"{name}={count} exceeds {upper_name}={upper}")
        return count, False
    check_scalar(count, name)
    if upper is None:
        raise ValueError(
            f"{name} is a float or traced value (the continuous relaxation): pass the static upper bound {upper_name}"
        )
    return upper, True


_RANGES_GUARANTEED = contextvars.ContextVar("ranges_guaranteed", default=False)


@contextlib.contextmanager
def ranges_guaranteed() -> Iterator[None]:
    """Trace without run-time range checks: the caller keeps every traced value in range itself.

    `fit` does (its unknowns are mapped into each field's bounds), and a
    program without `equinox.error_if`'s host callback can be stored in JAX's
    persistent compilation cache.
    """
    token = _RANGES_GUARANTEED.set(True)
    try:
        yield
    finally:
        _RANGES_GUARANTEED.reset(token)


def ranges_are_guaranteed() -> bool:
    """Whether the caller traces inside `ranges_guaranteed()`: part of what a stored program's trace depends on."""
    return _RANGES_GUARANTEED.get()


def checked_range(value, low: float, high: float, message: str):
    """`value`, checked to lie in `[low, high]`: now if it is known (a `ValueError`), else when it is computed.

    A known value (a constant closed over by a compiled function, as an
    effect's fields are in `apply` and `batch`) is checked on the host, so the
    compiled program needs no host callback and can be cached across
    processes; a traced one with `equinox.error_if`, unless the caller
    guarantees the range (`ranges_guaranteed`).
    """
    if not isinstance(value, jax.core.Tracer):
        values = np.asarray(value)
        if np.any(values < low) or np.any(values > high) or np.any(np.isnan(values)):
            raise ValueError(message)
        return value
    if _RANGES_GUARANTEED.get():
        return value
    return eqx.error_if(value, (value < low) | (value > high), message)


def checked_count(count, upper: int, name: str, upper_name: str, dtype):
    """A relaxed count as a `dtype` scalar, checked to lie in [0, upper] (`checked_range`)."""
    return jnp.asarray(checked_range(count, 0, upper, f"{name} must lie in [0, {upper_name}={upper}]"), dtype)


def error_line(error: BaseException) -> str:
    """The one line that says what went wrong, also for errors raised inside jitted code (`equinox.error_if`)."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    for line in lines:
        if line.startswith("equinox.EquinoxRuntimeError:"):
            return line.split(":", 1)[1].strip()
    return lines[0] if lines else type(error).__name__
