"""Visibility per pixel: antialiased coverage of triangles and spheres, the front, behind and hit layers, their surfaces."""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from godrays_jax.primitives.camera import Camera
from godrays_jax.raster.geometry import AREA, BOX, EDGE_C, EDGE_X, EDGE_Y, INV_DEPTH, TABLE_CORNERS, TABLE_NORMALS
from godrays_jax.raster.vectors import dot, unit_first


class Layer(eqx.Module):
    """What one compositing layer sees in each pixel (view space)."""

    object_id: Int[Array, "*P"]  # -1 where the layer is empty
    coverage: Float[Array, "*P"]
    position: Float[Array, "3 *P"]  # component first
    normal: Float[Array, "3 *P"]


class Layers(eqx.Module):
    front: Layer  # the nearest object touching the pixel
    behind: Layer  # the nearest other object touching it
    hit: Layer  # what the pixel centre hits (coverage unused)


def object_weight(layers: Layers, target: int) -> Float[Array, "H W"]:
    """Coverage of object `target` seen through the two layers."""
    front, behind = layers.front, layers.behind
    return front.coverage * (front.object_id == target) + (1.0 - front.coverage) * behind.coverage * (behind.object_id == target)


def total_coverage(layers: Layers) -> Float[Array, "H W"]:
    return layers.front.coverage + (1.0 - layers.front.coverage) * layers.behind.coverage


def _sphere_terms(centers: Float[Array, "*B K 3"], radii: Float[Array, "*B K"], camera: Camera, px: Float[Array, "*B P 1"], py: Float[Array, "*B P 1"]):
    """Signed silhouette distance (px), reciprocal view depth and area cap per (pixel, sphere)."""
    f = camera.focal_px
    dx, dy = (px - 0.5 * camera.width) / f, (0.5 * camera.height - py) / f
    cx, cy, cz = (centers[..., None, :, i] for i in range(3))
    radii = radii[..., None, :]
    dd = dx * dx + dy * dy + 1.0
    dc = dx * cx + dy * cy + cz
    inner = cx * cx + cy * cy + cz * cz - radii**2
    cone = dc**2 - dd * inner
    gradient_x = 2 * dc * cx - 2 * dx * inner
    gradient_y = 2 * dc * cy - 2 * dy * inner
    gradient_px = jnp.sqrt(gradient_x**2 + gradient_y**2 + 1e-30) / f
    camera_inside = inner < 0
    distance = jnp.where(camera_inside, jnp.inf, jnp.where(dc > 0, cone / gradient_px, -jnp.inf))
    positive_cone = jnp.where(cone > 0, cone, 1.0)
    root = jnp.where(cone > 0, jnp.sqrt(positive_cone), 0.0)
    depth = jnp.where(camera_inside, dc + root, dc - root) / dd
    center_depth = jnp.maximum(cz, camera.near)
    area = jnp.where(camera_inside, jnp.inf, jnp.pi * (f * radii / center_depth) ** 2)
    return distance, 1.0 / jnp.maximum(depth, 1e-30), area


class _Picks(eqx.Module):
    """Per pixel, from one set of candidates (a tile's triangles, or its
    spheres): the front, behind and hit layers' keys, primitive indices and
    objects (-1 for none), and the front and behind objects' coverage."""

    key: Int[Array, "3 *B P"]
    index: Int[Array, "3 *B P"]
    object: Int[Array, "3 *B P"]
    coverage: Float[Array, "2 *B P"]


def no_picks(pixels: tuple[int, ...]) -> _Picks:
    none = jnp.full((3, *pixels), -1, jnp.int32)
    return _Picks(key=none, index=none, object=none, coverage=jnp.zeros((2, *pixels)))


def _picks(distance, inverse_depth, area, candidate_object, candidate_index, camera: Camera, slot_bits: int) -> _Picks:
    """The three layers among `(B, P, K)` candidate terms.

    Nearest-candidate search is one integer max: the reciprocal depth's bits
    (monotonic for positive floats) with the slot number in the low bits;
    `slot_bits` is the same for every set, so keys of different sets compare."""
    in_depth_range = (inverse_depth <= 1.0 / camera.near) & (inverse_depth >= 1.0 / camera.far)
    coverage = jnp.where(in_depth_range, jnp.clip(0.5 + distance, 0.0, jnp.minimum(area, 1.0)), 0.0)
    depth_bits = jax.lax.bitcast_convert_type(jax.lax.stop_gradient(jnp.maximum(inverse_depth, 0.0)), jnp.int32)
    keys = ((depth_bits >> slot_bits) << slot_bits) | jnp.arange(distance.shape[-1], dtype=jnp.int32)
    nearest = lambda where: jnp.max(jnp.where(where, keys, -1), axis=-1)
    # Keys are unique within a set and never -1, so matching a key selects one
    # candidate (none for -1) without a gather.
    of = lambda key, values: jnp.max(jnp.where(keys == key[..., None], values, -1), axis=-1)
    touching = coverage > 0
    front_key = nearest(touching)
    front_object = of(front_key, candidate_object)
    behind_key = nearest(touching & (candidate_object != front_object[..., None]))
    hit_key = nearest(in_depth_range & (distance >= 0))
    key = jnp.stack([front_key, behind_key, hit_key])
    return _Picks(
        key=key,
        index=jnp.stack([of(k, candidate_index) for k in key]),
        object=jnp.stack([front_object, of(behind_key, candidate_object), of(hit_key, candidate_object)]),
        coverage=jnp.stack([
            # Padding candidates (object -1) never cover anything.
            jnp.minimum(jnp.sum(jnp.where(candidate_object == obj[..., None], coverage, 0.0), axis=-1), 1.0)
            for obj in (front_object, of(behind_key, candidate_object))
        ]),
    )


def triangle_picks(setup, objects, candidates: Int[Array, "B K"], px, py, camera: Camera, slot_bits: int) -> _Picks:
    rows = setup[candidates][:, None]
    x, y = px[..., None], py[..., None]
    edge_x, edge_y, edge_c = rows[..., EDGE_X], rows[..., EDGE_Y], rows[..., EDGE_C]
    edge = lambda i: x * edge_x[..., i] + y * edge_y[..., i] + edge_c[..., i]
    # The bounding box's sides join the three edges: past a sliver's sharp
    # corner the edges alone would leave coverage leaking along its extension.
    box = rows[..., BOX]
    box_distance = jnp.minimum(jnp.minimum(x - box[..., 0], box[..., 2] - x), jnp.minimum(y - box[..., 1], box[..., 3] - y))
    distance = jnp.minimum(jnp.minimum(jnp.minimum(edge(0), edge(1)), edge(2)), box_distance)
    plane = rows[..., INV_DEPTH]
    inverse_depth = x * plane[..., 0] + y * plane[..., 1] + plane[..., 2]
    return _picks(distance, inverse_depth, rows[..., AREA], objects[candidates][:, None], candidates[:, None], camera, slot_bits)


def sphere_picks(centers, radii, objects, candidates: Int[Array, "B K"], px, py, camera: Camera, slot_bits: int) -> _Picks:
    distance, inverse_depth, area = _sphere_terms(centers[candidates], radii[candidates], camera, px[..., None], py[..., None])
    return _picks(distance, inverse_depth, area, objects[candidates][:, None], candidates[:, None], camera, slot_bits)


def merge_picks(triangles: _Picks, spheres: _Picks) -> tuple[tuple[Array, ...], ...]:
    """The front, behind and hit layers of the union of both sets, each as
    `(from_triangles, key, index, object, coverage)`. An object is a mesh or a
    sphere, never both, so its coverage lies in one set, and the nearest other
    object is the other set's front or the winning set's behind."""

    def layer(picks: _Picks, i: int) -> tuple[Array, ...]:
        coverage = picks.coverage[i] if i < 2 else (picks.key[i] >= 0).astype(jnp.float32)
        return picks.key[i], picks.index[i], picks.object[i], coverage

    def nearer(triangle, sphere):
        from_triangles = triangle[0] >= sphere[0]
        return (from_triangles, *(jnp.where(from_triangles, a, b) for a, b in zip(triangle, sphere)))

    front = nearer(layer(triangles, 0), layer(spheres, 0))
    either = lambda a, b: tuple(jnp.where(front[0], x, y) for x, y in zip(a, b))
    behind = nearer(either(layer(triangles, 1), layer(triangles, 0)), either(layer(spheres, 0), layer(spheres, 1)))
    return front, behind, nearer(layer(triangles, 2), layer(spheres, 2))


def triangle_surface(columns: Float[Array, "27 P"], px: Float[Array, "P"], py: Float[Array, "P"]) -> tuple[Float[Array, "3 P"], Float[Array, "3 P"]]:
    """View-space position and unnormalised shading normal from `triangle_table`
    columns; barycentric weights are clamped to the triangle, so a silhouette
    pixel whose centre lies outside takes the triangle's nearest point."""
    weights = [columns[3 * i] * px + columns[3 * i + 1] * py + columns[3 * i + 2] for i in range(3)]
    total = weights[0] + weights[1] + weights[2]
    weights = [jnp.maximum(w / jnp.where(total == 0, 1.0, total), 0.0) for w in weights]
    total = jnp.maximum(weights[0] + weights[1] + weights[2], 1e-12)
    weights = [w / total for w in weights]
    blend = lambda start: jnp.stack([sum(weights[i] * columns[start + 3 * i + c] for i in range(3)) for c in range(3)])
    return blend(TABLE_CORNERS), blend(TABLE_NORMALS)


def sphere_surface(center: Float[Array, "3 P"], radius: Float[Array, "P"], rays: Float[Array, "3 P"]) -> tuple[Float[Array, "3 P"], Float[Array, "3 P"]]:
    """The ray's hit, or its closest approach to the sphere at silhouettes."""
    unit = unit_first(rays)
    along = dot(unit, center)
    center_squared = dot(center, center)
    chord_squared = radius**2 - (center_squared - along**2)
    positive = jnp.where(chord_squared > 0, chord_squared, 1.0)
    half_chord = jnp.where(chord_squared > 0, jnp.sqrt(positive), 0.0)
    camera_inside = center_squared < radius**2
    position = unit * jnp.where(camera_inside, along + half_chord, along - half_chord)
    normal = (position - center) / radius
    return position, jnp.where(camera_inside, -normal, normal)
