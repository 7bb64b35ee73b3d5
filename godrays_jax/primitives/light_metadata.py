"""The light stored in a frame's header: its pixel position, whether it is in front, its distance."""

import math
import os
from collections.abc import Sequence

from godrays_jax.primitives.image_files import read_header

LIGHT_PX_ATTR = "godrays:light_px"
LIGHT_IN_FRONT_ATTR = "godrays:light_in_front"
LIGHT_DEPTH_ATTR = "godrays:light_depth"
"""The light's distance from the camera in scene units (a float, `inf` for a light at infinity), as `render` writes it."""


def _parse_light_px(value: object, path: str) -> tuple[float, float]:
    if isinstance(value, str):
        parts = value.replace(",", " ").split()
    else:
        parts = list(value) if isinstance(value, Sequence) else [value]
    try:
        x, y = (float(p) for p in parts)
    except (TypeError, ValueError):
        raise ValueError(
            f"image '{path}': attribute {LIGHT_PX_ATTR} must be two numbers, got {value!r}"
        ) from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise ValueError(f"image '{path}': attribute {LIGHT_PX_ATTR} must be finite, got ({x}, {y})")
    return x, y


def read_light(path: str | os.PathLike) -> tuple[tuple[float, float], bool] | None:
    """The light stored in a frame's metadata by `write_buffers`.

    Returns:
        `((x, y), in_front)`: the light's pixel position (x right, y down,
        pixel centres at `i + 0.5`) and whether it is in front of the camera
        (True when the file does not say); `None` when the file has no
        `godrays:light_px` attribute.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the file is not a readable image, or `godrays:light_px`
            is not two finite numbers.
    """
    path = os.fspath(path)
    spec = read_header(path)
    value = spec.getattribute(LIGHT_PX_ATTR)
    if value is None:
        return None
    in_front = spec.getattribute(LIGHT_IN_FRONT_ATTR)
    return _parse_light_px(value, path), True if in_front is None else bool(int(in_front))


def read_light_depth(path: str | os.PathLike) -> float | None:
    """The light's distance from the camera stored in a frame's metadata (`godrays:light_depth`, scene units).

    `inf` for a light at infinity (a directional sun); `None` when the file
    does not say. Effects take it as `light_depth` (the XNA crepuscular-rays
    article's depth test and step clamp).

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the file is not a readable image, or the attribute is not a number.
    """
    path = os.fspath(path)
    value = read_header(path).getattribute(LIGHT_DEPTH_ATTR)
    if value is None:
        return None
    try:
        depth = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"image '{path}': attribute {LIGHT_DEPTH_ATTR} must be a number, got {value!r}") from None
    if math.isnan(depth) or depth < 0:
        raise ValueError(f"image '{path}': attribute {LIGHT_DEPTH_ATTR} must be >= 0, got {depth}")
    return depth
