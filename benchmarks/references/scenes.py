"""The path-traced reference scenes in this folder, for benchmark scripts to loop over.

    python benchmarks/references/scenes.py             # the README's table

    from benchmarks.references.scenes import SCENES      # or with this folder on sys.path: from scenes import SCENES
    for scene in SCENES:
        scene.clean, scene.fog_a, scene.fog_b, scene.light_px, scene.noise_floor

Read from `scenes.json`, which `render_references.py` (Mitsuba 3) and
`render_blender.py` (Cycles) write beside the frames. `noise_floor` is half
the display-space MSE between the two fog renders (`x / (1 + |x|)` per
channel, `godrays-jax fit`'s loss): what a perfect model would score against
either render. Ratios to it are the figures of merit.
"""

import json
import math
from dataclasses import dataclass
from pathlib import Path

HERE = Path(__file__).resolve().parent


@dataclass(frozen=True)
class ReferenceScene:
    """One scene: its frames, its light and camera, its medium and its noise floor.

    `light_px` is in pixels (x right, y down, pixel centres at `i + 0.5`; may
    lie off screen), `light_depth` in scene units along the light's camera ray
    (`inf` for the sun), `fov_x_deg` the horizontal field of view. Paths are
    absolute. `renderer` is `"mitsuba"` (frames with `R, G, B, A, Z`, depth
    along the ray) or `"blender"` (multilayer, `Z` planar). `lights`: for a
    scene of several lights (`street_two_lamps`; there `light_px` and
    `light_depth` are the first's) the header's `godrays:lights`,
    `godrays:lights_depth` and `godrays:lights_tint` texts by those names, as
    `--light`, `--light-depth` and `--light-tint` take them; `None` for one.
    """

    name: str
    shows: str
    renderer: str
    clean: Path
    fog_a: Path
    fog_b: Path
    light_px: tuple[float, float]
    light_in_front: bool
    light_depth: float
    fov_x_deg: float
    medium: dict
    light: str
    spp: dict
    seconds: dict
    noise_floor: float
    lights: dict | None = None


def _load(folder: Path, renderer: str) -> list[ReferenceScene]:
    path = folder / "scenes.json"
    if not path.exists():
        return []
    scenes = []
    for name, entry in json.loads(path.read_text()).items():
        fog_a, fog_b = entry["fog"]
        scenes.append(ReferenceScene(
            name=name,
            shows=entry["shows"],
            renderer=renderer,
            clean=folder / entry["clean"],
            fog_a=folder / fog_a,
            fog_b=folder / fog_b,
            light_px=tuple(entry["light_px"]),
            light_in_front=bool(entry["light_in_front"]),
            light_depth=math.inf if entry["light_depth"] is None else float(entry["light_depth"]),
            fov_x_deg=float(entry["fov_x_deg"]),
            medium=entry["medium"],
            light=entry["light"],
            spp=entry["spp"],
            seconds=entry["seconds"],
            noise_floor=float(entry["noise_floor"]),
            lights=(
                {key: entry[key] for key in ("lights", "lights_depth", "lights_tint")} if "lights" in entry else None
            ),
        ))
    return scenes


SCENES: tuple[ReferenceScene, ...] = tuple(_load(HERE, "mitsuba") + _load(HERE / "blender", "blender"))
"""Every scene: Mitsuba's (this folder), then Cycles' (`blender/`)."""

BY_NAME = {scene.name: scene for scene in SCENES}


def table() -> str:
    """The README's table (markdown): medium, light, samples, seconds, noise floor, today's fit (`baseline.json`)."""
    baseline_path = HERE / "baseline.json"
    baseline = json.loads(baseline_path.read_text()) if baseline_path.exists() else {}
    rows = ["| scene | what it shows | medium: sigma_t, albedo, g, extent | light | spp fog / clean | "
            "seconds per fog render (wall / CPU) | noise floor | today's model / floor (fog A, fog B) |",
            "|---|---|---|---|---|---|---|---|"]
    for s in SCENES:
        m = s.medium
        fog_seconds = ", ".join(f"{wall:g} / {cpu:g}" for wall, cpu in (s.seconds["fog_a"], s.seconds["fog_b"]))
        fit = baseline.get(s.name)
        today = f"{fit['ratio_fog_a']:.2f}, {fit['ratio_fog_b']:.2f}" if fit else "not measured"
        rows.append(f"| {s.name} | {s.shows} | {m['sigma_t']:g}, {m['albedo']:g}, {m['g']:g}, {m['extent']} | "
                    f"{s.light} | {s.spp['fog']} / {s.spp['clean']} | {fog_seconds} | {s.noise_floor:.3e} | {today} |")
    return "\n".join(rows)


if __name__ == "__main__":
    print(table())
