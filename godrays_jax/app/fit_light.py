"""`fit --light auto` and `--fit-light`: each frame's light found before the fit (`pipeline.light_search`), the lines
the command prints about it, and the file beside the parameters that `apply --params` reads (`found_lights_path`)."""

import json
import math
import os

import numpy as np

from godrays_jax.app.options import LIGHT_AUTO, CommandError, resolve_light
from godrays_jax.pipeline.light_profile import LightProfile
from godrays_jax.pipeline.light_search import LightSearch, halo_starts
from godrays_jax.pipeline.light_seen import SeenLight
from godrays_jax.primitives.buffers import Buffers
from godrays_jax.primitives.files import atomic_write


def first_light(
    given, frame: Buffers, target, path: str, *, fit_light: bool, space: str
) -> tuple[tuple[float, float], bool]:
    """The light a frame is made ready with (`ready_frame`: a frame without depth reads its sky around it) before
    the search: for `--light auto` (`given` is `LIGHT_AUTO`) the target's halo's first start (`halo_starts`), else
    `--light`'s or the header's (`resolve_light`). A light behind the camera is refused under `--fit-light`: no
    halo on screen shows it."""
    if given == LIGHT_AUTO:
        return tuple(float(v) for v in halo_starts(frame, target, space=space)[0]), True
    light, in_front = resolve_light(given, path)
    if fit_light and not in_front:
        raise CommandError(
            f"--fit-light: the light of {path} is behind the camera, where no halo on screen places it; "
            "fit without --fit-light"
        )
    return light, in_front


def light_lines(path: str, found: LightSearch, *, auto: bool, start_names: list[str]) -> list[str]:
    """The command's two lines about a light found: where, from where, and how well the frames determine it."""
    x, y = found.light_xy
    if auto:
        origin = f"from the target's halo (a start at {_pair(found.start_xy)})"
    else:
        origin = f"refined from {_pair(found.start_xy)} (moved {np.linalg.norm(found.light_xy - found.start_xy):.3g} px)"
    fields = f", with the fields of {start_names[found.start - 1]}" if found.start else ""
    error, shift = found.standard_error, found.visible_shift
    return [
        f"light of {path}: {x:.6g},{y:.6g} px, {origin}{fields}",
        (
            f"  standard error {error[0]:.3g} px in x, {error[1]:.3g} px in y; a move of {shift[0]:.3g} px in x or "
            f"{shift[1]:.3g} px in y changes the frame by 0.001 RMS (at 1/{found.factor} resolution)"
        ),
    ]


def seen_lines(
    path: str, seen: SeenLight, drawn: list[SeenLight], listed: list[SeenLight], *, given_xy=None, depth: float
) -> list[str]:
    """The command's lines about a light placed by its own pixels in view (`light_seen.seen_lights`): where, how
    (`given_xy`: the light it refines, else None), how well, the distance drawn (`depth`), the other lights in
    view `drawn` beside it, and those `listed` only, with the options that draw them all."""
    x, y = seen.light_xy
    shape = "a few pixels across" if math.isnan(seen.radius) else f"a disc of radius {seen.radius:.3g} px"
    how = "partly hidden: the centre of its edge's unhidden arc" if seen.hidden else "its pixels' centroid"
    where = "in the sky" if math.isinf(seen.depth) else f"its pixels at a distance of {seen.depth:.4g}"
    if depth != seen.depth:
        where += f" (drawn at the distance given, {depth:.4g})"
    moved = ""
    if given_xy is not None:
        moved = f", {np.linalg.norm(seen.light_xy - np.asarray(given_xy)):.3g} px from {_pair(given_xy)}"
    error = seen.standard_error
    lines = [
        f"light of {path}: {x:.6g},{y:.6g} px, in view ({shape}, {how}), {where}{moved}",
        (
            f"  standard error {error[0]:.3g} px in x, {error[1]:.3g} px in y (its edge about a circle)"
            if np.all(np.isfinite(error))
            else "  standard error not measured (no circle fits its edge)"
        ),
    ]
    if drawn:
        described = "; ".join(_pair(light.light_xy) + _distance(light.depth) for light in drawn)
        lines.append(f"  {len(drawn)} more in view, drawn beside it (their tints fitted): {described}")
    if listed:
        every = [seen, *drawn, *listed]
        positions = ";".join(_pair(light.light_xy) for light in every)
        depths = ";".join("inf" if math.isinf(light.depth) else f"{light.depth:.4g}" for light in every)
        fainter = "fainter " if given_xy is None else ""
        lines.append(
            f"  {len(listed)} {fainter}more in view; to draw them all: --light '{positions}' --light-depth '{depths}'"
        )
    return lines


def _distance(depth: float) -> str:
    return " in the sky" if math.isinf(depth) else f" at a distance of {depth:.4g}"


def tried_line(xy, loss: float) -> str:
    """The command's line about one fit of `light_profile.profile_light`: the light tried and the loss reached."""
    return f"  a fit with the light at {_pair(xy)} px: loss {loss:.6g}"


def profile_lines(profile: LightProfile, *, visible_rise: float | None, step: float) -> list[str]:
    """The command's lines about the light `light_profile.profile_light` placed (its first round's `step`, pixels)
    and how well the fits place it (`LightProfile.visible_shift`, a rise of `visible_rise` in a fit's loss; None: a
    loss that is not the MSE)."""
    placed = f"  placed at {_pair(profile.light_xy)} px: where the losses of the {len(profile.losses)} fits are lowest"
    if visible_rise is None:
        return [placed, "  how well the fits place it is measured for --loss mse only"]
    if np.all(np.isnan(profile.visible_shift)):
        return [placed, f"  how well the fits place it is not measured: fewer than six fits within {step:.3g} px of it"]
    shifts = dict(zip("xy", profile.visible_shift))
    seen = " or ".join(f"{shift:.3g} px in {axis}" for axis, shift in shifts.items() if np.isfinite(shift))
    unseen = " or ".join(axis for axis, shift in shifts.items() if not np.isfinite(shift))
    rises = f"raises a whole fit's loss by {visible_rise:.3g} (the fitted frame changes by {math.sqrt(visible_rise):.3g} RMS)"
    unplaced = f"the frames do not place the light along {unseen}"
    if not unseen:
        return [placed, f"  a move of {seen} {rises}"]
    if not seen:
        return [placed, f"  no move within {step:.3g} px in {unseen} {rises}: {unplaced}"]
    return [placed, f"  a move of {seen} {rises}; no move within {step:.3g} px in {unseen} does: {unplaced}"]


def _pair(xy) -> str:
    return f"{xy[0]:.6g},{xy[1]:.6g}"


def found_lights_text(
    found: dict[str, tuple[LightSearch | SeenLight, Buffers, float, list[SeenLight]]], tints=None
) -> str:
    """The file of the lights found (`options.found_lights_path`): for each frame (by file name, as `apply` finds
    it) the light in pixels, the frame's size, the light's standard error (`null` where not measured: a light placed
    by whole fits), the move that changes its fitted frame visibly where it was measured (`"visible_shift_px"`,
    `null` for an axis along which no move does), the distance the fit drew it at
    (`null`: infinite, the sun) and the lights in view drawn beside it (`"beside"`: each position and distance);
    and the fitted tints of the lights beside the first (`tints`, `(K, 3)`, over the first's), which `apply
    --params` takes; as JSON."""
    lights = [
        {
            "frame": os.path.basename(path),
            "size": [frame.width, frame.height],
            "light_px": [float(v) for v in light.light_xy],
            "standard_error_px": [float(v) if np.isfinite(v) else None for v in light.standard_error],
            **({"visible_shift_px": [float(v) if np.isfinite(v) else None for v in light.visible_shift]}
               if np.any(np.isfinite(getattr(light, "visible_shift", np.nan))) else {}),
            "light_depth": _depth_value(depth),
            **({"beside": [
                {"light_px": [float(v) for v in other.light_xy], "light_depth": _depth_value(other.depth)}
                for other in beside
            ]} if beside else {}),
        }  # fmt: skip
        for path, (light, frame, depth, beside) in found.items()
    ]
    fitted = {} if tints is None else {"light_tints": [[float(v) for v in tint] for tint in tints]}
    return json.dumps({"lights": lights, **fitted}, indent=2) + "\n"


def _depth_value(depth: float) -> float | None:
    """A distance as the file holds it: `null` for infinity, which JSON has no number for."""
    return float(depth) if math.isfinite(depth) else None


def write_text(path: str, text: str) -> None:
    """`text` written at `path` whole (atomically: a temporary file renamed into place)."""
    with atomic_write(path) as temporary, open(temporary, "w") as stream:
        stream.write(text)
