"""Scenes from JSON or TOML files (or the equivalent dicts) and meshes from Wavefront OBJ.

A scene file holds one table (all keys optional unless marked):

    camera:  {position, target, up, fov_x_deg, width, height, near, far}   (required)
    light:   {type: "directional", direction, color} | {type: "point", position, color}
    lights:  [light, ...]   (instead of `light`: several, the first as `light`, the others beside it)
    sky:     {zenith_color, horizon_color, sun_color, sun_distance, sun_sharpness}
    ambient: [r, g, b]
    materials: {name: {albedo, emission, atmosphere_color, atmosphere_sharpness,
                       night_color, night_sharpness}}
    objects: [ {type: "sphere", name, center, radius, material},
               {type: "mesh", name, obj | (vertices, faces[, normals]), material,
                translation, rotation_deg, scale, double_sided},
               {type: "uv_sphere", name, segments, rings, ...mesh transform keys} ]  (required)
    sun: the name (or index) of the object that is the visible light source

`material` is a material name or an inline material table. Relative OBJ paths
are relative to the scene file. Every unknown key, missing key or bad value
raises `ValueError` naming it (`objects[2].radius: ...`).
"""

import json
import os
import tomllib
from pathlib import Path

import numpy as np

from godrays_jax.primitives.camera import Camera
from godrays_jax.raster.scene import (
    DirectionalLight,
    Material,
    Mesh,
    PointLight,
    Scene,
    Sky,
    Sphere,
)

_CAMERA_KEYS = {"position", "target", "up", "fov_x_deg", "width", "height", "near", "far"}
_MATERIAL_KEYS = {"albedo", "emission", "atmosphere_color", "atmosphere_sharpness", "night_color", "night_sharpness"}
_SKY_KEYS = {"zenith_color", "horizon_color", "sun_color", "sun_distance", "sun_sharpness"}
_TRANSFORM_KEYS = {"translation", "rotation_deg", "scale", "double_sided"}
_OBJECT_KEYS = {
    "sphere": {"type", "name", "center", "radius", "material"},
    "mesh": {"type", "name", "obj", "vertices", "faces", "normals", "material"} | _TRANSFORM_KEYS,
    "uv_sphere": {"type", "name", "segments", "rings", "material"} | _TRANSFORM_KEYS,
}
_SCENE_KEYS = {"camera", "light", "lights", "sky", "ambient", "materials", "objects", "sun"}


def _check_keys(where: str, table: object, allowed: set[str], required: set[str] = frozenset()) -> dict:
    if not isinstance(table, dict):
        raise ValueError(f"{where}: expected a table, got {type(table).__name__}")
    for key in table:
        if key not in allowed:
            raise ValueError(f"{where}.{key}: unknown key (expected one of {', '.join(sorted(allowed))})")
    for key in sorted(required - table.keys()):
        raise ValueError(f"{where}.{key}: missing")
    return table


def _build(where: str, make, **fields):
    """Construct, re-raising a constructor's complaint with the file location."""
    try:
        return make(**fields)
    except (ValueError, TypeError) as error:
        raise ValueError(f"{where}: {error}") from None


def uv_sphere(*, segments: int = 32, rings: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Unit sphere vertices `(V, 3)` (also its normals) and CCW faces `(F, 3)`:
    `2 * segments * (rings - 1)` triangles."""
    if segments < 3 or rings < 2:
        raise ValueError(f"uv_sphere: need segments >= 3 and rings >= 2, got {segments}, {rings}")
    polar = np.linspace(0, np.pi, rings + 1)[1:-1]
    azimuth = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    ring = np.stack(
        [np.sin(polar)[:, None] * np.cos(azimuth), np.repeat(np.cos(polar)[:, None], segments, 1), -np.sin(polar)[:, None] * np.sin(azimuth)],
        axis=-1,
    ).reshape(-1, 3)
    vertices = np.concatenate([[[0.0, 1.0, 0.0]], ring, [[0.0, -1.0, 0.0]]])
    j = np.arange(segments)
    nxt = (j + 1) % segments
    faces = [np.stack([np.zeros(segments, int), 1 + j, 1 + nxt], 1)]
    for i in range(rings - 2):
        a, b = 1 + i * segments + j, 1 + i * segments + nxt
        c, d = a + segments, b + segments
        faces += [np.stack([a, c, d], 1), np.stack([a, d, b], 1)]
    last = len(vertices) - 1
    base = 1 + (rings - 2) * segments
    faces.append(np.stack([np.full(segments, last), base + nxt, base + j], 1))
    return vertices, np.concatenate(faces)


def load_obj(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Read a Wavefront OBJ: vertices `(V, 3)`, triangle faces `(F, 3)` (polygons
    fanned), and per-vertex normals `(V, 3)` when every face corner names one
    (`None` otherwise). Raises `ValueError` naming the file (and line) if it
    cannot be read or parsed."""
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as error:
        raise ValueError(f"OBJ file {os.fspath(path)!r}: cannot read ({error})") from None
    positions, normals, faces, corner_normals = [], [], [], []
    for number, line in enumerate(text.splitlines(), 1):
        fields = line.split("#", 1)[0].split()
        if not fields:
            continue
        try:
            if fields[0] == "v":
                positions.append([float(x) for x in fields[1:4]])
            elif fields[0] == "vn":
                normals.append([float(x) for x in fields[1:4]])
            elif fields[0] == "f":
                corners = []
                for corner in fields[1:]:
                    parts = corner.split("/")
                    vertex = int(parts[0])
                    normal = int(parts[2]) if len(parts) > 2 and parts[2] else None
                    corners.append(
                        (vertex - 1 if vertex > 0 else len(positions) + vertex,
                         None if normal is None else (normal - 1 if normal > 0 else len(normals) + normal))
                    )
                if len(corners) < 3:
                    raise ValueError("a face needs at least 3 vertices")
                for k in range(1, len(corners) - 1):
                    triangle = (corners[0], corners[k], corners[k + 1])
                    faces.append([c[0] for c in triangle])
                    corner_normals.append([c[1] for c in triangle])
        except (ValueError, IndexError) as error:
            raise ValueError(f"OBJ file {os.fspath(path)!r} line {number}: cannot parse {line.strip()!r} ({error})") from None
    if len(positions) < 3 or not faces:
        raise ValueError(f"OBJ file {os.fspath(path)!r}: no triangles (needs 'v' and 'f' lines)")
    vertices = np.asarray(positions, np.float32)
    faces = np.asarray(faces, np.int64)
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ValueError(f"OBJ file {os.fspath(path)!r}: a face indexes a missing vertex")
    vertex_normals = None
    if normals and all(n is not None for corner in corner_normals for n in corner):
        vertex_normals = np.zeros_like(vertices)
        vertex_normals[faces.ravel()] = np.asarray(normals, np.float32)[np.asarray(corner_normals).ravel()]
    return vertices, faces, vertex_normals


def _material(where: str, value, materials: dict[str, Material]) -> Material:
    if value is None:
        return Material()
    if isinstance(value, str):
        if value not in materials:
            raise ValueError(f"{where}: unknown material {value!r} (defined: {', '.join(sorted(materials)) or 'none'})")
        return materials[value]
    return _build(where, Material, **_check_keys(where, value, _MATERIAL_KEYS))


def _object(where: str, table: dict, materials: dict[str, Material], base: Path) -> Sphere | Mesh:
    if not isinstance(table, dict) or table.get("type") not in _OBJECT_KEYS:
        raise ValueError(f"{where}.type: must be one of {', '.join(sorted(_OBJECT_KEYS))}")
    kind = table["type"]
    _check_keys(where, table, _OBJECT_KEYS[kind])
    material = _material(f"{where}.material", table.get("material"), materials)
    if kind == "sphere":
        _check_keys(where, table, _OBJECT_KEYS[kind], {"center", "radius"})
        return _build(where, Sphere, center=table["center"], radius=table["radius"], material=material)
    transform = {key: table[key] for key in _TRANSFORM_KEYS if key in table}
    if kind == "uv_sphere":
        vertices, faces = uv_sphere(segments=table.get("segments", 32), rings=table.get("rings", 16))
        return _build(where, Mesh, vertices=vertices, faces=faces, normals=vertices, material=material, **transform)
    if "obj" in table:
        if {"vertices", "faces", "normals"} & table.keys():
            raise ValueError(f"{where}: give either 'obj' or 'vertices' and 'faces', not both")
        vertices, faces, normals = load_obj(base / table["obj"])
    else:
        _check_keys(where, table, _OBJECT_KEYS[kind], {"vertices", "faces"})
        vertices, faces, normals = table["vertices"], table["faces"], table.get("normals")
    return _build(where, Mesh, vertices=vertices, faces=faces, normals=normals, material=material, **transform)


def scene_from_dict(table: dict, *, base_dir: str | os.PathLike = ".") -> tuple[Scene, Camera]:
    """Build `(scene, camera)` from a parsed scene table (see the module docstring)."""
    _check_keys("scene", table, _SCENE_KEYS, {"camera", "objects"})
    camera = _build("camera", Camera, **_check_keys("camera", table["camera"], _CAMERA_KEYS, {"position", "target", "up", "fov_x_deg", "width", "height"}))
    materials = {
        name: _build(f"materials.{name}", Material, **_check_keys(f"materials.{name}", value, _MATERIAL_KEYS))
        for name, value in _check_keys("materials", table.get("materials", {}), set(table.get("materials", {}))).items()
    }
    if not isinstance(table["objects"], list) or not table["objects"]:
        raise ValueError("objects: must be a non-empty list")
    objects = tuple(_object(f"objects[{i}]", entry, materials, Path(base_dir)) for i, entry in enumerate(table["objects"]))
    names = [entry.get("name") for entry in table["objects"]]

    if "light" in table and "lights" in table:
        raise ValueError("lights: give light or lights, not both")
    if "lights" in table:
        if not isinstance(table["lights"], list) or not table["lights"]:
            raise ValueError("lights: must be a non-empty list")
        light, *other_lights = (_light(f"lights[{i}]", entry) for i, entry in enumerate(table["lights"]))
    else:
        light, other_lights = _light("light", table.get("light", {"type": "directional", "direction": [0, 0, 1]})), []

    sun = table.get("sun")
    if isinstance(sun, str):
        if sun not in names:
            raise ValueError(f"sun: no object named {sun!r}")
        sun = names.index(sun)
    sky = _build("sky", Sky, **_check_keys("sky", table.get("sky", {}), _SKY_KEYS))
    scene = _build("scene", Scene, objects=objects, light=light, sky=sky, ambient=table.get("ambient", (0.0, 0.0, 0.0)),
                   sun=sun, other_lights=tuple(other_lights))  # fmt: skip
    return scene, camera


def _light(where: str, light_table: object) -> DirectionalLight | PointLight:
    """A light's table (`light`, or an entry of `lights`) as a `DirectionalLight` or `PointLight`."""
    kind = light_table.get("type") if isinstance(light_table, dict) else None
    kinds = {"directional": (DirectionalLight, "direction"), "point": (PointLight, "position")}
    if kind not in kinds:
        raise ValueError(f"{where}.type: must be 'directional' or 'point'")
    make, place = kinds[kind]
    fields = _check_keys(where, light_table, {"type", place, "color"}, {place})
    return _build(where, make, **{key: value for key, value in fields.items() if key != "type"})


def load_scene(path: str | os.PathLike) -> tuple[Scene, Camera]:
    """Read a `.json` or `.toml` scene file; see the module docstring for its keys."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as error:
        raise ValueError(f"scene file {os.fspath(path)!r}: cannot read ({error})") from None
    try:
        table = tomllib.loads(text) if path.suffix.lower() == ".toml" else json.loads(text)
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as error:
        raise ValueError(f"scene file {os.fspath(path)!r}: not valid {'TOML' if path.suffix.lower() == '.toml' else 'JSON'} ({error})") from None
    try:
        return scene_from_dict(table, base_dir=path.parent)
    except ValueError as error:
        raise ValueError(f"scene file {os.fspath(path)!r}: {error}") from None
