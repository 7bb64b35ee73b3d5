"""Reading and writing frames and images with OpenImageIO.

Frames (`read_buffers` / `write_buffers`) are EXR files, one part, with these
channel names (the ones `write_buffers` writes; `read_buffers` accepts the
alternatives in brackets):

| channels | Buffers field | notes |
|---|---|---|
| `R`, `G`, `B` [`<layer>.R/G/B`] | `color` `(H, W, 3)` | linear HDR; required |
| `A` [`<layer>.A`] | `coverage` `(H, W)` | optional, see "Coverage" below |
| `Z` [`depth.Z`, `depth`, `<view layer>.Depth.Z`, or a name the caller gives] | `depth` `(H, W)` | linear distance along the camera ray, scene units; required |
| `N.X`, `N.Y`, `N.Z` | `normal` `(H, W, 3)` | optional |
| `object_id` | `object_id` `(H, W)` | optional; stored as float32, `-1` on sky |
| `light.Y` [`lightpass`] | `light_pass` `(H, W)` | optional; the galaxy-engine VLS article's pass |
| `glow.R`, `glow.G`, `glow.B`, `glow.A` | `glow_pass` `(H, W, 4)` | optional; the sun-overcasting article's pass |
| `glowtarget.R`, `glowtarget.G`, `glowtarget.B` | `glow_target` `(H, W, 3)` | optional; the VBex article's glow target |

Layers: compositors' files name channels `layer.channel`. Without a
`color_layer`, colour is the plain `R, G, B` when the file has them, else the
one layer with `.R`, `.G`, `.B` channels, preferring a layer named `Combined`
(Blender's multilayer EXR: `ViewLayer.Combined.R/G/B/A`, `ViewLayer.Depth.Z`).
Depth is the first of `Z`, `depth.Z` (Nuke), `depth`, then `<view
layer>.Depth.Z` or `<layer>.Z` beside the colour layer, then the one channel
named `*.Depth.Z` / `*.depth.Z`. Ambiguous files are refused with the
candidates listed; `color_layer` / `depth_channel` choose.

Sky: depth `+inf` means nothing was hit. Renderers write a finite "far" value
instead (Blender 1e10, some `FLT_MAX`), so depth values `>= sky_depth`
(default `SKY_DEPTH`, 1e9) are read as `+inf` too, and in a half-float depth
channel so is its largest value, 65504. A renderer that writes its camera's
far plane needs `sky_depth` set to it. `write_buffers` always writes `+inf`.

Coverage: by default (`coverage="auto"`) coverage is the `A` channel, except
when `A` is exactly 1 on every sky pixel: that alpha is an opaque background
composited in (Mitsuba does this with a constant sky emitter), not coverage,
so coverage then comes from depth (1 where depth is finite, 0 on sky), as it
does when there is no `A` channel. `coverage="alpha"` / `"depth"` force either.

The light: `write_buffers(..., light_xy=...)` stores the light's pixel position
(x right, y down, pixel centres at `i + 0.5`) as the `float2` attribute
`godrays:light_px` and whether it is in front of the camera as the int attribute
`godrays:light_in_front`; `read_light` reads them back (it also accepts an
`"x,y"` or `"x y"` string for `godrays:light_px`).

Images (`write_image` / `read_image`): EXR is written linear, as 32-bit float
(`dtype="float"`, the default) or half (`dtype="half"`). PNG, TIFF and JPEG are
display-encoded: colour channels clipped to [0, 1] and sRGB-encoded, alpha
clipped and left linear, quantised to `bit_depth` 8 (the default) or 16 bits
(JPEG: 8 only, no alpha, quality 95 without chroma subsampling). Channel
counts 1 (written as `Y`), 3 (`R, G, B`) and 4 (`R, G, B, A`). Four-channel images are premultiplied (associated) alpha, as
in EXR; PNG and TIFF are written with straight alpha (colour divided by alpha
before encoding) and `read_image` multiplies it back.

Every write goes to a hidden temporary file next to the destination
(`.name.tmp-XXXXXXXX.ext`) that is renamed over the destination only after the
whole image was written; on any failure the temporary file is removed, so no
partial output is ever left behind.
"""

import dataclasses
import math
import os
import tempfile
from collections.abc import Mapping, Sequence
from typing import Literal

import jax.numpy as jnp
import numpy as np
import OpenImageIO as oiio
from jaxtyping import Array, ArrayLike, Float

from godrays_jax.primitives.buffers import Buffers, coverage_from_depth
from godrays_jax.primitives.color import srgb_decode, srgb_encode
from godrays_jax.primitives.files import atomic_write

SKY_DEPTH = 1e9
"""Depth values at or above this are read as sky (`+inf`) by default: Blender writes 1e10, others inf or FLT_MAX."""

_HALF_MAX = 65504.0

_DEPTH_NAMES = ("Z", "depth.Z", "depth")
_LIGHT_PASS_NAMES = ("light.Y", "lightpass")
_GLOW_NAMES = ("glow.R", "glow.G", "glow.B", "glow.A")
_GLOW_TARGET_NAMES = ("glowtarget.R", "glowtarget.G", "glowtarget.B")
_NORMAL_NAMES = ("N.X", "N.Y", "N.Z")
_OBJECT_ID_NAME = "object_id"
_LIGHT_PX_ATTR = "godrays:light_px"
_LIGHT_IN_FRONT_ATTR = "godrays:light_in_front"
LIGHT_DEPTH_ATTR = "godrays:light_depth"
"""The light's distance from the camera in scene units (a float, `inf` for a light at infinity), as `render` writes it."""

_EXR_EXTENSIONS = (".exr",)
_DISPLAY_EXTENSIONS = (".png", ".tif", ".tiff", ".jpg", ".jpeg")
_JPEG_EXTENSIONS = (".jpg", ".jpeg")
_CHANNEL_NAMES = {1: ("Y",), 3: ("R", "G", "B"), 4: ("R", "G", "B", "A")}


# ----------------------------------------------------------------------------- reading


def _read_pixels(path: str | os.PathLike, *, straight_alpha: bool = False) -> tuple[np.ndarray, oiio.ImageSpec]:
    """All channels of the first subimage as float32 `(H, W, C)`, and its spec.

    `straight_alpha`: return straight-alpha files (PNG, TIFF) as stored instead
    of letting OpenImageIO premultiply them.
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"image file '{path}' does not exist")
    config = oiio.ImageSpec()
    if straight_alpha:
        config.attribute("oiio:UnassociatedAlpha", 1)
    inp = oiio.ImageInput.open(path, config)
    if inp is None:
        raise ValueError(f"cannot read image '{path}': {oiio.geterror()}")
    try:
        spec = inp.spec()
        pixels = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)
        if pixels is None:
            raise ValueError(f"cannot read image '{path}': {inp.geterror()}")
    finally:
        inp.close()
    pixels = np.asarray(pixels, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)
    return pixels, spec


def _channels_text(names: Sequence[str]) -> str:
    return ", ".join(names) if names else "(none)"


def read_buffers(
    path: str | os.PathLike,
    *,
    depth_channel: str | None = None,
    color_layer: str | None = None,
    sky_depth: float = SKY_DEPTH,
    coverage: Literal["auto", "alpha", "depth"] = "auto",
) -> Buffers:
    """Read a frame (colour, depth, coverage and any optional passes).

    Args:
        path: an EXR (or any format OpenImageIO reads) with colour channels,
            a depth channel and optionally alpha and the passes listed in the
            module docstring.
        depth_channel: the depth channel's full name (`ViewLayer.Depth.Z`);
            by default found as the module docstring's "Layers" says.
        color_layer: the colour layer (`ViewLayer.Combined`: channels
            `ViewLayer.Combined.R/G/B`, alpha `.A`); by default the plain
            `R, G, B`, else the one layer that has them.
        sky_depth: depth values at or above this (scene units, > 0) are sky,
            `+inf`; default `SKY_DEPTH` (1e9).
        coverage: where coverage comes from: `"alpha"` (the colour layer's
            alpha), `"depth"` (1 where depth is finite, 0 on sky) or `"auto"`
            (alpha unless it is missing or 1 on every sky pixel; module docstring).

    Returns:
        `Buffers` with float32 colour `(H, W, 3)` (linear, as stored), depth
        `(H, W)` in scene units with `+inf` on sky, coverage `(H, W)`.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the file is not a readable image, has no colour or depth
            channels or several candidates for them (the message lists the
            channels found), holds invalid values (see `check_buffers`), or
            `sky_depth` is not a positive number.
    """
    if coverage not in ("auto", "alpha", "depth"):
        raise ValueError(f"coverage must be 'auto', 'alpha' or 'depth', got {coverage!r}")
    pixels, spec = _read_pixels(path)
    return _decode_buffers(
        path, pixels, spec, depth_channel=depth_channel, color_layer=color_layer, sky_depth=sky_depth, coverage=coverage
    )[0]


def _color_names(path, names: Sequence[str], color_layer: str | None) -> tuple[str, ...]:
    """The colour channels' names, `(R, G, B, A)` or `(R, G, B)` of the chosen layer."""
    found = set(names)
    layers = [name[: -len(".R")] for name in names if name.endswith(".R")]
    layers = [layer for layer in layers if {f"{layer}.G", f"{layer}.B"} <= found]
    if color_layer is not None:
        prefix = color_layer.rstrip(".")
        chosen = [prefix] if (prefix and prefix in layers) or (not prefix and {"R", "G", "B"} <= found) else []
        if not chosen:
            raise ValueError(
                f"image '{os.fspath(path)}' has no colour layer {color_layer!r} (no {prefix + '.' if prefix else ''}R, "
                f"G, B); colour layers found: {_channels_text(layers + (['(plain R, G, B)'] if {'R', 'G', 'B'} <= found else []))}"
            )
    elif {"R", "G", "B"} <= found:
        chosen = [""]
    else:
        combined = [layer for layer in layers if layer.rsplit(".", 1)[-1].lower() == "combined"]
        chosen = combined if len(combined) == 1 else layers
        if not chosen:
            missing = [c for c in "RGB" if c not in found]
            raise ValueError(
                f"image '{os.fspath(path)}' has no {', '.join(missing)} colour channel (R, G, B or a layer's "
                f".R, .G, .B are required); channels found: {_channels_text(names)}"
            )
        if len(chosen) > 1:
            raise ValueError(
                f"image '{os.fspath(path)}' has several colour layers ({', '.join(chosen)}): choose one with "
                f"--color-layer (color_layer); channels found: {_channels_text(names)}"
            )
    dot = f"{chosen[0]}." if chosen[0] else ""
    rgb = tuple(f"{dot}{c}" for c in "RGB")
    return rgb + ((f"{dot}A",) if f"{dot}A" in found else ())


def _depth_name(path, names: Sequence[str], depth_channel: str | None, color: Sequence[str]) -> str:
    """The depth channel's name: the caller's, a conventional one, or the one beside the colour layer."""
    if depth_channel is not None:
        if depth_channel not in names:
            raise ValueError(
                f"image '{os.fspath(path)}' has no depth channel (looked for {depth_channel}); "
                f"channels found: {_channels_text(names)}"
            )
        return depth_channel
    layer = color[0][: -len(".R")] if "." in color[0] else ""
    view_layer = layer.rsplit(".", 1)[0] if "." in layer else ""
    beside = (f"{view_layer}.Depth.Z", f"{view_layer}.depth.Z") if view_layer else ()
    beside += (f"{layer}.Z",) if layer else ()
    for name in (*_DEPTH_NAMES, *beside):
        if name in names:
            return name
    layered = [name for name in names if name.endswith((".Depth.Z", ".depth.Z"))]
    if len(layered) == 1:
        return layered[0]
    if layered:
        raise ValueError(
            f"image '{os.fspath(path)}' has several depth channels ({', '.join(layered)}): choose one with "
            f"--depth-channel (depth_channel); channels found: {_channels_text(names)}"
        )
    looked = ", ".join((*_DEPTH_NAMES, *beside, "*.Depth.Z"))
    raise ValueError(
        f"image '{os.fspath(path)}' has no depth channel (looked for {looked}); channels found: "
        f"{_channels_text(names)} (--depth-channel names another)"
    )


def _decode_buffers(
    path, pixels: np.ndarray, spec: oiio.ImageSpec, *, depth_channel, color_layer, sky_depth, coverage
) -> tuple[Buffers, tuple[str, ...]]:
    """`read_buffers` after the file was read: pick the channels, build and check the `Buffers`.

    Also returns the colour channels' names (`R, G, B` of the layer read).
    """
    if not (isinstance(sky_depth, int | float) and sky_depth > 0):  # NaN fails too
        raise ValueError(f"sky_depth must be a positive number of scene units, got {sky_depth!r}")
    names = tuple(spec.channelnames)
    index = {name: i for i, name in enumerate(names)}

    def channels(wanted: Sequence[str]) -> np.ndarray:
        return pixels[..., [index[n] for n in wanted]]

    color_names = _color_names(path, names, color_layer)
    depth_name = _depth_name(path, names, depth_channel, color_names)
    depth = pixels[..., index[depth_name]].copy()
    if spec.channelformat(index[depth_name]) == oiio.TypeHalf:
        sky_depth = min(sky_depth, _HALF_MAX)  # a half channel holds no larger distance: its maximum is "far"
    depth[depth >= sky_depth] = np.inf

    sky = np.isposinf(depth)
    alpha = pixels[..., index[color_names[3]]] if len(color_names) == 4 else None
    if coverage == "alpha" and alpha is None:
        raise ValueError(
            f"image '{os.fspath(path)}' has no A channel for coverage='alpha'; "
            f"channels found: {_channels_text(names)}"
        )
    use_alpha = alpha is not None and (
        coverage == "alpha" or (coverage == "auto" and not (sky.any() and np.all(alpha[sky] == 1.0)))
    )

    def optional(wanted: Sequence[str]) -> np.ndarray | None:
        return channels(wanted) if all(n in index for n in wanted) else None

    light_names = [n for n in _LIGHT_PASS_NAMES if n in index]
    object_id = optional((_OBJECT_ID_NAME,))
    buffers = Buffers(
        color=jnp.asarray(channels(color_names[:3])),
        depth=jnp.asarray(depth),
        coverage=jnp.asarray(alpha) if use_alpha else coverage_from_depth(jnp.asarray(depth)),
        normal=None if (n := optional(_NORMAL_NAMES)) is None else jnp.asarray(n),
        object_id=None if object_id is None else jnp.asarray(np.rint(object_id[..., 0]).astype(np.int32)),
        light_pass=jnp.asarray(pixels[..., index[light_names[0]]]) if light_names else None,
        glow_pass=None if (g := optional(_GLOW_NAMES)) is None else jnp.asarray(g),
        glow_target=None if (t := optional(_GLOW_TARGET_NAMES)) is None else jnp.asarray(t),
    )
    check_buffers(buffers, name=os.fspath(path))
    return buffers, color_names[:3]


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
    depth = np.asarray(buffers.depth)
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


def _parse_light_px(value: object, path: str) -> tuple[float, float]:
    if isinstance(value, str):
        parts = value.replace(",", " ").split()
    else:
        parts = list(value) if isinstance(value, Sequence) else [value]
    try:
        x, y = (float(p) for p in parts)
    except (TypeError, ValueError):
        raise ValueError(
            f"image '{path}': attribute {_LIGHT_PX_ATTR} must be two numbers, got {value!r}"
        ) from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise ValueError(f"image '{path}': attribute {_LIGHT_PX_ATTR} must be finite, got ({x}, {y})")
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
    if not os.path.exists(path):
        raise FileNotFoundError(f"image file '{path}' does not exist")
    inp = oiio.ImageInput.open(path)
    if inp is None:
        raise ValueError(f"cannot read image '{path}': {oiio.geterror()}")
    try:
        spec = inp.spec()
    finally:
        inp.close()
    value = spec.getattribute(_LIGHT_PX_ATTR)
    if value is None:
        return None
    in_front = spec.getattribute(_LIGHT_IN_FRONT_ATTR)
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
    if not os.path.exists(path):
        raise FileNotFoundError(f"image file '{path}' does not exist")
    inp = oiio.ImageInput.open(path)
    if inp is None:
        raise ValueError(f"cannot read image '{path}': {oiio.geterror()}")
    try:
        value = inp.spec().getattribute(LIGHT_DEPTH_ATTR)
    finally:
        inp.close()
    if value is None:
        return None
    try:
        depth = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"image '{path}': attribute {LIGHT_DEPTH_ATTR} must be a number, got {value!r}") from None
    if math.isnan(depth) or depth < 0:
        raise ValueError(f"image '{path}': attribute {LIGHT_DEPTH_ATTR} must be >= 0, got {depth}")
    return depth


def read_image(path: str | os.PathLike) -> Float[Array, "H W C"]:
    """Read any image as float32 linear `(H, W, C)`, all channels in file order.

    Float files (EXR, float TIFF) are returned as stored. Integer files (8/16-bit
    PNG, TIFF, JPEG) are taken as display-encoded: mapped to [0, 1], colour
    channels sRGB-decoded to linear, an alpha channel (`A`) left as is, so
    `read_image` inverts `write_image` up to quantisation.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the file is not a readable image.
    """
    pixels, spec = _read_pixels(path, straight_alpha=True)
    if spec.format.basetype not in (oiio.FLOAT, oiio.HALF, oiio.DOUBLE):
        names = tuple(spec.channelnames)
        colour = np.array([name != "A" for name in names])
        pixels = np.where(colour, srgb_decode(pixels), pixels)
        if "A" in names:
            pixels = np.where(colour, pixels * pixels[..., names.index("A"), None], pixels)
    return jnp.asarray(pixels.astype(np.float32))


# ----------------------------------------------------------------------------- writing


def _set_attribute(spec: oiio.ImageSpec, name: str, value: object) -> None:
    if isinstance(value, bool | int | np.integer):
        spec.attribute(name, oiio.TypeInt, int(value))
    elif isinstance(value, float | np.floating):
        spec.attribute(name, oiio.TypeFloat, float(value))
    elif isinstance(value, str):
        spec.attribute(name, oiio.TypeString, value)
    elif isinstance(value, Sequence | np.ndarray) and len(value) > 0:
        floats = tuple(float(v) for v in value)
        spec.attribute(name, oiio.TypeDesc(f"float[{len(floats)}]"), floats)
    else:
        raise ValueError(
            f"metadata {name!r}: value must be a str, int, float or a sequence of numbers, "
            f"got {type(value).__name__}"
        )


def _write_image_file(
    path: str | os.PathLike, spec: oiio.ImageSpec, pixels: np.ndarray, *, replace: bool = True, sync: bool = True
) -> None:
    """Write `pixels` with `spec` to `path`, whole or not at all (`atomic_write`)."""
    path = os.fspath(path)
    with atomic_write(path, replace=replace, sync=sync) as temporary:
        out = oiio.ImageOutput.create(temporary)
        if out is None:
            raise OSError(f"cannot write image '{path}': {oiio.geterror()}")
        try:
            if not out.open(temporary, spec) or not out.write_image(pixels):
                raise OSError(f"cannot write image '{path}': {out.geterror()}")
        finally:
            closed = out.close()
        if not closed:
            raise OSError(f"cannot write image '{path}': {out.geterror()}")


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

    Channels (module docstring): `R, G, B, A` (coverage), `Z` (depth, `+inf`
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
    if os.path.splitext(os.fspath(path))[1].lower() not in _EXR_EXTENSIONS:
        raise ValueError(f"cannot write buffers to '{os.fspath(path)}': the file must end in .exr")
    color = np.asarray(buffers.color, dtype=np.float32)
    if color.ndim != 3 or color.shape[-1] != 3:
        raise ValueError(f"buffers.color must have shape (H, W, 3) to write, got {color.shape}")
    hw = color.shape[:2]
    names = ["R", "G", "B", "A", "Z"]
    planes = [color, _host_float("buffers.coverage", buffers.coverage, hw)[..., None],
              _host_float("buffers.depth", buffers.depth, hw)[..., None]]
    if buffers.normal is not None:
        names += _NORMAL_NAMES
        planes.append(_host_float("buffers.normal", buffers.normal, (*hw, 3)))
    if buffers.object_id is not None:
        names.append(_OBJECT_ID_NAME)
        planes.append(_host_float("buffers.object_id", buffers.object_id, hw)[..., None])
    if buffers.light_pass is not None:
        names.append(_LIGHT_PASS_NAMES[0])
        planes.append(_host_float("buffers.light_pass", buffers.light_pass, hw)[..., None])
    if buffers.glow_pass is not None:
        names += _GLOW_NAMES
        planes.append(_host_float("buffers.glow_pass", buffers.glow_pass, (*hw, 4)))
    if buffers.glow_target is not None:
        names += _GLOW_TARGET_NAMES
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
        _set_attribute(spec, key, value)
    if light_xy is not None:
        x, y = light_xy
        spec.attribute(_LIGHT_PX_ATTR, oiio.TypeFloat2, (float(x), float(y)))
        spec.attribute(_LIGHT_IN_FRONT_ATTR, oiio.TypeInt, int(bool(light_in_front)))
    _write_image_file(path, spec, pixels)


def write_image(
    path: str | os.PathLike,
    image: Float[ArrayLike, "H W C"] | Float[ArrayLike, "H W"],
    *,
    dtype: Literal["float", "half"] | None = None,
    bit_depth: Literal[8, 16] | None = None,
    metadata: Mapping[str, object] | None = None,
    replace: bool = True,
) -> None:
    """Write a linear image; the format follows the extension.

    Args:
        path: destination ending in `.exr`, `.png`, `.tif`/`.tiff` or
            `.jpg`/`.jpeg`; written atomically.
        image: linear float `(H, W, C)` with C = 1, 3 or 4 (channels `Y`,
            `R G B`, `R G B A`), or `(H, W)` for one channel.
        dtype: EXR only: `"float"` (32-bit, the default) or `"half"`.
            Values are written as they are, unclipped.
        bit_depth: PNG/TIFF/JPEG only: 8 (the default) or 16 (not JPEG).
            Colour is clipped to [0, 1] and sRGB-encoded, alpha clipped and
            kept linear, then rounded to the nearest code.
        metadata: header attributes, `name -> str | int | float | sequence of
            numbers` (formats other than EXR may keep only some).
        replace: False: never replace an existing `path`, even one another
            process creates meanwhile (`FileExistsError`).

    Raises:
        ValueError: an unknown extension, a wrong shape or channel count, an
            option that does not fit the format, or an unsupported metadata value.
        FileNotFoundError: the destination folder does not exist.
        OSError: OpenImageIO failed to write (nothing is left behind).
    """
    ext = os.path.splitext(os.fspath(path))[1].lower()
    pixels = np.asarray(image, dtype=np.float32)
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    if pixels.ndim != 3 or pixels.shape[-1] not in _CHANNEL_NAMES:
        raise ValueError(f"image must have shape (H, W) or (H, W, C) with C = 1, 3 or 4, got {pixels.shape}")
    channels = pixels.shape[-1]
    if ext in _EXR_EXTENSIONS:
        if bit_depth is not None:
            raise ValueError(f"bit_depth does not apply to EXR ('{os.fspath(path)}'); use dtype='float' or 'half'")
        if dtype not in (None, "float", "half"):
            raise ValueError(f"dtype must be 'float' or 'half', got {dtype!r}")
        fmt = oiio.HALF if dtype == "half" else oiio.FLOAT
    elif ext in _DISPLAY_EXTENSIONS:
        if dtype is not None:
            raise ValueError(f"dtype applies to EXR only; use bit_depth=8 or 16 for '{os.fspath(path)}'")
        bits = 8 if bit_depth is None else bit_depth
        if bits not in (8, 16) or (bits == 16 and ext in _JPEG_EXTENSIONS):
            allowed = "8" if ext in _JPEG_EXTENSIONS else "8 or 16"
            raise ValueError(f"bit_depth for '{os.fspath(path)}' must be {allowed}, got {bit_depth!r}")
        if channels == 4 and ext in _JPEG_EXTENSIONS:
            raise ValueError(f"JPEG has no alpha channel: cannot write 4 channels to '{os.fspath(path)}'")
        fmt = oiio.UINT8 if bits == 8 else oiio.UINT16
        if channels == 4:
            alpha = np.clip(pixels[..., 3:], 0.0, 1.0)
            straight = np.where(alpha > 0, pixels[..., :3] / np.where(alpha > 0, alpha, 1.0), 0.0)
            encoded = np.concatenate([srgb_encode(straight), alpha], axis=-1)
        else:
            encoded = srgb_encode(pixels)
        scale = 2**bits - 1
        pixels = np.rint(encoded * scale).astype(np.uint8 if bits == 8 else np.uint16)
    else:
        raise ValueError(
            f"cannot write image '{os.fspath(path)}': unknown extension {ext or '(none)'!r} "
            f"(use .exr, .png, .tif, .tiff, .jpg or .jpeg)"
        )
    spec = oiio.ImageSpec(pixels.shape[1], pixels.shape[0], channels, fmt)
    spec.channelnames = _CHANNEL_NAMES[channels]
    if channels == 4:
        spec.alpha_channel = 3
    if ext in _EXR_EXTENSIONS:
        spec.attribute("compression", "zip")
    else:
        spec.attribute("oiio:ColorSpace", "sRGB")
        spec.attribute("oiio:UnassociatedAlpha", 1)  # the pixels already hold straight alpha
    if ext in _JPEG_EXTENSIONS:
        spec.attribute("Compression", "jpeg:95")
        spec.attribute("jpeg:subsampling", "4:4:4")  # full-resolution colour
    for key, value in (metadata or {}).items():
        _set_attribute(spec, key, value)
    _write_image_file(path, spec, np.ascontiguousarray(pixels), replace=replace)


# ----------------------------------------------------------------------------- frames kept as stored


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


def read_frame(
    path: str | os.PathLike,
    *,
    depth_channel: str | None = None,
    color_layer: str | None = None,
    sky_depth: float = SKY_DEPTH,
    coverage: Literal["auto", "alpha", "depth"] = "auto",
) -> tuple[Buffers, FrameFile]:
    """`read_buffers` that also returns the file as stored, reading it once.

    Returns:
        `(buffers, frame_file)`: the `Buffers` exactly as `read_buffers` gives
        them, and the `FrameFile` to pass to `write_frame_like`.

    Raises:
        As `read_buffers`.
    """
    if coverage not in ("auto", "alpha", "depth"):
        raise ValueError(f"coverage must be 'auto', 'alpha' or 'depth', got {coverage!r}")
    pixels, spec = _read_pixels(path)
    buffers, color_channels = _decode_buffers(
        path, pixels, spec, depth_channel=depth_channel, color_layer=color_layer, sky_depth=sky_depth, coverage=coverage
    )
    return buffers, FrameFile(path=os.fspath(path), pixels=pixels, spec=spec, color_channels=color_channels)


def write_frame_like(
    path: str | os.PathLike, color: Float[ArrayLike, "H W 3"], like: FrameFile, *, replace: bool = True
) -> None:
    """Write `color` in place of the colour channels of `like` (`like.color_channels`), keeping everything else.

    Every other channel (alpha, depth, passes, anything the renderer wrote),
    each channel's storage format (half stays half: values above 65504 become
    `+inf` there), the compression, tiling and every metadata attribute are
    copied from `like.spec`, so the output reads back like the input with new
    colour. Only the first subimage (EXR part) is written. Atomic, as every
    write in this module.

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
        raise ValueError(f"'{like.path}' has no {', '.join(missing)} channel to replace; channels: {_channels_text(names)}")
    pixels = like.pixels.copy()
    pixels[..., [names.index(n) for n in like.color_channels]] = color
    _write_image_file(path, oiio.ImageSpec(like.spec), np.ascontiguousarray(pixels), replace=replace)


def encode_png(pixels: np.ndarray, *, compression: int = 1) -> bytes:
    """An 8-bit RGB `(H, W, 3)` array as PNG bytes, through OpenImageIO.

    `compression` is zlib's level, 0-9: the tuner's frames change with every
    request, so its default favours speed.
    """
    pixels = np.ascontiguousarray(pixels)
    if pixels.dtype != np.uint8 or pixels.ndim != 3 or pixels.shape[-1] != 3:
        raise ValueError(f"pixels must be uint8 of shape (H, W, 3), got {pixels.dtype} {pixels.shape}")
    height, width, _ = pixels.shape
    spec = oiio.ImageSpec(width, height, 3, oiio.UINT8)
    spec.attribute("png:compressionLevel", int(compression))
    with tempfile.TemporaryDirectory(prefix="godrays-png-") as folder:
        path = os.path.join(folder, "frame.png")
        _write_image_file(path, spec, pixels, sync=False)  # a throwaway file: no need to wait for the disk
        with open(path, "rb") as stream:
            return stream.read()
