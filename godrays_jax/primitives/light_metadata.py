"""The light stored in a frame's header: its pixel position, whether it is in front, its distance; and every light
of a frame that has several."""

import math
import os
from collections.abc import Sequence
from typing import NamedTuple

from godrays_jax.primitives.image_files import read_header

LIGHT_PX_ATTR = "godrays:light_px"
LIGHT_IN_FRONT_ATTR = "godrays:light_in_front"
LIGHT_DEPTH_ATTR = "godrays:light_depth"
"""The light's distance from the camera in scene units (a float, `inf` for a light at infinity), as `render` writes
it."""
LIGHTS_ATTR = "godrays:lights"
"""Every light of a frame that has several, in `--light`'s words: `x,y` or `x,y,behind`, `;` between lights; the first
is the one `godrays:light_px` holds, for readers of one light."""
LIGHTS_DEPTH_ATTR = "godrays:lights_depth"
"""Their distances from the camera in scene units, `;` between lights (`inf`: a light at infinity)."""
LIGHTS_TINT_ATTR = "godrays:lights_tint"
"""Their tints, the linear `r,g,b` each one's light is multiplied by (`effects.lights.Light.tint`), `;` between
lights."""
_SEPARATOR = ";"


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


class StoredLight(NamedTuple):
    """One light of a frame's header (`read_lights`): its pixel position (x right, y down, pixel centres at
    `i + 0.5`), whether it is in front of the camera, its distance in scene units (`inf`: at infinity) and its
    tint (linear RGB, 1 the effect's own light)."""

    xy: tuple[float, float]
    in_front: bool = True
    depth: float = math.inf
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)


def lights_metadata(lights: Sequence[StoredLight]) -> dict[str, str]:
    """The header attributes of a frame's several lights (`LIGHTS_ATTR`, `LIGHTS_DEPTH_ATTR`, `LIGHTS_TINT_ATTR`),
    for `write_buffers(..., metadata=)` beside `light_xy=` (the first light's); `read_lights` reads them back."""
    lights = [StoredLight(*light) for light in lights]
    if not lights:
        raise ValueError("lights must hold at least one light")
    for index, light in enumerate(lights):
        numbers = [*light.xy, *light.tint]
        if len(light.xy) != 2 or len(light.tint) != 3 or not all(math.isfinite(float(value)) for value in numbers):
            raise ValueError(f"lights[{index}] must have a finite (x, y) and a finite (r, g, b) tint, got {light!r}")
        if not (float(light.depth) > 0 and min(light.tint) >= 0):
            raise ValueError(f"lights[{index}] must have a distance > 0 and a tint >= 0, got {light!r}")
    return {
        LIGHTS_ATTR: _SEPARATOR.join(
            ",".join([repr(float(light.xy[0])), repr(float(light.xy[1])), *([] if light.in_front else ["behind"])])
            for light in lights
        ),
        LIGHTS_DEPTH_ATTR: _SEPARATOR.join(repr(float(light.depth)) for light in lights),
        LIGHTS_TINT_ATTR: _SEPARATOR.join(",".join(repr(float(value)) for value in light.tint) for light in lights),
    }


def read_lights(path: str | os.PathLike) -> list[StoredLight] | None:
    """Every light stored in a frame's header by a renderer that wrote several (`LIGHTS_ATTR`, `lights_metadata`:
    `godrays-jax render` of a scene with `lights`); `None` when the file has no `godrays:lights` (then
    `read_light` and `read_light_depth` say what it has of one light). Distances not stored are `inf`, tints 1.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the file is not a readable image, or an attribute is malformed or gives another count of lights.
    """
    path = os.fspath(path)
    spec = read_header(path)
    text = spec.getattribute(LIGHTS_ATTR)
    if text is None:
        return None

    def pieces(name, value):
        if not isinstance(value, str) or not value.strip():
            raise ValueError(f"image '{path}': attribute {name} must be a text, got {value!r}")
        return [piece.replace(" ", "").split(",") for piece in value.split(_SEPARATOR)]

    def numbers(name, piece, count):
        try:
            values = [float(value) for value in piece]
        except ValueError:
            values = []
        if len(values) != count or any(math.isnan(value) for value in values):
            raise ValueError(f"image '{path}': attribute {name} holds {','.join(piece)!r} where {count} numbers go")
        return values

    lights = []
    for piece in pieces(LIGHTS_ATTR, text):
        side = piece.pop().lower() if len(piece) == 3 else "front"
        if side not in ("front", "behind"):
            raise ValueError(f"image '{path}': attribute {LIGHTS_ATTR}: a side is front or behind, got {side!r}")
        x, y = numbers(LIGHTS_ATTR, piece, 2)
        if not (math.isfinite(x) and math.isfinite(y)):
            raise ValueError(f"image '{path}': attribute {LIGHTS_ATTR} must hold finite positions, got {text!r}")
        lights.append(StoredLight((x, y), side == "front"))
    for name, field, count in ((LIGHTS_DEPTH_ATTR, "depth", 1), (LIGHTS_TINT_ATTR, "tint", 3)):
        value = spec.getattribute(name)
        if value is None:
            continue
        values = [numbers(name, piece, count) for piece in pieces(name, value)]
        if len(values) != len(lights):
            raise ValueError(f"image '{path}': attribute {name} gives {len(values)} lights where {LIGHTS_ATTR} gives "
                             f"{len(lights)}")  # fmt: skip
        if any(not (v > 0) if count == 1 else not (math.isfinite(v) and v >= 0) for vs in values for v in vs):
            raise ValueError(f"image '{path}': attribute {name} must hold distances > 0 or tints >= 0, got {value!r}")
        lights = [light._replace(**{field: v[0] if count == 1 else tuple(v)}) for light, v in zip(lights, values)]
    return lights
