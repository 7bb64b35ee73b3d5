"""The camera a frame's header carries: its horizontal field of view, and how its depth channel measures distance.

Where the field of view comes from, first found first:

| header | writer | field of view |
|---|---|---|
| `godrays:fov_x_deg` (float, degrees) | `godrays-jax render` | as stored |
| `worldToCamera` and `worldToNDC` (4x4 matrices, OpenEXR's standard attributes) | renderers and compositors that keep the camera (Arnold, RenderMan, Nuke's `exr/` metadata written back) | from the projection `cameraToNDC = inverse(worldToCamera) * worldToNDC`, NDC in [-1, 1] or [0, 1] (told apart by where the camera's axis lands) |
| `Lens` (a string in mm) beside Blender's marks | Blender with Output > Metadata > Lens on | `2 atan(18 / lens)`: Blender's default 36 mm sensor width |

The depth kind (`camera.DEPTH_KINDS`): a Blender render's `Z` pass is
planar (distance along the camera's axis); Blender marks its files with
`BlenderMultiChannel` (multilayer EXR) and Cycles' `cycles.*` statistics, so
those read as planar without a flag. Every other file reads as ray depth
(distance along the camera ray: Mitsuba, `render`) unless the caller says
otherwise (`--depth-kind planar`).
"""

import dataclasses
import math
import os

import numpy as np
import OpenImageIO as oiio

from godrays_jax.primitives.camera import DepthKind
from godrays_jax.primitives.image_files import read_header

FOV_X_ATTR = "godrays:fov_x_deg"
"""The camera's horizontal field of view in degrees (a float), as `render` writes it."""

CLIP_PLANES_ATTR = "godrays:clip_planes"
"""The camera's near and far clip planes in scene units (two floats), as `render` writes them: the XNA depth test's
`near_plane` and `far_plane`."""

BLENDER_SENSOR_WIDTH_MM = 36.0
"""Blender's default sensor width: its header stamps the lens but not the sensor."""


@dataclasses.dataclass(frozen=True)
class FrameCamera:
    """What a frame's header says about its camera.

    Attributes:
        fov_x_deg: the horizontal field of view in degrees, or None when the header does not say.
        depth_kind: how the depth channel measures distance, `"ray"` or `"planar"` (Blender's files).
        source: which attribute the field of view was read from (for messages), or None.
    """

    fov_x_deg: float | None
    depth_kind: DepthKind
    source: str | None


def is_blender(spec: oiio.ImageSpec) -> bool:
    """Whether Blender wrote the file: its multilayer mark, or Cycles' render statistics in the header."""
    names = [attribute.name for attribute in spec.extra_attribs]
    return "BlenderMultiChannel" in names or any(name.startswith("cycles.") for name in names)


def _fov_from_matrices(world_to_camera, world_to_ndc) -> float | None:
    """The horizontal field of view of OpenEXR's `worldToCamera` / `worldToNDC` (row vectors: `p' = p M`)."""
    try:
        to_camera = np.asarray(world_to_camera, np.float64).reshape(4, 4)
        to_ndc = np.asarray(world_to_ndc, np.float64).reshape(4, 4)
        projection = np.linalg.inv(to_camera) @ to_ndc
    except (ValueError, TypeError, np.linalg.LinAlgError):
        return None
    for forward in (-1.0, 1.0):  # OpenGL-style cameras look down -z, RenderMan's down +z
        axis = np.array([0.0, 0.0, forward, 1.0]) @ projection
        side = np.array([1.0, 0.0, forward, 1.0]) @ projection
        if axis[3] <= 0 or side[3] <= 0:
            continue
        centre, edge = axis[0] / axis[3], side[0] / side[3]
        half_width = 0.5 if abs(centre - 0.5) < 1e-3 else 1.0 if abs(centre) < 1e-3 else None
        if half_width is None or edge == centre:
            return None
        fov = 2.0 * math.degrees(math.atan(half_width / abs(edge - centre)))
        return fov if 0.0 < fov < 180.0 else None
    return None


def _number(value) -> float | None:
    try:
        number = float(str(value).lower().replace("mm", "").strip())
    except (TypeError, ValueError):
        return None
    return number if math.isfinite(number) else None


def camera_from_header(spec: oiio.ImageSpec) -> FrameCamera:
    """The field of view and depth kind a header carries (module docstring)."""
    blender = is_blender(spec)
    kind: DepthKind = "planar" if blender else "ray"
    stored = _number(spec.getattribute(FOV_X_ATTR))
    if stored is not None and 0.0 < stored < 180.0:
        return FrameCamera(stored, kind, FOV_X_ATTR)
    world_to_camera, world_to_ndc = spec.getattribute("worldToCamera"), spec.getattribute("worldToNDC")
    if world_to_camera is not None and world_to_ndc is not None:
        fov = _fov_from_matrices(world_to_camera, world_to_ndc)
        if fov is not None:
            return FrameCamera(fov, kind, "worldToCamera, worldToNDC")
    lens = _number(spec.getattribute("Lens")) if blender else None
    if lens is not None and lens > 0:
        fov = 2.0 * math.degrees(math.atan(BLENDER_SENSOR_WIDTH_MM / 2 / lens))
        return FrameCamera(fov, kind, f"Blender's Lens ({lens:g} mm, {BLENDER_SENSOR_WIDTH_MM:g} mm sensor)")
    return FrameCamera(None, kind, None)


def read_frame_camera(path: str | os.PathLike) -> FrameCamera:
    """`camera_from_header` of a file's header (the pixels are not read).

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the file is not a readable image.
    """
    return camera_from_header(read_header(path))


def read_clip_planes(path: str | os.PathLike) -> tuple[float, float] | None:
    """The near and far clip planes a frame's header carries (`CLIP_PLANES_ATTR`, scene units), or None.

    None also when the stored pair is not `0 < near < far < inf`.
    """
    stored = read_header(path).getattribute(CLIP_PLANES_ATTR)
    try:
        near, far = (float(value) for value in stored)
    except (TypeError, ValueError):
        return None
    return (near, far) if 0.0 < near < far < math.inf else None
