"""Image files through OpenImageIO: all pixels of the first subimage with its header, atomic writes, header attributes."""

import os
from collections.abc import Sequence

import numpy as np
import OpenImageIO as oiio

from godrays_jax.primitives.files import atomic_write

EXR_EXTENSIONS = (".exr",)
"""Extensions written linear, as stored (every other format is display-encoded)."""


def _open(path: str, config: oiio.ImageSpec | None = None) -> oiio.ImageInput:
    if not os.path.exists(path):
        raise FileNotFoundError(f"image file '{path}' does not exist")
    inp = oiio.ImageInput.open(path) if config is None else oiio.ImageInput.open(path, config)
    if inp is None:
        raise ValueError(f"cannot read image '{path}': {oiio.geterror()}")
    return inp


def read_header(path: str | os.PathLike) -> oiio.ImageSpec:
    """The header of the first subimage (size, channels, metadata), without reading the pixels.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the file is not a readable image.
    """
    inp = _open(os.fspath(path))
    try:
        return inp.spec()
    finally:
        inp.close()


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """`(width, height)` of the first subimage, from the header alone (no pixel is read).

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the file is not a readable image.
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"image file '{path}' does not exist")
    inp = oiio.ImageInput.open(path)
    if inp is None:
        raise ValueError(f"cannot read image '{path}': {oiio.geterror()}")
    try:
        spec = inp.spec()
        return spec.width, spec.height
    finally:
        inp.close()


def read_pixels(path: str | os.PathLike, *, straight_alpha: bool = False) -> tuple[np.ndarray, oiio.ImageSpec]:
    """All channels of the first subimage as float32 `(H, W, C)`, and its spec.

    `straight_alpha`: return straight-alpha files (PNG, TIFF) as stored instead
    of letting OpenImageIO premultiply them.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the file is not a readable image.
    """
    path = os.fspath(path)
    config = oiio.ImageSpec()
    if straight_alpha:
        config.attribute("oiio:UnassociatedAlpha", 1)
    inp = _open(path, config)
    try:
        spec = inp.spec()
        pixels = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)
        if pixels is None:
            raise ValueError(f"cannot read image '{path}': {inp.geterror()}")
    finally:
        inp.close()
    pixels = np.asarray(pixels, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)
    return pixels, spec


def set_attribute(spec: oiio.ImageSpec, name: str, value: object) -> None:
    """Store a metadata value in `spec` with the OpenImageIO type that fits it (`ValueError` for any other value)."""
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


def write_pixels(
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
