"""Frames written: `write_buffers`, and a frame kept as stored (`FrameFile`) rewritten with new colour."""

import dataclasses
import os
from collections.abc import Mapping

import numpy as np
import OpenImageIO as oiio
from jaxtyping import ArrayLike, Float

from godrays_jax.primitives.buffers import Buffers
from godrays_jax.primitives.channels import (
    GLOW_NAMES,
    GLOW_TARGET_NAMES,
    LIGHT_PASS_NAMES,
    NORMAL_NAMES,
    OBJECT_ID_NAME,
    channels_text,
)
from godrays_jax.primitives.frame_reading import decode_buffers, reads_straight_alpha
from godrays_jax.primitives.image_files import EXR_EXTENSIONS, read_pixels, set_attribute, write_pixels
from godrays_jax.primitives.light_metadata import LIGHT_IN_FRONT_ATTR, LIGHT_PX_ATTR


def _host_float(name: str, array: ArrayLike, shape: tuple[int, ...]) -> np.ndarray:
    a = np.asarray(array, dtype=np.float32)
    if a.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {a.shape}")
    return a


def write_buffers(
    path: str | os.PathLike,
    buffers: Buffers,
    *,
    light_xy: tuple[float, float] | None = None,
    light_in_front: bool = True,
    metadata: Mapping[str, object] | None = None,
    half: bool = False,
) -> None:
    """Write a frame as an EXR that `read_buffers` reads back.

    Channels (docs/file_formats.md): `R, G, B, A` (coverage), `Z` (depth, `+inf`
    on sky), then whichever optional passes `buffers` holds. Zip compression.

    Args:
        path: destination, must end in `.exr`; written atomically.
        buffers: the frame; colour must have 3 channels.
        light_xy: the light's pixel position (x right, y down), stored as
            `godrays:light_px` with `godrays:light_in_front`; omitted if None.
        light_in_front: whether the light is in front of the camera.
        metadata: extra header attributes, `name -> str | int | float |
            sequence of numbers`.
        half: store `R, G, B, A` as half floats (max 65504, ~3 significant
            digits) instead of 32-bit floats; depth and passes stay float32.

    Raises:
        ValueError: not an `.exr` path, colour not 3 channels, shapes that
            disagree, or an unsupported metadata value.
        FileNotFoundError: the destination folder does not exist.
        OSError: OpenImageIO failed to write (nothing is left behind).
    """
    if os.path.splitext(os.fspath(path))[1].lower() not in EXR_EXTENSIONS:
        raise ValueError(f"cannot write buffers to '{os.fspath(path)}': the file must end in .exr")
    color = np.asarray(buffers.color, dtype=np.float32)
    if color.ndim != 3 or color.shape[-1] != 3:
        raise ValueError(f"buffers.color must have shape (H, W, 3) to write, got {color.shape}")
    hw = color.shape[:2]
    names = ["R", "G", "B", "A", "Z"]
    planes = [color, _host_float("buffers.coverage", buffers.coverage, hw)[..., None],
              _host_float("buffers.depth", buffers.depth, hw)[..., None]]
    if buffers.normal is not None:
        names += NORMAL_NAMES
        planes.append(_host_float("buffers.normal", buffers.normal, (*hw, 3)))
    if buffers.object_id is not None:
        names.append(OBJECT_ID_NAME)
        planes.append(_host_float("buffers.object_id", buffers.object_id, hw)[..., None])
    if buffers.light_pass is not None:
        names.append(LIGHT_PASS_NAMES[0])
        planes.append(_host_float("buffers.light_pass", buffers.light_pass, hw)[..., None])
    if buffers.glow_pass is not None:
        names += GLOW_NAMES
        planes.append(_host_float("buffers.glow_pass", buffers.glow_pass, (*hw, 4)))
    if buffers.glow_target is not None:
        names += GLOW_TARGET_NAMES
        planes.append(_host_float("buffers.glow_target", buffers.glow_target, (*hw, 3)))
    pixels = np.ascontiguousarray(np.concatenate(planes, axis=-1))

    spec = oiio.ImageSpec(hw[1], hw[0], len(names), oiio.FLOAT)
    spec.channelnames = tuple(names)
    spec.alpha_channel = 3
    spec.z_channel = 4
    if half:
        spec.channelformats = tuple(oiio.TypeHalf if i < 4 else oiio.TypeFloat for i in range(len(names)))
    spec.attribute("compression", "zip")
    for key, value in (metadata or {}).items():
        set_attribute(spec, key, value)
    if light_xy is not None:
        x, y = light_xy
        spec.attribute(LIGHT_PX_ATTR, oiio.TypeFloat2, (float(x), float(y)))
        spec.attribute(LIGHT_IN_FRONT_ATTR, oiio.TypeInt, int(bool(light_in_front)))
    write_pixels(path, spec, pixels)


@dataclasses.dataclass(frozen=True)
class FrameFile:
    """A frame file as it was stored: every channel of its first subimage and its header.

    What `write_frame_like` needs to write a processed frame with the input's
    channels, per-channel formats (half / float), compression, tiling and
    metadata. `pixels` is float32 `(H, W, C)` in the file's channel order;
    `color_channels` names the channels the colour was read from (and
    `write_frame_like` replaces).
    """

    path: str
    pixels: np.ndarray
    spec: oiio.ImageSpec
    color_channels: tuple[str, str, str] = ("R", "G", "B")


def read_frame(path: str | os.PathLike, **options) -> tuple[Buffers, FrameFile]:
    """`read_buffers` that also returns the file as stored, reading it once.

    Args:
        path: the frame, as for `read_buffers`.
        **options: `read_buffers`' keywords (`depth_channel`, `color_layer`,
            `sky_depth`, `coverage`, `depth_kind`, `fov_x_deg`, `without_depth`).

    Returns:
        `(buffers, frame_file)`: the `Buffers` exactly as `read_buffers` gives
        them, and the `FrameFile` to pass to `write_frame_like`.

    Raises:
        As `read_buffers`; `TypeError` for a keyword it does not take.
    """
    pixels, spec = read_pixels(path, straight_alpha=reads_straight_alpha(path))
    buffers, color_channels = decode_buffers(path, pixels, spec, **options)
    return buffers, FrameFile(path=os.fspath(path), pixels=pixels, spec=spec, color_channels=color_channels)


def write_frame_like(
    path: str | os.PathLike, color: Float[ArrayLike, "H W 3"], like: FrameFile, *, replace: bool = True
) -> None:
    """Write `color` in place of the colour channels of `like` (`like.color_channels`), keeping everything else.

    Every other channel (alpha, depth, passes, anything the renderer wrote),
    each channel's storage format (half stays half: values above 65504 become
    `+inf` there), the compression, tiling and every metadata attribute are
    copied from `like.spec`, so the output reads back like the input with new
    colour. Only the first subimage (EXR part) is written. Written atomically.

    Args:
        path: destination; its extension must be the input's (use
            `write_image` to change format).
        color: linear `(H, W, 3)`, the size of `like`.
        like: the input frame, from `read_frame`.
        replace: False: never replace an existing `path`, even one another
            process creates meanwhile (`FileExistsError`).

    Raises:
        ValueError: a different extension than the input, a wrong shape, or
            `like` without its colour channels.
        FileNotFoundError: the destination folder does not exist.
        OSError: OpenImageIO failed to write (nothing is left behind).
    """
    ext = os.path.splitext(os.fspath(path))[1].lower()
    like_ext = os.path.splitext(like.path)[1].lower()
    if ext != like_ext:
        raise ValueError(
            f"write_frame_like keeps the input's format: '{os.fspath(path)}' must end in {like_ext!r} like "
            f"'{like.path}' (use write_image to change format)"
        )
    color = _host_float("color", color, (*like.pixels.shape[:2], 3))
    names = tuple(like.spec.channelnames)
    missing = [n for n in like.color_channels if n not in names]
    if missing:
        raise ValueError(f"'{like.path}' has no {', '.join(missing)} channel to replace; channels: {channels_text(names)}")
    pixels = like.pixels.copy()
    pixels[..., [names.index(n) for n in like.color_channels]] = color
    write_pixels(path, oiio.ImageSpec(like.spec), np.ascontiguousarray(pixels), replace=replace)
