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


MAX_LIGHT_PX = 1e9
"""How far from the frame's corner (pixels, on either axis) `check_light` keeps a light: squares and sums of pixel
distances up to it stay finite in float32."""


def check_light(light_xy, name: str = "light_xy") -> jax.Array | np.ndarray:
    """`light_xy` as an array: a pixel position `(x, y)`, moved along its direction to at most `MAX_LIGHT_PX`.

    A light farther than `MAX_LIGHT_PX` pixels from the frame's corner
    `(0, 0)` on either axis (an infinite coordinate too) is drawn as at that
    bound in the same direction, so that float32 maths on pixel distances
    stays finite: the direction from a pixel to it changes by less than the
    frame's size over `MAX_LIGHT_PX` radians, and every light-driven effect
    has faded such a light out entirely (`offscreen_fade` reaches at most ten
    frame sizes). Lights within the bound are returned exactly; past it the
    gradient keeps only the light's direction. Python numbers and NumPy
    arrays are bounded in float64 (a float64 NumPy array comes back), before
    a cast to float32 could overflow. NaN stays NaN.

    Raises:
        ValueError: `light_xy` is not of shape (2,), naming `name`.
    """
    if np.shape(light_xy) != (2,):
        raise ValueError(f"{name} must be a pixel position (x, y) of shape (2,), got shape {np.shape(light_xy)}")
    if isinstance(light_xy, jax.Array):
        xp, light = jnp, light_xy
        if not jnp.issubdtype(light.dtype, jnp.floating):
            light = light.astype(jnp.float32)
        work = jnp.promote_types(light.dtype, jnp.float32)  # the bound is beyond float16's range
    else:
        xp, light = np, np.asarray(light_xy, np.float64)
        work = np.float64
    inputs = light.astype(work)
    infinite = xp.isinf(inputs)
    finite = xp.where(infinite, 0.0, inputs)  # no infinity in the scaled branch: its gradient would be NaN
    scale = MAX_LIGHT_PX / xp.maximum(xp.max(xp.abs(finite)), MAX_LIGHT_PX)
    along_axes = xp.where(infinite, xp.sign(inputs) * MAX_LIGHT_PX, 0.0)  # the limit of a direction to infinity
    bounded = xp.where(xp.any(infinite), along_axes, finite * scale).astype(work)
    return bounded.astype(light.dtype) if xp is jnp else bounded


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
