"""Channel layouts of frame files: plain, Nuke and Blender multilayer names, and finding colour and depth among them."""

import os
from collections.abc import Sequence

DEPTH_NAMES = ("Z", "depth.Z", "depth")
"""Depth channels looked for first, in this order."""
LIGHT_PASS_NAMES = ("light.Y", "lightpass")
GLOW_NAMES = ("glow.R", "glow.G", "glow.B", "glow.A")
GLOW_TARGET_NAMES = ("glowtarget.R", "glowtarget.G", "glowtarget.B")
NORMAL_NAMES = ("N.X", "N.Y", "N.Z")
OBJECT_ID_NAME = "object_id"
"""The optional passes' channels, as `write_buffers` writes them (the light pass's first name) and `read_buffers` reads them."""


def channels_text(names: Sequence[str]) -> str:
    return ", ".join(names) if names else "(none)"


def color_channel_names(path, names: Sequence[str], color_layer: str | None) -> tuple[str, ...]:
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
                f"G, B); colour layers found: {channels_text(layers + (['(plain R, G, B)'] if {'R', 'G', 'B'} <= found else []))}"
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
                f".R, .G, .B are required); channels found: {channels_text(names)}"
            )
        if len(chosen) > 1:
            raise ValueError(
                f"image '{os.fspath(path)}' has several colour layers ({', '.join(chosen)}): choose one with "
                f"--color-layer (color_layer); channels found: {channels_text(names)}"
            )
    dot = f"{chosen[0]}." if chosen[0] else ""
    rgb = tuple(f"{dot}{c}" for c in "RGB")
    return rgb + ((f"{dot}A",) if f"{dot}A" in found else ())


def depth_channel_name(
    path, names: Sequence[str], depth_channel: str | None, color: Sequence[str], *, required: bool = True
) -> str | None:
    """The depth channel's name: the caller's, a conventional one, or the one beside the colour layer.

    None when the file has no depth channel and none is `required` (a frame without depth).
    """
    if depth_channel is not None:
        if depth_channel not in names:
            raise ValueError(
                f"image '{os.fspath(path)}' has no depth channel (looked for {depth_channel}); "
                f"channels found: {channels_text(names)}"
            )
        return depth_channel
    layer = color[0][: -len(".R")] if "." in color[0] else ""
    view_layer = layer.rsplit(".", 1)[0] if "." in layer else ""
    beside = (f"{view_layer}.Depth.Z", f"{view_layer}.depth.Z") if view_layer else ()
    beside += (f"{layer}.Z",) if layer else ()
    for name in (*DEPTH_NAMES, *beside):
        if name in names:
            return name
    layered = [name for name in names if name.endswith((".Depth.Z", ".depth.Z"))]
    if len(layered) == 1:
        return layered[0]
    if layered:
        raise ValueError(
            f"image '{os.fspath(path)}' has several depth channels ({', '.join(layered)}): choose one with "
            f"--depth-channel (depth_channel); channels found: {channels_text(names)}"
        )
    if not required:
        return None
    looked = ", ".join((*DEPTH_NAMES, *beside, "*.Depth.Z"))
    raise ValueError(
        f"image '{os.fspath(path)}' has no depth channel (looked for {looked}); channels found: "
        f"{channels_text(names)} (--depth-channel names another)"
    )
