"""Render reference scenes with Blender Cycles (CPU) as Blender multilayer EXR: a clean frame and two fog frames.

    python benchmarks/references/render_blender.py [SCENE ...] [--samples 256] [--blender blender] [--out DIR]
        [--volume-bounces 1] [--threads 1] [--light-view]

The scenes are `render_references.py`'s (same camera, shapes, light and
medium), built in Blender (its z up: our `(x, y, z)` is Blender's
`(x, -z, y)`). Per scene NAME it writes into `blender/`:

- `NAME_clean.exr`: without a medium, four times the fog's samples;
- `NAME_fog_a.exr`, `NAME_fog_b.exr`: inside the medium, Cycles seeds 1 and 2;

- `NAME_light_view.exr` (`--light-view`, a sun scene): the depth seen from the sun, made as
  docs/file_formats.md tells a Blender user to: an orthographic camera with the sun lamp's rotation,
  `render_references.LIGHT_VIEW_DISTANCE` up-sun of the frame's camera, `LIGHT_VIEW_SPAN` across in
  `LIGHT_VIEW_PIXELS` square, its `Z` pass without the medium, and the three `godrays:light_view_*`
  attributes set afterwards with OpenImageIO from both cameras' `matrix_world`;

each as Blender writes it (`OPEN_EXR_MULTILAYER`, half floats, zip):
`ViewLayer.Combined.R/G/B/A` and `ViewLayer.Depth.Z`, Cycles' Z pass, the
distance along the camera's axis (planar), `1e10` on sky; the header stamps
the lens (`Lens`, 36 mm sensor), from which the field of view is read. Blender
cannot add the `godrays:*` attributes, so the light's pixel position and
depth are in `blender/scenes.json` (read by `scenes.py`) and go to `fit` and
`apply` as `--light X,Y` (and `--light-depth`).

Cycles settings: no denoising, no adaptive sampling, no clamping, max
bounces 1 (direct light and one bounce: Mitsuba's max depth 3; `--volume-bounces 0`: light scattered once in
the medium, for a diagnosis in another `--out` folder), the medium a
`Volume Scatter` (anisotropy g) plus `Volume Absorption` in a closed sphere
around the camera (homogeneous), the sun a sun lamp of the disc's angle and
irradiance (Cycles does not show a sun lamp to the camera: the scenes here
hide it or use a lamp), the lamp an emitting sphere. One render thread (`--threads`).

Run by Python, it calls `blender -b --factory-startup --python THIS -- ...`
once per frame (seconds: wall and CPU of that call); run by Blender (`bpy` importable), it builds and renders one.
"""

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
OUT = HERE / "blender"
SCENE_NAMES = ("hidden_sun", "point_light")
SEEDS = {"clean": 0, "fog_a": 1, "fog_b": 2}
CLEAN_SAMPLES_FACTOR = 4
PREFIX = "cycles_"  # scene names in scenes.json, apart from Mitsuba's


# ----------------------------------------------------------------------------- inside Blender


def _to_blender(matrix):
    """A shape's 4x4 to-world matrix (its own frame to our y-up world) into Blender's z-up world: C M.

    C maps our `(x, y, z)` to Blender's `(x, -z, y)`; the shape's own frame stays as it is.
    """
    from mathutils import Matrix

    axes = Matrix(((1, 0, 0, 0), (0, 0, -1, 0), (0, 1, 0, 0), (0, 0, 0, 1)))
    return axes @ Matrix(matrix)


def _point(p):
    return (p[0], -p[2], p[1])


def _diffuse(bpy, name, reflectance):
    material = bpy.data.materials.new(name)
    material.use_nodes = True
    nodes = material.node_tree.nodes
    nodes.remove(nodes["Principled BSDF"])
    diffuse = nodes.new("ShaderNodeBsdfDiffuse")
    diffuse.inputs["Color"].default_value = (*reflectance, 1.0)
    material.node_tree.links.new(diffuse.outputs["BSDF"], nodes["Material Output"].inputs["Surface"])
    return material


def _emission(bpy, radiance):
    material = bpy.data.materials.new("lamp")
    material.use_nodes = True
    nodes = material.node_tree.nodes
    nodes.remove(nodes["Principled BSDF"])
    emission = nodes.new("ShaderNodeEmission")
    strength = max(radiance)
    emission.inputs["Color"].default_value = (*(c / strength for c in radiance), 1.0)
    emission.inputs["Strength"].default_value = strength  # Cycles: radiance = strength x colour
    material.node_tree.links.new(emission.outputs["Emission"], nodes["Material Output"].inputs["Surface"])
    return material


def _medium(bpy, sigma_t, albedo, g):
    material = bpy.data.materials.new("medium")
    material.use_nodes = True
    material.cycles.homogeneous_volume = True
    nodes, links = material.node_tree.nodes, material.node_tree.links
    nodes.remove(nodes["Principled BSDF"])  # no surface: the sphere only bounds the volume
    scatter, absorb, add = (nodes.new(kind) for kind in
                            ("ShaderNodeVolumeScatter", "ShaderNodeVolumeAbsorption", "ShaderNodeAddShader"))
    scatter.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    scatter.inputs["Density"].default_value = sigma_t * albedo
    scatter.inputs["Anisotropy"].default_value = g
    # Cycles absorbs `(1 - Color) * Density` (svm_closure.h): black, so that the absorption is the density.
    absorb.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
    absorb.inputs["Density"].default_value = sigma_t * (1.0 - albedo)
    links.new(scatter.outputs[0], add.inputs[0])
    links.new(absorb.outputs[0], add.inputs[1])
    links.new(add.outputs[0], nodes["Material Output"].inputs["Volume"])
    return material


def _add(bpy, kind, matrix, material):
    from mathutils import Matrix

    if kind == "cube":
        bpy.ops.mesh.primitive_cube_add(size=2.0)
        local = Matrix.Identity(4)
    elif kind == "cylinder":  # Mitsuba's: open, radius 1, along z from 0 to 1; Blender's: centred
        bpy.ops.mesh.primitive_cylinder_add(vertices=48, radius=1.0, depth=1.0, end_fill_type="NOTHING")
        local = Matrix.Translation((0.0, 0.0, 0.5))
    else:
        bpy.ops.mesh.primitive_uv_sphere_add(segments=64, ring_count=32, radius=1.0)
        local = Matrix.Identity(4)
    thing = bpy.context.active_object
    thing.matrix_world = _to_blender(matrix) @ local
    if kind != "cube":
        bpy.ops.object.shade_smooth()
    thing.data.materials.append(material)
    return thing


def build_and_render(
    description: dict, output: str, seed: int, samples: int, fog: bool, volume_bounces: int, threads: int = 1,
    light_view: dict | None = None,
) -> None:
    """Render the frame (or, with `light_view`'s `pixels`, `span` and `distance`, the sun's depth map, and write
    its camera beside it as `OUTPUT.json`: the docs' `light_view_from_camera` and `light_view_scale`)."""
    import bpy
    from mathutils import Matrix, Vector

    scene = bpy.context.scene
    for thing in list(bpy.data.objects):
        bpy.data.objects.remove(thing)
    render, cycles = scene.render, scene.cycles
    render.engine = "CYCLES"
    cycles.device = "CPU"
    cycles.samples = samples
    cycles.seed = seed
    cycles.use_adaptive_sampling = False
    cycles.use_denoising = False
    cycles.sample_clamp_direct = cycles.sample_clamp_indirect = 0.0
    cycles.max_bounces = cycles.diffuse_bounces = cycles.glossy_bounces = 1
    cycles.transmission_bounces, cycles.volume_bounces = 1, volume_bounces
    render.threads_mode, render.threads = "FIXED", threads
    render.resolution_x, render.resolution_y, render.resolution_percentage = description["width"], description["height"], 100
    for view_layer in scene.view_layers:
        view_layer.cycles.use_denoising = False
        view_layer.use_pass_combined = view_layer.use_pass_z = True

    lens = bpy.data.cameras.new("camera")
    lens.sensor_fit, lens.sensor_width = "HORIZONTAL", 36.0
    lens.lens = 18.0 / math.tan(math.radians(description["fov_x_deg"]) / 2)
    lens.clip_end = 1000.0
    camera = bpy.data.objects.new("camera", lens)
    scene.collection.objects.link(camera)
    scene.camera = camera
    camera.location = _point(description["camera"])
    camera.rotation_euler = (math.radians(90.0), 0.0, 0.0)  # looks along Blender's +y, our -z

    world = bpy.data.worlds.new("sky")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (*description["sky"], 1.0)
    scene.world = world

    bpy.ops.mesh.primitive_plane_add(size=400.0)
    bpy.context.active_object.data.materials.append(_diffuse(bpy, "ground", description["ground"]))
    for index, (kind, matrix, reflectance) in enumerate(description["shapes"]):
        _add(bpy, kind, matrix, _diffuse(bpy, f"shape_{index}", reflectance))

    light = description["light"]
    if "direction" in light:
        sun = bpy.data.lights.new("sun", "SUN")
        irradiance = light["irradiance"]
        sun.energy = max(irradiance)  # W/m^2 facing the sun
        sun.color = tuple(c / sun.energy for c in irradiance)
        sun.angle = math.radians(2.0 * light["radius_deg"])
        lamp = bpy.data.objects.new("sun", sun)
        scene.collection.objects.link(lamp)
        lamp.rotation_euler = Vector(_point(light["direction"])).to_track_quat("Z", "Y").to_euler()  # emits along -z
    for lamp_light in ([] if "direction" in light else [light]) + description.get("more_lights", []):
        bpy.ops.mesh.primitive_uv_sphere_add(segments=32, ring_count=16, radius=lamp_light["radius"],
                                             location=_point(lamp_light["position"]))
        bpy.ops.object.shade_smooth()
        bpy.context.active_object.data.materials.append(_emission(bpy, lamp_light["radiance"]))

    if fog:
        medium = description["medium"]
        bpy.ops.mesh.primitive_uv_sphere_add(segments=96, ring_count=48, radius=medium["extent"],
                                             location=_point(description["camera"]))
        bpy.context.active_object.data.materials.append(_medium(bpy, medium["sigma_t"], medium["albedo"], medium["g"]))

    if light_view is not None:  # the sun's orthographic camera, as docs/file_formats.md has a Blender user add it
        view = bpy.data.cameras.new("light_view")
        view.type, view.ortho_scale, view.clip_end = "ORTHO", light_view["span"], 10.0 * light_view["distance"]
        light_camera = bpy.data.objects.new("light_view", view)
        scene.collection.objects.link(light_camera)
        light_camera.rotation_euler = lamp.rotation_euler  # both look down their own -z
        light_camera.location = camera.location - light_view["distance"] * (lamp.rotation_euler.to_matrix() @ Vector((0, 0, -1)))
        scene.camera = light_camera
        render.resolution_x = render.resolution_y = light_view["pixels"]
        cycles.samples, cycles.filter_width = 1, 0.01  # one ray through each pixel's centre
        bpy.context.view_layer.update()
        flip = Matrix.Diagonal((1, 1, -1, 1))  # Blender camera axes -> x right, y up, z forward
        from_camera = flip @ light_camera.matrix_world.inverted() @ camera.matrix_world @ flip
        Path(output + ".json").write_text(json.dumps({
            "from_camera": [list(row) for row in from_camera[:3]], "scale": light_view["pixels"] / view.ortho_scale,
        }))  # fmt: skip

    render.use_stamp_lens = True
    settings = render.image_settings
    settings.file_format, settings.color_depth, settings.exr_codec = "OPEN_EXR_MULTILAYER", "16", "ZIP"
    if light_view is not None:
        settings.color_depth = "32"  # depths of hundreds of units: half floats keep 0.1-0.25 of a unit
    render.filepath = output
    bpy.ops.render.render(write_still=True)


# ----------------------------------------------------------------------------- driver


def describe(name: str) -> dict:
    """What Blender needs of `render_references.SCENES[name]`, as plain JSON values."""
    sys.path.insert(0, str(HERE))
    import render_references as mitsuba_scenes

    scene = mitsuba_scenes.SCENES[name]
    light = scene.light
    if isinstance(light, mitsuba_scenes.Sun):
        solid_angle = 2 * math.pi * (1 - math.cos(math.radians(light.radius_deg)))
        light_json = {"direction": [float(v) for v in light.direction()], "radius_deg": light.radius_deg,
                      "irradiance": [c * solid_angle for c in light.radiance]}
    else:
        light_json = {"position": list(light.position), "radius": light.radius, "radiance": list(light.radiance)}
    if isinstance(scene.medium.extent, tuple):
        raise ValueError(f"{name}: only a medium sphere around the camera is built in Blender here")
    if any(isinstance(other, mitsuba_scenes.Sun) for other in scene.more_lights):
        raise ValueError(f"{name}: only lamps beside the first light are built in Blender here")
    more = [{"position": list(other.position), "radius": other.radius, "radiance": list(other.radiance)}
            for other in scene.more_lights]  # fmt: skip
    return {
        "width": mitsuba_scenes.WIDTH, "height": mitsuba_scenes.HEIGHT, "fov_x_deg": mitsuba_scenes.FOV_X_DEG,
        "camera": list(scene.camera), "sky": list(light.sky), "ground": list(mitsuba_scenes.GROUND_REFLECTANCE),
        "shapes": [(kind, matrix, list(reflectance)) for kind, matrix, reflectance in scene.shapes],
        "light": light_json, "more_lights": more,
        "medium": {"sigma_t": scene.medium.sigma_t, "albedo": scene.medium.albedo, "g": scene.medium.g,
                   "extent": scene.medium.extent},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("scenes", nargs="*", help=f"default: {', '.join(SCENE_NAMES)}")
    parser.add_argument("--samples", type=int, default=256, help="fog samples per pixel (clean: 4x)")
    parser.add_argument("--blender", default="blender")
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--volume-bounces", type=int, default=1, help="Cycles' volume bounces (0: light scattered once)")
    parser.add_argument("--threads", type=int, default=1, help="Cycles' render threads")
    parser.add_argument("--light-view", action="store_true", help="also render a sun scene's depth seen from the sun")
    args = parser.parse_args()

    import numpy as np
    import OpenImageIO as oiio

    sys.path.insert(0, str(HERE))
    import render_references as mitsuba_scenes

    out = args.out
    out.mkdir(exist_ok=True)
    index_path = out / "scenes.json"
    for name in args.scenes or SCENE_NAMES:
        description = describe(name)
        seconds = {}

        def run_blender(key, **job):
            job = json.dumps({"description": description, "output": str(out / f"{name}_{key}.exr"),
                              "volume_bounces": args.volume_bounces, "threads": args.threads, **job})  # fmt: skip
            start, cpu = time.perf_counter(), _children_cpu()
            subprocess.run([args.blender, "-b", "--factory-startup", "--python", __file__, "--", job],
                           check=True, capture_output=True, text=True)
            seconds[key] = [round(time.perf_counter() - start, 1), round(_children_cpu() - cpu, 1)]

        if args.light_view:
            if "direction" not in description["light"]:
                raise SystemExit(f"{name}: --light-view is for a sun scene")
            view = {"pixels": mitsuba_scenes.LIGHT_VIEW_PIXELS, "span": mitsuba_scenes.LIGHT_VIEW_SPAN,
                    "distance": mitsuba_scenes.LIGHT_VIEW_DISTANCE}  # fmt: skip
            run_blender("light_view", seed=0, samples=1, fog=False, light_view=view)
            _set_light_view_attributes(out / f"{name}_light_view.exr")
        for key, seed in SEEDS.items():
            samples = args.samples * (CLEAN_SAMPLES_FACTOR if key == "clean" else 1)
            run_blender(key, seed=seed, samples=samples, fog=key != "clean")

        def rgb(key):
            buffer = oiio.ImageBuf(str(out / f"{name}_{key}.exr"))
            names = buffer.spec().channelnames
            pixels = buffer.get_pixels(oiio.FLOAT).astype(np.float64)
            return pixels[..., [names.index(f"ViewLayer.Combined.{c}") for c in "RGB"]]

        a, b = rgb("fog_a"), rgb("fog_b")
        floor = 0.5 * float(np.mean((a / (1 + np.abs(a)) - b / (1 + np.abs(b))) ** 2))
        scene = mitsuba_scenes.SCENES[name]
        light_px, in_front, light_depth = mitsuba_scenes.project(scene)
        record = mitsuba_scenes.record(scene, args.samples, seconds, floor, f"Blender {bpy_version(args.blender)} Cycles CPU")
        record.update(shows=f"{scene.shows} (Cycles)", light_px=list(light_px), light_in_front=in_front,
                      light_depth=None if math.isinf(light_depth) else light_depth)
        index = json.loads(index_path.read_text()) if index_path.exists() else {}
        index[PREFIX + name] = record
        index_path.write_text(json.dumps(dict(sorted(index.items())), indent=1) + "\n")
        print(f"{PREFIX}{name}: {seconds} s, noise floor {floor:.3e}", flush=True)


def _set_light_view_attributes(path: Path) -> None:
    """The three `godrays:light_view_*` attributes a Blender user sets with OpenImageIO (docs/file_formats.md), from
    the camera Blender wrote beside the map (`PATH.json`, then removed), on the map's depth channel."""
    import OpenImageIO as oiio

    camera_path = Path(f"{path}.json")
    camera = json.loads(camera_path.read_text())
    # Its depth channel alone (Blender writes the colour too, which no reader of the map takes): a smaller file.
    buffer = oiio.ImageBufAlgo.channels(oiio.ImageBuf(str(path)), ("ViewLayer.Depth.Z",))
    spec = buffer.specmod()
    spec.attribute("godrays:light_view_projection", "orthographic")
    spec.attribute("godrays:light_view_from_camera", " ".join(repr(float(v)) for row in camera["from_camera"] for v in row))
    spec.attribute("godrays:light_view_scale", repr(float(camera["scale"])))
    if not buffer.write(str(path)):
        raise SystemExit(f"{path}: {buffer.geterror()}")
    camera_path.unlink()


def _children_cpu() -> float:
    times = os.times()
    return times.children_user + times.children_system


def bpy_version(blender: str) -> str:
    first = subprocess.run([blender, "--version"], capture_output=True, text=True).stdout.splitlines()
    return first[0].replace("Blender", "").strip() if first else "?"


if __name__ == "__main__":
    try:
        import bpy  # noqa: F401  (run by Blender)
    except ImportError:
        main()
    else:
        job = json.loads(sys.argv[sys.argv.index("--") + 1])
        build_and_render(
            job["description"], job["output"], job["seed"], job["samples"], job["fog"], job["volume_bounces"],
            job.get("threads", 1), job.get("light_view"),
        )  # fmt: skip
