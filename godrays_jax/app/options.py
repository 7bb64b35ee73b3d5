"""What the commands share: their user errors, the light, the effect and output-path options, a frame made ready."""

import argparse
import contextlib
import dataclasses
import math
import os
import sys
from collections.abc import Callable, Iterator

import numpy as np

from godrays_jax.effects.base import Effect
from godrays_jax.effects.fields import MAX_TEXTURE_SIDE
from godrays_jax.effects.lights import Light
from godrays_jax.effects.presets import PRESETS, preset
from godrays_jax.effects.serialization import MAX_EFFECT_FILE_BYTES, load_effect, parse_json_object
from godrays_jax.pipeline.batch import ready_frame
from godrays_jax.primitives.buffers import Buffers
from godrays_jax.primitives.checks import check_light, error_line
from godrays_jax.primitives.camera_metadata import read_clip_planes, read_frame_camera
from godrays_jax.primitives.frame_reading import SKY_DEPTH, read_buffers
from godrays_jax.primitives.image_files import image_size
from godrays_jax.primitives.images import read_image
from godrays_jax.primitives.light_metadata import read_light, read_light_depth, read_lights
from godrays_jax.primitives.light_view_files import read_light_view

DEFAULT_PRESET = "xna_crepuscular"
"""The effect `apply`, `batch` and `tune` use without `--preset` / `--params`."""


def default_fit_effect() -> Effect:
    """The model `godrays-jax fit` starts from without `--preset` / `--params`: `preset("volumetric_haze")`.

    Chosen by fitting the path-traced references (`benchmarks/fit_volumetric.py`, table in
    `benchmarks/README.md`): against a volumetric path tracer's fog, additive effects can only add
    light while real fog also removes it; of the two media, `VolumetricFog` (each view ray lit
    segment by segment, its shadows read from the depth buffer) fits every reference measured
    closer than `ScatteringFog` (one lit fraction per ray from a radial blur of the open sky).
    When the camera's field of view is known, set it and keep it fixed
    (`fixed=("fov_x_deg", ...)`); the command line does so when the frame carries it.
    """
    return preset("volumetric_haze")


COARSE_FIT_PIXELS = 160 * 90
"""Without `--coarse-factor`, `fit` races its starts at a reduced resolution on frames larger than this many pixels.

A race step there costs a fraction of a full-resolution one; the winner then descends and is polished at full
resolution, where thin surfaces a reduced frame loses count again (benchmarks/README.md, "The fit as users run
it")."""


def model_presets(effect: Effect) -> list[str]:
    """The presets of `effect`'s model (its type), by name: `fit` tries them as starts beside the one it is given."""
    return [name for name in sorted(PRESETS) if type(preset(name)) is type(effect)]


def auto_coarse_factor(height: int, width: int) -> int:
    """The smallest factor that brings a `height x width` frame to at most `COARSE_FIT_PIXELS` pixels (1: no coarse phase)."""
    factor = 1
    while -(-height // factor) * -(-width // factor) > COARSE_FIT_PIXELS:
        factor += 1
    return factor


class CommandError(Exception):
    """A user error the CLI reports as one line (no traceback)."""


LIGHT_SIDES = {"front": True, "behind": False}
"""`--light X,Y,SIDE`'s last word: the light in front of the camera (the default) or behind it (its position then
the projection `camera.project_point` gives, mirrored through the camera plane)."""


LIGHTS_SEPARATOR = ";"
"""What separates the lights of one frame in `apply --light`, `--light-depth` and `--light-tint`."""


def parse_light(text: str) -> tuple[tuple[float, float], bool]:
    """`"X,Y"` or `"X,Y,front"` or `"X,Y,behind"` -> `((x, y), in_front)`: pixels, both finite numbers, a far light
    moved along its direction to `MAX_LIGHT_PX`; `behind` a light behind the camera (`LIGHT_SIDES`)."""
    parts = text.replace(" ", "").split(",")
    side = parts.pop().lower() if len(parts) == 3 else "front"
    usage = f"--light must be X,Y in pixels, or X,Y,behind for a light behind the camera (e.g. 160.5,42), got {text!r}"
    if side not in LIGHT_SIDES:
        raise argparse.ArgumentTypeError(usage)
    try:
        x, y = (float(part) for part in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(usage) from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise argparse.ArgumentTypeError(f"--light must be finite, got {text!r}")
    x, y = check_light((x, y))  # as the library bounds it, before a float32 cast could overflow
    return (float(x), float(y)), LIGHT_SIDES[side]


def parse_lights(text: str) -> list[tuple[tuple[float, float], bool]]:
    """`--light`: one light as `parse_light` reads it, or several separated by `;` (`"160,40;300,90,behind"`),
    each drawn by `effects.lights.lit_by`."""
    return [parse_light(part) for part in text.split(LIGHTS_SEPARATOR)]


def parse_light_depths(text: str) -> list[float]:
    """`apply --light-depth` and `batch --light-depth`: one distance as `parse_light_depth` reads it, or one per light separated by `;`."""
    return [parse_light_depth(part) for part in text.split(LIGHTS_SEPARATOR)]


def parse_light_tints(text: str) -> list[tuple[float, float, float]]:
    """`apply --light-tint` and `batch --light-tint`: one light's tint, the linear `"R,G,B"` its light is multiplied by (finite numbers >= 0;
    one number for a grey), or one per light separated by `;`."""
    tints = []
    for part in text.split(LIGHTS_SEPARATOR):
        usage = f"--light-tint must be R,G,B (finite numbers >= 0; ';' between lights), got {text!r}"
        try:
            values = [float(value) for value in part.replace(" ", "").split(",")]
        except ValueError:
            raise argparse.ArgumentTypeError(usage) from None
        if len(values) not in (1, 3) or not all(math.isfinite(value) and value >= 0 for value in values):
            raise argparse.ArgumentTypeError(usage)
        tints.append(tuple(values * 3 if len(values) == 1 else values))
    return tints


def split_lights(
    lights: list | None, depths: list[float] | None, tints: list | None, default_depth: Callable[[], float], *,
    layer_only: bool = False,
) -> tuple[tuple[tuple[float, float], bool] | None, float, tuple[float, float, float] | None, list[Light]]:
    """`apply`'s or `batch`'s `--light`, `--light-depth` and `--light-tint` (`parse_lights`' lists, or None):
    the first light (None: the frame's), its distance (`default_depth()` when none is given: the frame's), its
    tint (None: 1), and the lights beside it as `effects.lights.Light`s. A distance or a tint given once is
    every light's. `CommandError` for counts that match neither, and for `--layer-only` with several or tinted
    lights (`pipeline.batch.frames_function` refuses it too)."""
    count = len(lights) if lights else 1
    if layer_only and (count > 1 or tints is not None):
        raise CommandError(
            "--layer-only draws one light as the effect has it: a fog's layer under several or tinted lights is not "
            "a sum of layers"
        )
    for name, values in (("--light-depth", depths), ("--light-tint", tints)):
        if values is not None and len(values) not in (1, count):
            raise CommandError(f"{name} gives {len(values)} values for {count} lights: give one, or one per light")
    depths = depths or [default_depth()]
    depths = depths * count if len(depths) == 1 else depths
    every = tints * count if tints is not None and len(tints) == 1 else tints
    beside = [
        Light(np.asarray(xy, np.float32), in_front=front, depth=depth,
              tint=np.asarray((1.0, 1.0, 1.0) if every is None else every[index], np.float32))
        for index, ((xy, front), depth) in enumerate(zip(lights or [], depths)) if index > 0
    ]  # fmt: skip
    return (lights[0] if lights else None), depths[0], (None if every is None else every[0]), beside


def resolve_light(light: tuple[tuple[float, float], bool] | None, buffers_path: str) -> tuple[tuple[float, float], bool]:
    """The `--light` value (`parse_light`'s), or the position and side stored in the frame's metadata."""
    if light is not None:
        return light
    stored = read_light(buffers_path)
    if stored is None:
        raise CommandError(f"{buffers_path} stores no light position (godrays:light_px): pass --light X,Y")
    return stored


LIGHT_AUTO = "auto"
"""`fit --light auto`: the light found from the frame and its target (`pipeline.light_search.find_light`)."""


def parse_fit_light(text: str) -> list[tuple[tuple[float, float], bool]] | str:
    """`fit --light`: `LIGHT_AUTO` (`"auto"`, any case), or a frame's lights as `parse_lights` reads them."""
    if text.strip().lower() == LIGHT_AUTO:
        return LIGHT_AUTO
    try:
        return parse_lights(text)
    except argparse.ArgumentTypeError as error:
        raise argparse.ArgumentTypeError(f"{error}; or auto, to find it from the target") from None


def found_lights_path(params_path: str) -> str:
    """The file beside a fit's parameters where `fit --light auto` / `--fit-light` writes the lights it found
    (`params.json` -> `params.light.json`), which `apply --params` reads."""
    root, extension = os.path.splitext(params_path)
    return f"{root}.light{extension or '.json'}"


@dataclasses.dataclass(frozen=True)
class FoundLights:
    """The lights `fit --light auto` / `--fit-light` found for a frame (`lights_of_params`): positions in the
    frame's pixels, each in front of the camera (`parse_lights`' pairs), the first the light found and the rest the
    lights in view drawn beside it; each one's distance (None where the file does not say: the header's, else
    `inf`)."""

    lights: list[tuple[tuple[float, float], bool]]
    depths: list[float | None]


def lights_of_params(params_path: str | None, frame_path: str, buffers: Buffers) -> FoundLights | None:
    """The lights `fit` found for this frame (by its file name) beside the parameters `params_path`
    (`found_lights_path`), positions scaled to the frame's size, said on stdout; None where there are none (the
    frame's header then, `resolve_light`)."""
    if params_path is None or not os.path.exists(path := found_lights_path(params_path)):
        return None
    try:
        found = _found_lights(path, os.path.basename(frame_path))
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise CommandError(f"{path} is not the lights `fit` writes: {error_line(error)}") from None
    if found is None:
        return None
    positions, (width, height), depths = found
    lights = [
        (tuple(float(v) for v in check_light((x * buffers.width / width, y * buffers.height / height))), True)
        for x, y in positions
    ]
    described = "; ".join(
        f"{xy[0]:.6g},{xy[1]:.6g}" + ("" if depth is None else f" at a distance of {depth:.6g}")
        for (xy, _), depth in zip(lights, depths)
    )
    print(f"light{'s' if len(lights) > 1 else ''} {described} from {path} (found by fit)", flush=True)
    return FoundLights(lights, depths)


def tints_text(tints) -> str:
    """The tints of the lights beside the first as `--light-tint` takes them, the first's 1: `"1;r,g,b;..."`."""
    return ";".join(["1", *(",".join(f"{float(v):.6g}" for v in tint) for tint in tints)])


def tints_of_params(tints: list | None, params_path: str | None, lights: list | None) -> list | None:
    """`tints` (`--light-tint`) if given; else, for a frame of `lights` (several), the tints `fit` fitted for the
    lights beside the first, from the file beside the parameters `params_path` (`found_lights_path`), said on
    stdout, where it holds one for each of them; else None (the frame's header's, or 1)."""
    if tints is not None or params_path is None or not lights:
        return tints
    if not os.path.exists(path := found_lights_path(params_path)):
        return tints
    try:
        with open(path, "rb") as stream:
            fitted = parse_json_object(stream.read(MAX_EFFECT_FILE_BYTES + 1)).get("light_tints")
        fitted = None if fitted is None else [tuple(float(v) for v in tint) for tint in fitted]
    except (OSError, ValueError, TypeError) as error:
        raise CommandError(f"{path} is not the lights `fit` writes: {error_line(error)}") from None
    if fitted is None or len(fitted) != len(lights) - 1:
        return tints
    if not all(len(tint) == 3 and all(math.isfinite(v) and v >= 0 for v in tint) for tint in fitted):
        raise CommandError(f"{path}: light_tints must be R,G,B triples of finite numbers >= 0, got {fitted}")
    print(f"light tints {tints_text(fitted)} from {path} (fitted by fit)", flush=True)
    return [(1.0, 1.0, 1.0), *fitted]


def _found_lights(path: str, frame_name: str) -> tuple[list, tuple[int, int], list[float | None]] | None:
    """The positions (the light found, then those beside it), frame size and distances (None where the file does
    not say; `null` in it: infinite) of the lights `fit` found for the frame named `frame_name`, from the file at
    `path`; None when it holds none for that frame."""
    with open(path, "rb") as stream:
        entries = parse_json_object(stream.read(MAX_EFFECT_FILE_BYTES + 1))["lights"]
    entry = next((entry for entry in entries if entry["frame"] == frame_name), None)
    if entry is None:
        return None
    width, height = (int(v) for v in entry["size"])
    if not (width > 0 and height > 0):
        raise ValueError(f"the frame of {frame_name} must have a positive size, got {entry['size']}")
    positions, depths = [], []
    for light in [entry, *entry.get("beside", [])]:
        x, y = (float(v) for v in light["light_px"])
        if not (math.isfinite(x) and math.isfinite(y)):
            raise ValueError(f"the lights of {frame_name} must be finite, got {light['light_px']}")
        positions.append((x, y))
        if "light_depth" not in light:  # a file of an earlier fit: the header's distance, else infinity
            depths.append(None)
            continue
        depth = light["light_depth"]
        if depth is not None and not (isinstance(depth, (int, float)) and math.isfinite(depth) and depth > 0):
            raise ValueError(f"a light_depth of {frame_name} must be a number > 0 or null, got {depth!r}")
        depths.append(math.inf if depth is None else float(depth))
    return positions, (width, height), depths


def parse_light_depth(text: str) -> float:
    """`"D"` -> the light's distance in scene units, a number > 0 (`inf` allowed: a light at infinity; a light at
    the camera has no direction the fog could be lit from)."""
    try:
        depth = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--light-depth must be a number > 0 or inf, got {text!r}") from None
    if math.isnan(depth) or depth <= 0:
        raise argparse.ArgumentTypeError(f"--light-depth must be a number > 0 or inf, got {text!r}")
    return depth


def resolve_light_depth(light_depth: float | None, buffers_path: str) -> float:
    """The `--light-depth` value, or the distance stored in the frame's metadata, or `inf` (a light at infinity)."""
    if light_depth is not None:
        return light_depth
    stored = read_light_depth(buffers_path)
    return math.inf if stored is None else stored


@contextlib.contextmanager
def _c_library_messages_dropped() -> Iterator[None]:
    """Whatever C code writes to stderr meanwhile is dropped: libpng prints a line of its own before OpenImageIO
    reports the same error, which the command prints as its one line."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def with_flare_texture(effect: Effect, texture_path: str | None) -> Effect:
    """The effect with its flare texture read from `--flare-texture` (any image; linear values).

    The texture is checked as the effect's `flare_texture` field checks it
    (1 to 4 channels, alpha premultiplied and dropped, at most
    `MAX_TEXTURE_SIDE` texels on a side, finite values of magnitude at most
    `MAX_TEXTURE_VALUE`); its size is read from the header, before its pixels.
    """
    if texture_path is None:
        return effect
    try:
        with _c_library_messages_dropped():
            width, height = image_size(texture_path)
            if max(width, height) > MAX_TEXTURE_SIDE:
                raise ValueError(f"{width}x{height} texels, more than {MAX_TEXTURE_SIDE} on a side: resample it")
            texture = read_image(texture_path)
        return effect.with_flare_texture(texture)
    except (OSError, ValueError) as error:
        raise CommandError(f"--flare-texture {texture_path}: {error_line(error)}") from None


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


def parse_sky_depth(text: str) -> float:
    """`--sky-depth`: a positive number of scene units (`inf`: only infinite depth is sky)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not value > 0:
        raise argparse.ArgumentTypeError(f"--sky-depth must be a positive number of scene units, got {text!r}")
    return value


SKY_DEPTH_HELP = (
    f"depth at or above this (scene units) is open sky (default {SKY_DEPTH:.0e}: Blender's 1e10 background, "
    "FLT_MAX and inf; in a half-float depth channel also 65504); set it to the far plane your renderer writes "
    "on the background, e.g. --sky-depth 1000"
).replace("e+0", "e")


def parse_fov(text: str) -> float:
    """`--fov-x-deg`: a horizontal field of view in degrees, in (0, 180)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0 < value < 180:
        raise argparse.ArgumentTypeError(f"--fov-x-deg must be a number of degrees in (0, 180), got {text!r}")
    return value


def frame_reading(args: argparse.Namespace) -> dict:
    """The keyword arguments of `read_buffers` / `read_frame` / `run_batch` from the frame options.

    Frames without depth are read too (`without_depth`): `batch.ready_frame` gives them their open sky.
    """
    return {
        "depth_channel": args.depth_channel, "color_layer": args.color_layer, "sky_depth": args.sky_depth,
        "depth_kind": args.depth_kind, "fov_x_deg": args.fov_x_deg, "without_depth": True,
    }  # fmt: skip


def with_light_view(buffers: Buffers, path: str | None) -> Buffers:
    """`buffers` with the depth map seen from the light that `--light-view` names (`read_light_view`), or as they
    are without one; a file that cannot be read is the command's error."""
    if path is None:
        return buffers
    try:
        return dataclasses.replace(buffers, light_view=read_light_view(path))
    except (OSError, ValueError) as error:
        raise CommandError(f"--light-view: {error}") from None


def frame_field_of_view(args: argparse.Namespace, path: str) -> float | None:
    """The field of view effects use: `--fov-x-deg`, else the one the frame's header carries, else None."""
    return args.fov_x_deg if args.fov_x_deg is not None else read_frame_camera(path).fov_x_deg


def read_target(path: str) -> np.ndarray:
    """A reference image's colour: its plain `R, G, B`, or a render's colour layer (Blender's `ViewLayer.Combined`).

    Read as a frame's colour is (`read_buffers`, depth not needed), so a multilayer render's other passes
    (`ViewLayer.AO.R`, `ViewLayer.Depth.Z`, ...) are never taken for its colour.
    """
    return read_buffers(path, without_depth=True, depth_kind="ray").color


def warn(command: str, text: str) -> None:
    """One line on stderr: `godrays-jax COMMAND: warning: TEXT`."""
    print(f"godrays-jax {command}: warning: {text}", file=sys.stderr, flush=True)


def with_stored_lights(
    path: str, lights: list | None, depths: list[float] | None, tints: list | None
) -> tuple[list | None, list[float] | None, list | None]:
    """`--light`, `--light-depth` and `--light-tint` (`parse_lights`' lists, or None) as given; without `--light`, a
    frame at `path` that stores several lights (`godrays:lights`: a render of several) gives them all, with their
    stored distances and tints where those are not given (`split_lights` then splits them as `--light`'s)."""
    if lights is not None or len(stored := read_lights(path) or []) < 2:
        return lights, depths, tints
    return (
        [(tuple(light.xy), light.in_front) for light in stored],
        depths or [light.depth for light in stored],
        tints or [tuple(light.tint) for light in stored],
    )


def warn_of_stored_lights(command: str, path: str, *, hint: str = "") -> None:
    """`warn` when the frame at `path` stores several lights (`godrays:lights`, a render of several) and `command`
    draws one, its first (`godrays:light_px`); `apply` draws them all. An unreadable header says nothing here (the
    frame is read, and reported, where the command reads it)."""
    try:
        stored = read_lights(path) or []
    except (OSError, ValueError):
        return
    if len(stored) > 1:
        warn(command, f"{path} stores {len(stored)} lights (godrays:lights): {command} draws the first "
                      f"(godrays:light_px), apply draws them all{hint}")  # fmt: skip


def has_sky(buffers: Buffers) -> bool:
    """Whether any pixel is (partly) open sky: coverage below 1 somewhere."""
    return bool(np.min(np.asarray(buffers.coverage)) < 1.0)


NO_SKY = (
    "no sky pixel (no depth >= --sky-depth, no alpha below 1): effects that shine through the sky draw "
    "nothing; if the renderer writes its far plane on the background, pass --sky-depth FAR"
)
"""The warning for a frame without sky: `f"{name} has {NO_SKY}"`."""


def effect_for_frame(command: str, effect: Effect, buffers: Buffers, name: str) -> Effect:
    """The effect to draw on the frame `name` (`Effect.for_buffers`), with a warning when it is a stand-in for one
    that reads what the frame lacks (the galaxy-engine VLS preset's rendered light pass)."""
    chosen, why = effect.for_buffers(buffers)
    if why is not None:
        warn(command, f"{name} {why}")
    return chosen


def with_frame_camera(effect: Effect, args: argparse.Namespace, path: str) -> Effect:
    """`effect` through the camera of the frame at `path` (`Effect.with_camera`): its field of view (`--fov-x-deg`,
    else its header) and its clip planes (`godrays:clip_planes`, as `render` writes them)."""
    return effect.with_camera(fov_x_deg=frame_field_of_view(args, path), clip_planes=read_clip_planes(path))


def frame_for_command(
    command: str, effect: Effect, buffers: Buffers, path: str, light: tuple[tuple[float, float], bool] | None
) -> tuple[Effect, Buffers, tuple[float, float], bool]:
    """One frame made ready for `effect` (`ready_frame`): `(effect, buffers, light pixel, light in front)`.

    The effect falls back to the disc emitter when the frame lacks its light
    pass (`effect_for_frame`); the light is `light` (`parse_light`'s position
    and side) or the frame's header (`resolve_light`); a frame without sky gets a warning. Raises
    `CommandError` for a frame the effect cannot use (no depth).
    """
    effect = effect_for_frame(command, effect, buffers, path)
    light_xy, in_front = resolve_light(light, path)
    try:
        buffers = ready_frame(effect, buffers, light_xy, path)
    except ValueError as error:
        raise CommandError(str(error)) from None
    if not has_sky(buffers):
        warn(command, f"{path} has {NO_SKY}")
    return effect, buffers, light_xy, in_front
