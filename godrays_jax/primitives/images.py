"""Images read and written linear, display formats sRGB-encoded, and PNG bytes for the tuner."""

import os
import tempfile
from collections.abc import Mapping
from typing import Literal

import jax.numpy as jnp
import numpy as np
import OpenImageIO as oiio
from jaxtyping import Array, ArrayLike, Float

from godrays_jax.primitives.color import quantize, srgb_decode, srgb_encode
from godrays_jax.primitives.image_files import EXR_EXTENSIONS, read_pixels, set_attribute, write_pixels

_DISPLAY_EXTENSIONS = (".png", ".tif", ".tiff", ".jpg", ".jpeg")
_JPEG_EXTENSIONS = (".jpg", ".jpeg")
_CHANNEL_NAMES = {1: ("Y",), 3: ("R", "G", "B"), 4: ("R", "G", "B", "A")}


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
    pixels, spec = read_pixels(path, straight_alpha=True)
    if spec.format.basetype not in (oiio.FLOAT, oiio.HALF, oiio.DOUBLE):
        names = tuple(spec.channelnames)
        colour = np.array([name != "A" for name in names])
        pixels = np.where(colour, srgb_decode(pixels), pixels)
        if "A" in names:
            pixels = np.where(colour, pixels * pixels[..., names.index("A"), None], pixels)
    return jnp.asarray(pixels.astype(np.float32))


def write_image(
    path: str | os.PathLike,
    image: Float[ArrayLike, "H W C"] | Float[ArrayLike, "H W"],
    *,
    dtype: Literal["float", "half"] | None = None,
    bit_depth: Literal[8, 16] | None = None,
    metadata: Mapping[str, object] | None = None,
    replace: bool = True,
    dither_seed: int | None = None,
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
        dither_seed: 8-bit PNG/TIFF/JPEG only: add triangular noise of one
            code to the colour before rounding (`color.quantize`), drawn from
            this seed, so smooth gradients do not band; None (the default)
            rounds; EXR and 16-bit files ignore it. `apply` and `batch` pass
            one per frame (`dither_seed_of`).

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
    if ext in EXR_EXTENSIONS:
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
        colour_seed = dither_seed if bits == 8 else None
        if channels == 4:
            alpha = np.clip(pixels[..., 3:], 0.0, 1.0)
            straight = np.where(alpha > 0, pixels[..., :3] / np.where(alpha > 0, alpha, 1.0), 0.0)
            colour = quantize(srgb_encode(straight), bits=bits, dither_seed=colour_seed)
            pixels = np.concatenate([colour, quantize(alpha, bits=bits)], axis=-1)
        else:
            pixels = quantize(srgb_encode(pixels), bits=bits, dither_seed=colour_seed)
    else:
        raise ValueError(
            f"cannot write image '{os.fspath(path)}': unknown extension {ext or '(none)'!r} "
            f"(use .exr, .png, .tif, .tiff, .jpg or .jpeg)"
        )
    spec = oiio.ImageSpec(pixels.shape[1], pixels.shape[0], channels, fmt)
    spec.channelnames = _CHANNEL_NAMES[channels]
    if channels == 4:
        spec.alpha_channel = 3
    if ext in EXR_EXTENSIONS:
        spec.attribute("compression", "zip")
    else:
        spec.attribute("oiio:ColorSpace", "sRGB")
        spec.attribute("oiio:UnassociatedAlpha", 1)  # the pixels already hold straight alpha
    if ext in _JPEG_EXTENSIONS:
        spec.attribute("Compression", "jpeg:95")
        spec.attribute("jpeg:subsampling", "4:4:4")  # full-resolution colour
    for key, value in (metadata or {}).items():
        set_attribute(spec, key, value)
    write_pixels(path, spec, np.ascontiguousarray(pixels), replace=replace)



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
        write_pixels(path, spec, pixels, sync=False)  # a throwaway file: no need to wait for the disk
        with open(path, "rb") as stream:
            return stream.read()
