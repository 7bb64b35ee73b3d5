"""Frames read into `Buffers`: choosing the channels, the sky threshold, coverage, and the checks every frame passes."""

import os
from collections.abc import Sequence
from typing import Literal

import jax.numpy as jnp
import numpy as np
import OpenImageIO as oiio
from jaxtyping import ArrayLike

from godrays_jax.primitives.buffers import Buffers, coverage_from_depth
from godrays_jax.primitives.camera import DEPTH_KINDS, planar_to_ray_depth
from godrays_jax.primitives.camera_metadata import camera_from_header
from godrays_jax.primitives.channels import (
    GLOW_NAMES,
    GLOW_TARGET_NAMES,
    LIGHT_PASS_NAMES,
    NORMAL_NAMES,
    OBJECT_ID_NAME,
    channels_text,
    color_channel_names,
    depth_channel_name,
)
from godrays_jax.primitives.color import srgb_decode
from godrays_jax.primitives.image_files import read_pixels

SKY_DEPTH = 1e9
"""Depth values at or above this are read as sky (`+inf`) by default: Blender writes 1e10, others inf or FLT_MAX."""

_HALF_MAX = 65504.0

DepthKindOption = Literal["auto", "ray", "planar"]


def reads_straight_alpha(path: str | os.PathLike) -> bool:
    """PNG and JPEG store straight alpha and display-encoded colour: read as stored, premultiplied after decoding."""
    return os.path.splitext(os.fspath(path))[1].lower() in (".png", ".jpg", ".jpeg")


def read_buffers(
    path: str | os.PathLike,
    *,
    depth_channel: str | None = None,
    color_layer: str | None = None,
    sky_depth: float = SKY_DEPTH,
    coverage: Literal["auto", "alpha", "depth"] = "auto",
    depth_kind: DepthKindOption = "auto",
    fov_x_deg: float | None = None,
    without_depth: bool = False,
) -> Buffers:
    """Read a frame (colour, depth, coverage and any optional passes).

    Args:
        path: an EXR (or any format OpenImageIO reads) with colour channels,
            a depth channel and optionally alpha and the passes listed in
            docs/file_formats.md.
        depth_channel: the depth channel's full name (`ViewLayer.Depth.Z`);
            by default found as docs/file_formats.md ("Layers") says.
        color_layer: the colour layer (`ViewLayer.Combined`: channels
            `ViewLayer.Combined.R/G/B`, alpha `.A`); by default the plain
            `R, G, B`, else the one layer that has them.
        sky_depth: depth values at or above this (scene units, > 0) are sky,
            `+inf`; default `SKY_DEPTH` (1e9).
        coverage: where coverage comes from: `"alpha"` (the colour layer's
            alpha), `"depth"` (1 where depth is finite, 0 on sky) or `"auto"`
            (alpha unless it is missing or 1 on every sky pixel; docs/file_formats.md).
        depth_kind: how the depth channel measures distance: `"ray"` (along
            each camera ray), `"planar"` (along the camera's axis), or
            `"auto"`: planar for Blender's files, else ray
            (`camera_metadata`).
        fov_x_deg: the camera's horizontal field of view in degrees; by
            default the one the header carries (`camera_metadata`). Planar
            depth is converted to ray depth with it; without one it stays
            planar (`Buffers.depth_kind`) and effects convert it with their own.
        without_depth: read a file without a depth channel (a photograph, a
            plate; PNG, JPEG and TIFF are sRGB-decoded) as a frame without
            depth: `depth` None, coverage its alpha or 1 (see
            `plates.buffers_without_depth` for its open sky).

    Returns:
        `Buffers` with float32 colour `(H, W, 3)` (linear, as stored), depth
        `(H, W)` in scene units with `+inf` on sky (distance along the ray,
        or `depth_kind="planar"` when no field of view was known), coverage `(H, W)`.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the file is not a readable image, has no colour or depth
            channels or several candidates for them (the message lists the
            channels found), holds invalid values (see `check_buffers`), or
            `sky_depth` is not a positive number.
    """
    pixels, spec = read_pixels(path, straight_alpha=reads_straight_alpha(path))
    return decode_buffers(
        path, pixels, spec, depth_channel=depth_channel, color_layer=color_layer, sky_depth=sky_depth, coverage=coverage,
        depth_kind=depth_kind, fov_x_deg=fov_x_deg, without_depth=without_depth,
    )[0]  # fmt: skip

def _display_decoded(path, pixels: np.ndarray, spec: oiio.ImageSpec, color_names: Sequence[str]) -> np.ndarray:
    """An integer (display-encoded) file's pixels as linear premultiplied values, as `read_image` reads them."""
    if spec.format.basetype in (oiio.FLOAT, oiio.HALF, oiio.DOUBLE):
        return pixels
    names = tuple(spec.channelnames)
    colour = np.array([name in color_names[:3] for name in names])
    decoded = np.where(colour, srgb_decode(pixels), pixels)
    if len(color_names) == 4 and reads_straight_alpha(path):
        decoded = np.where(colour, decoded * pixels[..., names.index(color_names[3]), None], decoded)
    return decoded.astype(np.float32)


def decode_buffers(
    path,
    pixels: np.ndarray,
    spec: oiio.ImageSpec,
    *,
    depth_channel: str | None = None,
    color_layer: str | None = None,
    sky_depth: float = SKY_DEPTH,
    coverage: Literal["auto", "alpha", "depth"] = "auto",
    depth_kind: DepthKindOption = "auto",
    fov_x_deg: float | None = None,
    without_depth: bool = False,
) -> tuple[Buffers, tuple[str, ...]]:
    """`read_buffers` after the file was read: pick the channels, build and check the `Buffers`.

    Also returns the colour channels' names (`R, G, B` of the layer read).
    """
    if coverage not in ("auto", "alpha", "depth"):
        raise ValueError(f"coverage must be 'auto', 'alpha' or 'depth', got {coverage!r}")
    if depth_kind not in ("auto", *DEPTH_KINDS):
        raise ValueError(f"depth_kind must be 'auto', 'ray' or 'planar', got {depth_kind!r}")
    if fov_x_deg is not None and not (isinstance(fov_x_deg, int | float) and 0 < fov_x_deg < 180):
        raise ValueError(f"fov_x_deg must be a number of degrees in (0, 180), got {fov_x_deg!r}")
    if not (isinstance(sky_depth, int | float) and sky_depth > 0):  # NaN fails too
        raise ValueError(f"sky_depth must be a positive number of scene units, got {sky_depth!r}")
    names = tuple(spec.channelnames)
    index = {name: i for i, name in enumerate(names)}

    def channels(wanted: Sequence[str]) -> np.ndarray:
        return pixels[..., [index[n] for n in wanted]]

    color_names = color_channel_names(path, names, color_layer)
    depth_name = depth_channel_name(path, names, depth_channel, color_names, required=not without_depth)
    if depth_name is None:
        return _without_depth(path, _display_decoded(path, pixels, spec, color_names), names, color_names), color_names[:3]
    header = camera_from_header(spec)
    kind = header.depth_kind if depth_kind == "auto" else depth_kind
    fov = header.fov_x_deg if fov_x_deg is None else fov_x_deg
    depth = pixels[..., index[depth_name]].copy()
    if spec.channelformat(index[depth_name]) == oiio.TypeHalf:
        sky_depth = min(sky_depth, _HALF_MAX)  # a half channel holds no larger distance: its maximum is "far"
    depth[depth >= sky_depth] = np.inf
    if kind == "planar" and fov is not None:
        depth = np.asarray(planar_to_ray_depth(depth, fov_x_deg=fov), np.float32)
        kind = "ray"

    sky = np.isposinf(depth)
    alpha = pixels[..., index[color_names[3]]] if len(color_names) == 4 else None
    if coverage == "alpha" and alpha is None:
        raise ValueError(
            f"image '{os.fspath(path)}' has no A channel for coverage='alpha'; "
            f"channels found: {channels_text(names)}"
        )
    use_alpha = alpha is not None and (
        coverage == "alpha" or (coverage == "auto" and not (sky.any() and np.all(alpha[sky] == 1.0)))
    )

    def optional(wanted: Sequence[str]) -> np.ndarray | None:
        return channels(wanted) if all(n in index for n in wanted) else None

    light_names = [n for n in LIGHT_PASS_NAMES if n in index]
    object_id = optional((OBJECT_ID_NAME,))
    buffers = Buffers(
        color=jnp.asarray(channels(color_names[:3])),
        depth=jnp.asarray(depth),
        coverage=jnp.asarray(alpha) if use_alpha else coverage_from_depth(jnp.asarray(depth)),
        normal=None if (n := optional(NORMAL_NAMES)) is None else jnp.asarray(n),
        object_id=None if object_id is None else jnp.asarray(np.rint(object_id[..., 0]).astype(np.int32)),
        light_pass=jnp.asarray(pixels[..., index[light_names[0]]]) if light_names else None,
        glow_pass=None if (g := optional(GLOW_NAMES)) is None else jnp.asarray(g),
        glow_target=None if (t := optional(GLOW_TARGET_NAMES)) is None else jnp.asarray(t),
        depth_kind=kind,
    )
    check_buffers(buffers, name=os.fspath(path))
    return buffers, color_names[:3]


def _without_depth(path, pixels: np.ndarray, names: Sequence[str], color_names: Sequence[str]) -> Buffers:
    """A frame without depth: colour, and its alpha as coverage (1 without alpha)."""
    index = {name: i for i, name in enumerate(names)}
    color = pixels[..., [index[n] for n in color_names[:3]]]
    alpha = pixels[..., index[color_names[3]]] if len(color_names) == 4 else np.ones(color.shape[:2], np.float32)
    buffers = Buffers(color=jnp.asarray(color), depth=None, coverage=jnp.asarray(np.clip(alpha, 0.0, 1.0)))
    check_buffers(buffers, name=os.fspath(path))
    return buffers


def _count_message(count: int, what: str) -> str:
    return f"{count} pixel{'s' if count != 1 else ''} {what}"


def check_buffers(buffers: Buffers, *, name: str) -> None:
    """Raise `ValueError` if a frame holds values no effect can use.

    Checks on the host with NumPy (input validation, not traced): colour has no
    NaN or +-inf; depth has no NaN and nothing negative (`+inf` is sky);
    coverage has no NaN and lies in [0, 1]; the optional float passes have no
    NaN or +-inf. Each message names `name` (a file name or label), the
    buffer, and how many pixels are bad.
    """
    problems = []

    def nonfinite(label: str, array: ArrayLike | None) -> None:
        if array is None:
            return
        a = np.asarray(array)
        bad = ~np.isfinite(a)
        if a.ndim == 3:
            bad = bad.any(axis=-1)
        if (count := int(bad.sum())) > 0:
            problems.append(f"{label} has {_count_message(count, 'with NaN or infinite values')}")

    nonfinite("color", buffers.color)
    depth = np.zeros(0) if buffers.depth is None else np.asarray(buffers.depth)
    if (count := int(np.isnan(depth).sum())) > 0:
        problems.append(f"depth has {_count_message(count, 'with NaN')}")
    if (count := int((depth < 0).sum())) > 0:
        problems.append(f"depth has {_count_message(count, 'with negative values')}")
    cov = np.asarray(buffers.coverage)
    if (count := int(np.isnan(cov).sum())) > 0:
        problems.append(f"coverage has {_count_message(count, 'with NaN')}")
    if (count := int(((cov < 0) | (cov > 1)).sum())) > 0:
        problems.append(f"coverage has {_count_message(count, 'outside [0, 1]')}")
    nonfinite("normal", buffers.normal)
    nonfinite("light_pass", buffers.light_pass)
    nonfinite("glow_pass", buffers.glow_pass)
    if problems:
        raise ValueError(f"invalid buffers in '{name}': " + "; ".join(problems))

