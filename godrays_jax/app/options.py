"""What the commands share: their user errors, the light, the effect and output-path options."""

import argparse
import math
import os
from collections.abc import Callable

from godrays_jax.effects.base import Effect
from godrays_jax.effects.presets import preset
from godrays_jax.effects.serialization import load_effect
from godrays_jax.primitives.io import read_light

DEFAULT_PRESET = "xna_crepuscular"
"""The effect `apply`, `batch` and `tune` use without `--preset` / `--params`."""


class CommandError(Exception):
    """A user error the CLI reports as one line (no traceback)."""


def parse_light(text: str) -> tuple[float, float]:
    """`"X,Y"` -> `(x, y)` pixels; both finite numbers."""
    parts = text.replace(" ", "").split(",")
    try:
        x, y = (float(part) for part in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--light must be X,Y in pixels (e.g. 160.5,42), got {text!r}") from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise argparse.ArgumentTypeError(f"--light must be finite, got {text!r}")
    return x, y


def resolve_light(light: tuple[float, float] | None, buffers_path: str) -> tuple[tuple[float, float], bool]:
    """The `--light` value, or the position stored in the frame's metadata."""
    if light is not None:
        return light, True
    stored = read_light(buffers_path)
    if stored is None:
        raise CommandError(f"{buffers_path} stores no light position (godrays:light_px): pass --light X,Y")
    return stored


def effect_option(
    preset_name: str | None, params_path: str | None, *, default: Callable[[], Effect] = lambda: preset(DEFAULT_PRESET)
) -> Effect:
    """The effect named by `--preset` or stored in `--params`; `default()` if neither is given."""
    if preset_name and params_path:
        raise CommandError("give --preset or --params, not both")
    if params_path:
        return load_effect(params_path)
    if preset_name:
        return preset(preset_name)
    return default()


def check_output_path(output: str, *inputs: str) -> None:
    """Refuse to overwrite an input and to write into a folder that does not exist."""
    folder = os.path.dirname(os.path.abspath(output))
    if not os.path.isdir(folder):
        raise CommandError(f"output folder {folder} does not exist")
    for path in inputs:
        if os.path.exists(output) and os.path.exists(path) and os.path.samefile(output, path):
            raise CommandError(f"refusing to overwrite the input {path}")
