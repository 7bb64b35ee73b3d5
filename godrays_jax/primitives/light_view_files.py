"""Depth maps seen from the light, as files: `read_light_view` and `write_light_view`.

An EXR (or any float image OpenImageIO reads) whose depth channel (`Z`, or
Blender's `*.Depth.Z`) holds the light camera's planar depth, `inf` (or
Blender's 1e10) where it sees nothing, and whose header carries the light
camera (`LightView`'s fields): `godrays:light_view_projection`
(`orthographic` or `perspective`), `godrays:light_view_from_camera` (the 12
numbers of `[R | t]`, row by row) and `godrays:light_view_scale`. The numbers
are written as text, numbers separated by spaces, so that any tool that sets a
string attribute can write them; an attribute of floats is read as well.
docs/file_formats.md ("A depth map seen from the light") shows how to render one.
"""

import math
import os

import numpy as np
import OpenImageIO as oiio

from godrays_jax.primitives.channels import channels_text, depth_channel_name
from godrays_jax.primitives.image_files import read_pixels, write_pixels
from godrays_jax.primitives.light_view import PROJECTIONS, LightView

PROJECTION_ATTR = "godrays:light_view_projection"
FROM_CAMERA_ATTR = "godrays:light_view_from_camera"
SCALE_ATTR = "godrays:light_view_scale"

NOTHING_SEEN = 1e9
"""Depths at or beyond this are taken as seeing nothing: renderers write their far plane's distance there
(Blender's Z pass writes 1e10 on the world's background)."""


def _numbers(spec: oiio.ImageSpec, name: str, count: int, path: str) -> list[float]:
    value = spec.getattribute(name)
    if value is None:
        raise ValueError(f"light view '{path}' has no {name} in its header (docs/file_formats.md)")
    try:
        numbers = [float(v) for v in (value.split() if isinstance(value, str) else np.ravel(value))]
    except (TypeError, ValueError):
        numbers = []
    if len(numbers) != count or not all(math.isfinite(v) for v in numbers):
        raise ValueError(f"light view '{path}': {name} must be {count} finite numbers, got {value!r}")
    return numbers


def read_light_view(path: str | os.PathLike) -> LightView:
    """The depth map seen from the light stored in `path`, with its camera from the header.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: not a readable image, no depth channel, or a header
            attribute missing or not what it must be (the message names it).
    """
    path = os.fspath(path)
    pixels, spec = read_pixels(path)
    names = list(spec.channelnames)
    name = depth_channel_name(path, names, None, names[:1]) if len(names) > 1 else names[0]
    depth = pixels[..., names.index(name)]
    if np.isnan(depth).any() or (depth < 0).any():
        raise ValueError(
            f"light view '{path}': its depth ({name}) must be >= 0 and not NaN (channels: {channels_text(names)})"
        )
    projection = spec.getattribute(PROJECTION_ATTR)
    if projection not in PROJECTIONS:
        raise ValueError(
            f"light view '{path}': {PROJECTION_ATTR} must be one of {', '.join(PROJECTIONS)}, got {projection!r}"
        )
    transform = np.asarray(_numbers(spec, FROM_CAMERA_ATTR, 12, path), np.float32).reshape(3, 4)
    (scale,) = _numbers(spec, SCALE_ATTR, 1, path)
    if scale <= 0:
        raise ValueError(f"light view '{path}': {SCALE_ATTR} must be > 0, got {scale}")
    depth = np.where(depth >= NOTHING_SEEN, np.inf, depth).astype(np.float32)
    return LightView(depth=depth, from_camera=transform, scale=np.float32(scale), projection=projection)


def write_light_view(path: str | os.PathLike, light_view: LightView) -> None:
    """Write `light_view` as `read_light_view` reads it (an EXR with a `Z` channel), whole or not at all."""
    depth = np.asarray(light_view.depth, np.float32)
    if depth.ndim != 2:
        raise ValueError(f"light_view.depth must have shape (h, w) to be written, got {depth.shape}")
    spec = oiio.ImageSpec(depth.shape[1], depth.shape[0], 1, oiio.FLOAT)
    spec.channelnames = ("Z",)
    spec.attribute(PROJECTION_ATTR, light_view.projection)
    spec.attribute(FROM_CAMERA_ATTR, " ".join(repr(float(v)) for v in np.ravel(light_view.from_camera)))
    spec.attribute(SCALE_ATTR, repr(float(light_view.scale)))
    write_pixels(path, spec, depth[..., None])
