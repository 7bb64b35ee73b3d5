"""Render the hero scene (a low sun behind a forest) and ship its buffers as examples/data/forest_hero.exr.

    python examples/make_hero_frame.py [--obj] [--out PATH]

`--obj` first regenerates examples/scenes/forest.obj (36 tapered trunks, each
with 4-7 branches ending in 2-4 leaf clumps; deterministic) from the seed
below. The frame is rendered by the project's rasterizer, exactly as
`godrays-jax render examples/scenes/forest_hero.json -o X.exr --light` does,
and written with half-float colour (about 1 MB): colour, depth, coverage,
seed 004's light pass and seed 000's glow pass; the light's pixel position and
distance and the camera's field of view and clip planes in the metadata. Runs from any directory.
"""

import argparse
from pathlib import Path

import numpy as np

import godrays_jax as gr
from godrays_jax.app.render_command import frame_lights, frame_metadata

EXAMPLES = Path(__file__).resolve().parent
SCENE = EXAMPLES / "scenes" / "forest_hero.json"
OBJ = EXAMPLES / "scenes" / "forest.obj"
FRAME = EXAMPLES / "data" / "forest_hero.exr"
SEED = 5
TRUNKS = 36


def _outward(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Faces of a convex-ish part turned counter-clockwise seen from outside (the rasterizer culls back faces)."""
    corners = vertices[faces]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    outward = np.einsum("fi,fi->f", normal, corners.mean(1) - vertices.mean(0)) >= 0
    return np.where(outward[:, None], faces, faces[:, ::-1])


def _prism(rng, start, end, radius_start, radius_end, sides):
    """A tapered closed prism from `start` to `end`."""
    axis = (end - start) / np.linalg.norm(end - start)
    a = np.cross(axis, [0.3, 0.1, 1.0] if abs(axis[2]) < 0.9 else [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(axis, a)
    angles = np.linspace(0, 2 * np.pi, sides, endpoint=False) + rng.uniform(0, 1)
    ring = np.cos(angles)[:, None] * a + np.sin(angles)[:, None] * b
    vertices = np.concatenate([start + radius_start * ring, end + radius_end * ring, [start, end]])
    faces = []
    for i in range(sides):
        j = (i + 1) % sides
        faces += [[i, j, sides + j], [i, sides + j, sides + i], [2 * sides, j, i], [2 * sides + 1, sides + i, sides + j]]
    return vertices, np.asarray(faces)


def _clump(rng, centre, radius):
    """A lumpy, flattened icosahedron: a clump of leaves."""
    t = (1 + 5**0.5) / 2
    vertices = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
                         [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float)  # fmt: skip
    vertices /= np.linalg.norm(vertices, axis=1, keepdims=True)
    faces = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
                      [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
                      [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])  # fmt: skip
    vertices = vertices * radius * rng.uniform(0.7, 1.3, size=(12, 1)) * np.array([1.0, 0.6, 1.0])
    return vertices + centre, faces


def forest(seed: int = SEED, trunks: int = TRUNKS) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and faces of the forest: half the trunks gathered toward the sun's bearing, so it is cut into many gaps."""
    rng = np.random.default_rng(seed)
    parts = []
    for k in range(trunks):
        z = -rng.uniform(2, 45)
        spread = rng.normal(0, 0.45) if k % 2 else rng.uniform(-0.9, 0.9)
        x = spread * (6 + 0.8 * abs(z)) - 0.14 * abs(z)
        radius = rng.uniform(0.18, 0.45)
        height = rng.uniform(14, 20)
        lean = rng.normal(0, 0.6, 2)
        base, top = np.array([x, -0.5, z]), np.array([x + lean[0], height, z + lean[1]])
        parts.append(_prism(rng, base, top, radius, radius * 0.55, 7))
        for _ in range(rng.integers(4, 8)):
            t = rng.uniform(0.45, 0.9)
            start = base * (1 - t) + top * t
            direction = rng.normal(0, 1, 3)
            direction[1] = abs(direction[1]) * 0.6 + 0.3
            end = start + direction / np.linalg.norm(direction) * rng.uniform(2.0, 4.5)
            parts.append(_prism(rng, start, end, radius * 0.35, radius * 0.12, 5))
            for _ in range(rng.integers(2, 5)):
                parts.append(_clump(rng, end + rng.normal(0, 0.9, 3) * [1, 0.5, 1], rng.uniform(0.5, 1.1)))
    vertices, faces, offset = [], [], 0
    for part_vertices, part_faces in parts:
        vertices.append(part_vertices)
        faces.append(_outward(part_vertices, part_faces) + offset)
        offset += len(part_vertices)
    return np.concatenate(vertices), np.concatenate(faces)


def write_obj(path: Path) -> None:
    vertices, faces = forest()
    lines = [f"# forest: {TRUNKS} tapered trunks, branches and leaf clumps (examples/make_hero_frame.py --obj, seed {SEED})"]
    lines += [f"v {x:.4f} {y:.4f} {z:.4f}" for x, y, z in vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")
    print(f"wrote {path}: {len(vertices)} vertices, {len(faces)} triangles")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--obj", action="store_true", help="regenerate examples/scenes/forest.obj first")
    parser.add_argument("--out", type=Path, default=FRAME, help=f"the frame to write (default {FRAME})")
    args = parser.parse_args()
    if args.obj:
        write_obj(OBJ)
    scene, camera = gr.load_scene(SCENE)
    buffers = gr.render(scene, camera)
    lights = frame_lights(scene, camera)
    # Normals and object ids serve no effect: leaving them out halves the file.
    shipped = gr.Buffers(color=buffers.color, depth=buffers.depth, coverage=buffers.coverage,
                         light_pass=buffers.light_pass, glow_pass=buffers.glow_pass)  # fmt: skip
    light = lights[0].xy
    gr.write_buffers(args.out, shipped, light_xy=light, light_in_front=lights[0].in_front, half=True,
                     metadata=frame_metadata(camera, lights))  # fmt: skip
    print(f"wrote {args.out}: {camera.width}x{camera.height}, light at ({light[0]:.1f}, {light[1]:.1f}) px")


if __name__ == "__main__":
    main()
