"""The jitted rasterizer: `render(scene, camera) -> Buffers`.

How it works (all inside one `jit`):

1. Triangles are set up in view space as 2D-homogeneous edge functions
   (Olano & Greer 1997): each edge, and the reciprocal depth, is an affine
   function of the pixel position, which stays exact for triangles crossing the
   camera plane, so nothing is clipped. Back faces of single-sided meshes,
   degenerate and out-of-view triangles are culled.
2. Binning: triangles, sorted front to back, are listed per 64 px tile and
   then per 16 px tile (`tile_size`), keeping at most `tile_capacity` per tile;
   when a tile holds more, the farthest are dropped (they are the likeliest to
   be hidden). Spheres are listed per tile from their projected bounding cubes.
   Tiles are sorted by load and evaluated 16 at a time, each batch with the
   smallest bucket (0, 1, 2, 4, ... candidates) that holds its busiest tile,
   chosen by `lax.switch`: sky costs only its colour, and busy tiles do not
   pad quiet ones. Shading happens in the same loop, so only tiles with
   geometry are shaded.
3. Per pixel, every candidate gives a hard inside test at the pixel centre and
   an antialiased coverage: an analytic edge term, `clip(0.5 + s, 0, 1)` with
   `s` the signed distance in pixels from the pixel centre to the primitive's
   outline (a triangle's nearest edge, or a sphere's projected silhouette
   from its exact implicit cone), capped by the primitive's projected area.
   This is the exact box-filtered coverage of a straight edge through the pixel
   and is a smooth function of the geometry, so coverage and colour have
   non-zero gradients at silhouettes (no supersampling).
4. Two layers are composited per pixel: the nearest object touching the pixel
   and the nearest other object behind it, each with its coverage (the sum of
   its primitives' coverage, clipped to 1, which is exact across a mesh's shared
   edges), over the sky. Depth, normal and object id are the hard values at the
   pixel centre.
5. The glow pass (the sun-overcasting article) rasterizes the scaled geometry again, but only in
   the tiles that the enlarged sun object (or, without one, the sky's sun spot)
   overlaps: everything else is transparent black, so the pass is zero there.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from godrays_jax.kernels.lens import sun_spot_intensity
from godrays_jax.primitives.buffers import Buffers
from godrays_jax.primitives.camera import Camera, project_point, unit_vectors
from godrays_jax.raster.scene import DirectionalLight, Scene, Sphere

GLOW_SOURCE_SCALE = 1.3
GLOW_OCCLUDER_SCALE = 0.8
GLOW_COLOR = (0.8, 0.5, 0.0, 0.65)
DEFAULT_TILE_CAPACITY = 128

_COARSE_TILES_PER_SIDE = 4
# A coarse tile keeps up to this many times a fine tile's capacity: triangles
# span several fine tiles, so a coarse tile holds a few times its busiest fine tile's load.
_COARSE_CAPACITY_FACTOR = 4
# Fine tiles evaluated together; tile grids are multiples of 4 x 4 tiles.
_TILES_PER_BATCH = 16
# Columns of the per-triangle setup table.
_EDGE_X, _EDGE_Y, _EDGE_C = slice(0, 3), slice(3, 6), slice(6, 9)
_INV_DEPTH = slice(9, 12)
_AREA = 12
_BOX = slice(13, 17)
# Rows of the per-triangle shading table (`_triangle_table`), component first: the barycentric numerators as
# affine functions of the pixel position (3 per corner), then the corners, then the shading normals (3 each).
_TABLE_CORNERS = 9
_TABLE_NORMALS = 18


class _Geometry(eqx.Module):
    """Everything flattened: triangles (N) then spheres (S), in view space."""

    corners: Float[Array, "N 3 3"]
    corner_normals: Float[Array, "N 3 3"]
    triangle_object: Int[Array, "N"]
    triangle_drawn: Array
    centers: Float[Array, "S 3"]
    radii: Float[Array, "S"]
    sphere_object: Int[Array, "S"]


def _flatten(scene: Scene, camera: Camera, object_scales: tuple[float | None, ...] | None) -> _Geometry:
    corners, normals, triangle_object, triangle_drawn = [], [], [], []
    centers, radii, sphere_object = [], [], []
    right, up, forward = camera.basis()
    to_view = jnp.stack([right, up, forward], axis=1)
    for index, obj in enumerate(scene.objects):
        scale = 1.0 if object_scales is None else object_scales[index]
        if isinstance(obj, Sphere):
            centers.append(camera.to_view(obj.center))
            radii.append(obj.radius * scale)
            sphere_object.append(index)
        else:
            world, world_normals = obj.world_triangles(local_scale=scale)
            face_normal = jnp.cross(world[:, 1] - world[:, 0], world[:, 2] - world[:, 0])
            facing_camera = jnp.einsum("fi,fi->f", world[:, 0] - camera.position, face_normal, precision="highest") < 0
            corners.append(camera.to_view(world))
            normals.append(jnp.matmul(world_normals, to_view, precision="highest"))
            triangle_object.append(jnp.full(world.shape[0], index, jnp.int32))
            triangle_drawn.append(facing_camera | obj.double_sided)
    if not corners:
        # Scenes of spheres alone get one culled placeholder triangle, so that
        # the binning's shapes are never empty.
        corners, normals = [jnp.eye(3)[None]], [jnp.eye(3)[None]]
        triangle_object, triangle_drawn = [jnp.array([-1], jnp.int32)], [jnp.array([False])]
    return _Geometry(
        corners=jnp.concatenate(corners),
        corner_normals=jnp.concatenate(normals),
        triangle_object=jnp.concatenate(triangle_object),
        triangle_drawn=jnp.concatenate(triangle_drawn),
        centers=jnp.stack(centers) if centers else jnp.zeros((0, 3)),
        radii=jnp.stack(radii) if radii else jnp.zeros((0,)),
        sphere_object=jnp.asarray(sphere_object, jnp.int32),
    )


def _pixel_affine(vectors: Float[Array, "*N 3"], camera: Camera) -> Float[Array, "*N 3"]:
    """Coefficients (a, b, c) with `v . d(px, py) = a px + b py + c`, where
    `d = ((px - W/2) / f, (H/2 - py) / f, 1)` is the view ray through pixel
    position (px, py)."""
    f = camera.focal_px
    a = vectors[..., 0] / f
    b = -vectors[..., 1] / f
    c = vectors[..., 2] - a * (0.5 * camera.width) - b * (0.5 * camera.height)
    return jnp.stack([a, b, c], axis=-1)


def _triangle_setup(geometry: _Geometry, camera: Camera) -> tuple[Float[Array, "N 13"], Array]:
    """Per-triangle edge, reciprocal-depth and area terms; and which are drawn."""
    v0, v1, v2 = geometry.corners[:, 0], geometry.corners[:, 1], geometry.corners[:, 2]
    edge_normals = jnp.stack([jnp.cross(v1, v2), jnp.cross(v2, v0), jnp.cross(v0, v1)], axis=1)
    plane = edge_normals.sum(axis=1)
    plane_offset = jnp.einsum("ni,ni->n", v0, plane, precision="highest")
    orientation = jnp.where(plane_offset < 0, -1.0, 1.0)
    edges = _pixel_affine(edge_normals, camera)
    edge_gradient = jnp.sqrt(jnp.sum(edges[..., :2] ** 2, axis=-1, keepdims=True) + 1e-30)
    edges = edges * (orientation[:, None, None] / edge_gradient)
    safe_offset = jnp.where(plane_offset == 0, 1.0, plane_offset)
    inverse_depth = _pixel_affine(plane / safe_offset[:, None], camera)

    depth = geometry.corners[..., 2]
    all_in_front = depth.min(axis=1) > camera.near
    focal = camera.focal_px
    projected = geometry.corners[..., :2] * (focal / jnp.where(all_in_front[:, None], depth, 1.0))[..., None]
    area_px = 0.5 * jnp.abs(
        (projected[:, 1, 0] - projected[:, 0, 0]) * (projected[:, 2, 1] - projected[:, 0, 1])
        - (projected[:, 2, 0] - projected[:, 0, 0]) * (projected[:, 1, 1] - projected[:, 0, 1])
    )
    area_px = jnp.where(all_in_front, area_px, jnp.inf)
    drawn = (
        geometry.triangle_drawn
        & (plane_offset != 0)
        & (depth.max(axis=1) > camera.near)
        & (depth.min(axis=1) < camera.far)
    )
    setup = jnp.concatenate(
        [edges[..., 0], edges[..., 1], edges[..., 2], inverse_depth, area_px[:, None], _triangle_bounds(geometry, camera, drawn, margin=0.0)],
        axis=1,
    )
    return setup, drawn


def _triangle_bounds(geometry: _Geometry, camera: Camera, drawn: Array, *, margin: float = 1.0) -> Float[Array, "N 4"]:
    """Conservative pixel bounding boxes (x0, y0, x1, y1) grown by `margin`
    (room for the antialiased edge); the whole screen for triangles crossing the
    near plane; empty for culled ones."""
    depth = geometry.corners[..., 2]
    all_in_front = depth.min(axis=1) > camera.near
    safe_depth = jnp.where(all_in_front[:, None], depth, 1.0)
    x = 0.5 * camera.width + camera.focal_px * geometry.corners[..., 0] / safe_depth
    y = 0.5 * camera.height - camera.focal_px * geometry.corners[..., 1] / safe_depth
    boxes = jnp.stack([x.min(1) - margin, y.min(1) - margin, x.max(1) + margin, y.max(1) + margin], axis=1)
    screen = jnp.array([-jnp.inf, -jnp.inf, jnp.inf, jnp.inf]) if margin == 0 else jnp.array([0.0, 0.0, camera.width, camera.height])
    boxes = jnp.where(all_in_front[:, None], boxes, screen)
    return jnp.where(drawn[:, None], boxes, jnp.array([1.0, 1.0, -1.0, -1.0]) * 1e9)


def _first_overlapping(overlap: Array, capacity: int) -> Int[Array, "... K"]:
    """Indices of the first `capacity` True entries along the last axis, -1 past the end."""
    running = jnp.cumsum(overlap, axis=-1, dtype=jnp.int32)
    wanted = jnp.arange(1, capacity + 1, dtype=jnp.int32)
    flat = running.reshape(-1, running.shape[-1])
    found = jax.vmap(lambda row: jnp.searchsorted(row, wanted, side="left"))(flat)
    found = jnp.where(found < running.shape[-1], found, -1)
    return found.reshape(*running.shape[:-1], capacity)


def _bin_triangles(
    boxes: Float[Array, "N 4"], order_key: Float[Array, "N"], *, tile_size: int, tiles_y: int, tiles_x: int, capacity: int
) -> Int[Array, "TY TX K"]:
    """Per fine tile, up to `capacity` triangle indices, nearest first, -1 for none.

    Two levels (coarse tiles of `_COARSE_TILES_PER_SIDE` fine tiles a side,
    keeping up to `_COARSE_CAPACITY_FACTOR * capacity` each, then fine tiles)
    keep the tile x triangle overlap table small."""
    coarse = tile_size * _COARSE_TILES_PER_SIDE
    order = jnp.argsort(order_key)
    boxes = boxes[order]
    coarse_y, coarse_x = tiles_y // _COARSE_TILES_PER_SIDE, tiles_x // _COARSE_TILES_PER_SIDE

    def spans(lo, hi, size, n):
        starts = jnp.arange(n, dtype=jnp.float32) * size
        return (lo[None, :] < starts[:, None] + size) & (hi[None, :] >= starts[:, None])

    overlap_x = spans(boxes[:, 0], boxes[:, 2], coarse, coarse_x)
    overlap_y = spans(boxes[:, 1], boxes[:, 3], coarse, coarse_y)
    coarse_capacity = min(capacity * _COARSE_CAPACITY_FACTOR, boxes.shape[0])
    coarse_lists = _first_overlapping(overlap_y[:, None, :] & overlap_x[None, :, :], coarse_capacity)

    empty_box = jnp.array([1.0, 1.0, -1.0, -1.0]) * 1e9
    fine_boxes = jnp.where((coarse_lists >= 0)[..., None], boxes[jnp.maximum(coarse_lists, 0)], empty_box)
    offsets = jnp.arange(_COARSE_TILES_PER_SIDE, dtype=jnp.float32) * tile_size
    starts_y = jnp.arange(coarse_y, dtype=jnp.float32)[:, None] * coarse + offsets[None, :]
    starts_x = jnp.arange(coarse_x, dtype=jnp.float32)[:, None] * coarse + offsets[None, :]
    # Axes: (coarse y, coarse x, fine y within, fine x within, coarse list slot).
    in_y = (fine_boxes[:, :, None, None, :, 1] < starts_y[:, None, :, None, None] + tile_size) & (
        fine_boxes[:, :, None, None, :, 3] >= starts_y[:, None, :, None, None]
    )
    in_x = (fine_boxes[:, :, None, None, :, 0] < starts_x[None, :, None, :, None] + tile_size) & (
        fine_boxes[:, :, None, None, :, 2] >= starts_x[None, :, None, :, None]
    )
    local = _first_overlapping(in_y & in_x, capacity)
    coarse_slots = jnp.broadcast_to(coarse_lists[:, :, None, None, :], local.shape[:-1] + coarse_lists.shape[-1:])
    fine = jnp.where(local >= 0, jnp.take_along_axis(coarse_slots, jnp.maximum(local, 0), axis=-1), -1)
    fine = jnp.where(fine >= 0, order[jnp.maximum(fine, 0)], -1)
    return fine.transpose(0, 2, 1, 3, 4).reshape(tiles_y, tiles_x, capacity)


class _Layer(eqx.Module):
    """What one compositing layer sees in each pixel (view space)."""

    object_id: Int[Array, "*P"]  # -1 where the layer is empty
    coverage: Float[Array, "*P"]
    position: Float[Array, "3 *P"]  # component first
    normal: Float[Array, "3 *P"]


class _Layers(eqx.Module):
    front: _Layer  # the nearest object touching the pixel
    behind: _Layer  # the nearest other object touching it
    hit: _Layer  # what the pixel centre hits (coverage unused)


def _triangle_table(geometry: _Geometry, camera: Camera) -> Float[Array, "N 27"]:
    """Per triangle: barycentric numerators as affine functions of the pixel
    position (9), corners (9) and shading normals turned to face the camera (9)."""
    v0, v1, v2 = geometry.corners[:, 0], geometry.corners[:, 1], geometry.corners[:, 2]
    edge_normals = jnp.stack([jnp.cross(v1, v2), jnp.cross(v2, v0), jnp.cross(v0, v1)], axis=1)
    # View space is left-handed, so a positive plane offset means the front face is seen.
    back_facing = jnp.einsum("ni,ni->n", v0, edge_normals.sum(axis=1), precision="highest") < 0
    normals = jnp.where(back_facing[:, None, None], -geometry.corner_normals, geometry.corner_normals)
    count = geometry.corners.shape[0]
    return jnp.concatenate(
        [_pixel_affine(edge_normals, camera).reshape(count, 9), geometry.corners.reshape(count, 9), normals.reshape(count, 9)],
        axis=1,
    )


def _sphere_bounds(geometry: _Geometry, camera: Camera, *, margin: float = 2.0) -> Float[Array, "S 4"]:
    """Conservative pixel boxes (x0, y0, x1, y1) of the spheres' silhouettes:
    the projected corners of each sphere's view-space bounding cube, grown by
    `margin` (the antialiased edge, measured by a first-order distance); the
    whole screen for spheres reaching the near plane; empty for spheres wholly
    before the near plane or past the far plane."""
    signs = jnp.array(np.stack(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij"), axis=-1).reshape(8, 3), jnp.float32)
    corners = geometry.centers[:, None, :] + geometry.radii[:, None, None] * signs
    all_in_front = corners[..., 2].min(axis=1) > camera.near
    safe_depth = jnp.where(all_in_front[:, None], corners[..., 2], 1.0)
    x = 0.5 * camera.width + camera.focal_px * corners[..., 0] / safe_depth
    y = 0.5 * camera.height - camera.focal_px * corners[..., 1] / safe_depth
    boxes = jnp.stack([x.min(1) - margin, y.min(1) - margin, x.max(1) + margin, y.max(1) + margin], axis=1)
    boxes = jnp.where(all_in_front[:, None], boxes, jnp.array([0.0, 0.0, camera.width, camera.height]))
    depth = geometry.centers[:, 2]
    visible = (depth + geometry.radii > camera.near) & (depth - geometry.radii < camera.far)
    return jnp.where(visible[:, None], boxes, jnp.array([1.0, 1.0, -1.0, -1.0]) * 1e9)


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


def _no_picks(pixels: tuple[int, ...]) -> _Picks:
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


def _triangle_picks(setup, objects, candidates: Int[Array, "B K"], px, py, camera: Camera, slot_bits: int) -> _Picks:
    rows = setup[candidates][:, None]
    x, y = px[..., None], py[..., None]
    edge_x, edge_y, edge_c = rows[..., _EDGE_X], rows[..., _EDGE_Y], rows[..., _EDGE_C]
    edge = lambda i: x * edge_x[..., i] + y * edge_y[..., i] + edge_c[..., i]
    # The bounding box's sides join the three edges: past a sliver's sharp
    # corner the edges alone would leave coverage leaking along its extension.
    box = rows[..., _BOX]
    box_distance = jnp.minimum(jnp.minimum(x - box[..., 0], box[..., 2] - x), jnp.minimum(y - box[..., 1], box[..., 3] - y))
    distance = jnp.minimum(jnp.minimum(jnp.minimum(edge(0), edge(1)), edge(2)), box_distance)
    plane = rows[..., _INV_DEPTH]
    inverse_depth = x * plane[..., 0] + y * plane[..., 1] + plane[..., 2]
    return _picks(distance, inverse_depth, rows[..., _AREA], objects[candidates][:, None], candidates[:, None], camera, slot_bits)


def _sphere_picks(centers, radii, objects, candidates: Int[Array, "B K"], px, py, camera: Camera, slot_bits: int) -> _Picks:
    distance, inverse_depth, area = _sphere_terms(centers[candidates], radii[candidates], camera, px[..., None], py[..., None])
    return _picks(distance, inverse_depth, area, objects[candidates][:, None], candidates[:, None], camera, slot_bits)


def _merge(triangles: _Picks, spheres: _Picks) -> tuple[tuple[Array, ...], ...]:
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


def _dot(a: Float[Array, "3 *P"], b: Float[Array, "3 *P"]) -> Float[Array, "*P"]:
    """Dot products of component-first vectors (inside the tile loop vectors
    are `(3, P)`: XLA on CPU reduces a minor axis of 3 slowly)."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _times(vectors: Float[Array, "3 *P"], matrix: Float[Array, "3 3"]) -> Float[Array, "3 *P"]:
    """`vectors @ matrix`, component-first."""
    column = lambda i: matrix[i].reshape((3,) + (1,) * (vectors.ndim - 1))
    return vectors[0] * column(0) + vectors[1] * column(1) + vectors[2] * column(2)


def _unit_first(vectors: Float[Array, "3 *P"]) -> Float[Array, "3 *P"]:
    """Component-first vectors scaled to length 1 (`unit_vectors` along axis 0)."""
    return unit_vectors(vectors, axis=0)


def _triangle_surface(columns: Float[Array, "27 P"], px: Float[Array, "P"], py: Float[Array, "P"]) -> tuple[Float[Array, "3 P"], Float[Array, "3 P"]]:
    """View-space position and unnormalised shading normal from `_triangle_table`
    columns; barycentric weights are clamped to the triangle, so a silhouette
    pixel whose centre lies outside takes the triangle's nearest point."""
    weights = [columns[3 * i] * px + columns[3 * i + 1] * py + columns[3 * i + 2] for i in range(3)]
    total = weights[0] + weights[1] + weights[2]
    weights = [jnp.maximum(w / jnp.where(total == 0, 1.0, total), 0.0) for w in weights]
    total = jnp.maximum(weights[0] + weights[1] + weights[2], 1e-12)
    weights = [w / total for w in weights]
    blend = lambda start: jnp.stack([sum(weights[i] * columns[start + 3 * i + c] for i in range(3)) for c in range(3)])
    return blend(_TABLE_CORNERS), blend(_TABLE_NORMALS)


def _sphere_surface(center: Float[Array, "3 P"], radius: Float[Array, "P"], rays: Float[Array, "3 P"]) -> tuple[Float[Array, "3 P"], Float[Array, "3 P"]]:
    """The ray's hit, or its closest approach to the sphere at silhouettes."""
    unit = _unit_first(rays)
    along = _dot(unit, center)
    center_squared = _dot(center, center)
    chord_squared = radius**2 - (center_squared - along**2)
    positive = jnp.where(chord_squared > 0, chord_squared, 1.0)
    half_chord = jnp.where(chord_squared > 0, jnp.sqrt(positive), 0.0)
    camera_inside = center_squared < radius**2
    position = unit * jnp.where(camera_inside, along + half_chord, along - half_chord)
    normal = (position - center) / radius
    return position, jnp.where(camera_inside, -normal, normal)


def _tile_grid(camera: Camera, tile_size: int) -> tuple[int, int]:
    coarse = tile_size * _COARSE_TILES_PER_SIDE
    return -(-camera.height // coarse) * _COARSE_TILES_PER_SIDE, -(-camera.width // coarse) * _COARSE_TILES_PER_SIDE


def _tile_loads(geometry: _Geometry, camera: Camera, tile_size: int) -> Int[Array, "T"]:
    """How many triangles overlap each fine tile, busiest first."""
    tiles_y, tiles_x = _tile_grid(camera, tile_size)
    _, drawn = _triangle_setup(geometry, camera)
    boxes = _triangle_bounds(geometry, camera, drawn)
    starts_y = jnp.arange(tiles_y, dtype=jnp.float32) * tile_size
    starts_x = jnp.arange(tiles_x, dtype=jnp.float32) * tile_size
    in_y = (boxes[None, :, 1] < starts_y[:, None] + tile_size) & (boxes[None, :, 3] >= starts_y[:, None])
    in_x = (boxes[None, :, 0] < starts_x[:, None] + tile_size) & (boxes[None, :, 2] >= starts_x[:, None])
    loads = in_y.astype(jnp.float32) @ in_x.astype(jnp.float32).T
    return -jnp.sort(-loads.reshape(-1)).astype(jnp.int32)


def _tiles_overlapping(boxes: Float[Array, "M 4"], tile_size: int, tiles_y: int, tiles_x: int) -> Array:
    """(T, M) booleans: which pixel boxes overlap which tile (row-major tiles)."""
    starts_y = jnp.arange(tiles_y, dtype=jnp.float32) * tile_size
    starts_x = jnp.arange(tiles_x, dtype=jnp.float32) * tile_size
    in_y = (boxes[None, :, 1] < starts_y[:, None] + tile_size) & (boxes[None, :, 3] >= starts_y[:, None])
    in_x = (boxes[None, :, 0] < starts_x[:, None] + tile_size) & (boxes[None, :, 2] >= starts_x[:, None])
    return (in_y[:, None, :] & in_x[None, :, :]).reshape(tiles_y * tiles_x, -1)


def _bucket_sizes(limit: int) -> tuple[int, ...]:
    """The candidate counts a batch of tiles is evaluated with: 0 (nothing to
    test), then doubling up to `limit`; a batch takes the smallest that holds
    its busiest tile."""
    sizes = [0]
    while sizes[-1] < limit:
        sizes.append(min(max(1, 2 * sizes[-1]), limit))
    return tuple(sizes)


def _rasterize(geometry: _Geometry, camera: Camera, finish, *, tile_size: int, capacity: int, tile_mask: Array | None = None):
    """`finish(layers, px, py)` of every pixel, as (H, W, ...) images.

    `finish` turns the three layers of `P` pixels (a `_Layers` of (P,) and
    component-first (3, P) arrays, or None where no geometry can touch them) at pixel
    positions `px`, `py` (P,) into a pytree of (P, ...) arrays. Tiles are sorted
    by how many triangles and spheres overlap them and evaluated
    `_TILES_PER_BATCH` at a time, each batch with the smallest bucket of
    candidates that holds its busiest tile (a `lax.switch`, so empty sky costs
    only `finish(None, ...)` and a few busy tiles do not pad the others). Tiles
    where `tile_mask` is False are treated as empty."""
    tiles_y, tiles_x = _tile_grid(camera, tile_size)
    tile_count = tiles_y * tiles_x
    triangle_count, sphere_count = geometry.corners.shape[0], geometry.radii.shape[0]
    setup, drawn = _triangle_setup(geometry, camera)
    triangle_lists = _bin_triangles(
        jax.lax.stop_gradient(_triangle_bounds(geometry, camera, drawn)),
        jax.lax.stop_gradient(geometry.corners[..., 2].min(axis=1)),
        tile_size=tile_size,
        tiles_y=tiles_y,
        tiles_x=tiles_x,
        capacity=capacity,
    ).reshape(tile_count, capacity)
    triangle_loads = jnp.sum(triangle_lists >= 0, axis=1)
    sphere_overlap = _tiles_overlapping(jax.lax.stop_gradient(_sphere_bounds(geometry, camera)), tile_size, tiles_y, tiles_x)
    sphere_loads = jnp.sum(sphere_overlap, axis=1)
    # Overlapping spheres first (a stable sort keeps them in scene order).
    sphere_lists = jnp.argsort(~sphere_overlap, axis=1, stable=True).astype(jnp.int32)
    if tile_mask is not None:
        triangle_loads, sphere_loads = (jnp.where(tile_mask.reshape(-1), loads, 0) for loads in (triangle_loads, sphere_loads))

    # Row / entry `count` of each table is a sentinel that never covers anything.
    setup = jnp.concatenate([setup, jnp.zeros((1, setup.shape[1])).at[0, _EDGE_C].set(-1e9)])
    columns = jnp.concatenate([_triangle_table(geometry, camera), jnp.zeros((1, 27))]).T
    triangle_objects = jnp.concatenate([geometry.triangle_object, jnp.array([-1], jnp.int32)])
    triangle_lists = jnp.where(triangle_lists >= 0, triangle_lists, triangle_count)
    centers = jnp.concatenate([geometry.centers, jnp.array([[0.0, 0.0, -1e6]])])
    radii = jnp.concatenate([geometry.radii, jnp.ones(1)])
    sphere_objects = jnp.concatenate([geometry.sphere_object, jnp.array([-1], jnp.int32)])
    sphere_lists = jnp.where(jnp.arange(sphere_count) < sphere_loads[:, None], sphere_lists, sphere_count)

    triangle_sizes, sphere_sizes = _bucket_sizes(capacity), _bucket_sizes(sphere_count)
    triangle_bucket = jnp.searchsorted(jnp.asarray(triangle_sizes), triangle_loads)
    sphere_bucket = jnp.searchsorted(jnp.asarray(sphere_sizes), sphere_loads)
    order = jnp.argsort(-(triangle_bucket * len(sphere_sizes) + sphere_bucket))
    batch_count = tile_count // _TILES_PER_BATCH
    batched = lambda values: values[order].reshape(batch_count, _TILES_PER_BATCH, *values.shape[1:])
    grid_y, grid_x = jnp.divmod(jnp.arange(tile_count, dtype=jnp.int32), tiles_x)
    slot_bits = max(capacity, sphere_count).bit_length()

    def pixels(tile_y, tile_x):
        local = jnp.arange(tile_size, dtype=jnp.float32) + 0.5
        py = (tile_y[:, None, None] * tile_size + local[None, :, None]) + jnp.zeros(tile_size)
        px = (tile_x[:, None, None] * tile_size + local[None, None, :]) + jnp.zeros((tile_size, 1))
        return px.reshape(_TILES_PER_BATCH, -1), py.reshape(_TILES_PER_BATCH, -1)

    def evaluate_batch(tile_y, tile_x, triangle_candidates, sphere_candidates, triangle_size, sphere_size):
        px, py = pixels(tile_y, tile_x)
        triangle_branch = lambda size: lambda candidates: (
            _triangle_picks(setup, triangle_objects, candidates[:, :size], px, py, camera, slot_bits) if size else _no_picks(px.shape)
        )
        sphere_branch = lambda size: lambda candidates: (
            _sphere_picks(centers, radii, sphere_objects, candidates[:, :size], px, py, camera, slot_bits) if size else _no_picks(px.shape)
        )
        triangles = jax.lax.switch(triangle_size, [triangle_branch(size) for size in triangle_sizes], triangle_candidates)
        spheres = jax.lax.switch(sphere_size, [sphere_branch(size) for size in sphere_sizes], sphere_candidates)
        layers = _merge(triangles, spheres)

        px, py = px.reshape(-1), py.reshape(-1)
        f = camera.focal_px
        rays = jnp.stack([(px - 0.5 * camera.width) / f, (0.5 * camera.height - py) / f, jnp.ones_like(px)])

        def surface(from_triangles, index):
            from_triangles, index = from_triangles.reshape(-1), index.reshape(-1)
            found = index >= 0
            position, normal = _triangle_surface(columns[:, jnp.where(from_triangles & found, index, triangle_count)], px, py)
            if sphere_count:
                sphere = jnp.where(~from_triangles & found, index, sphere_count)
                sphere_position, sphere_normal = _sphere_surface(centers.T[:, sphere], radii[sphere], rays)
                position = jnp.where(from_triangles, position, sphere_position)
                normal = jnp.where(from_triangles, normal, sphere_normal)
            return position, _unit_first(normal)

        # One copy of the surface code for the three layers keeps compilation short.
        positions, normals = jax.vmap(surface)(*(jnp.stack([layer[i] for layer in layers]) for i in (0, 2)))
        found = _Layers(*(_Layer(layer[3].reshape(-1), layer[4].reshape(-1), positions[i], normals[i]) for i, layer in enumerate(layers)))
        return finish(found, px, py)

    def empty_batch(tile_y, tile_x, *_):
        return finish(None, *(a.reshape(-1) for a in pixels(tile_y, tile_x)))

    def run(args):
        triangle_size, sphere_size = args[4], args[5]
        return jax.lax.cond((triangle_size == 0) & (sphere_size == 0), empty_batch, evaluate_batch, *args)

    sizes = (batched(triangle_bucket).max(axis=1), batched(sphere_bucket).max(axis=1))
    values = jax.lax.map(run, (batched(grid_y), batched(grid_x), batched(triangle_lists), batched(sphere_lists), *sizes))
    tile_position = jnp.argsort(order)

    def to_image(values):
        values = values.reshape(tile_count, tile_size, tile_size, *values.shape[2:])[tile_position]
        image = values.reshape(tiles_y, tiles_x, tile_size, tile_size, *values.shape[3:]).swapaxes(1, 2)
        return image.reshape(tiles_y * tile_size, tiles_x * tile_size, *values.shape[3:])[: camera.height, : camera.width]

    return jax.tree_util.tree_map(to_image, values)


def _city_pattern(normal: Float[Array, "3 *P"]) -> Float[Array, "*P"]:
    """Procedural stand-in for an emissive night-light map: scattered bright cells."""
    x, y, z = normal[0], normal[1], normal[2]
    waves = jnp.sin(83.0 * x + 3.0 * jnp.sin(11.0 * y)) * jnp.sin(89.0 * y + 2.0 * jnp.sin(13.0 * z)) * jnp.sin(97.0 * z + 2.5 * jnp.sin(7.0 * x))
    return jnp.clip(8.0 * (waves - 0.45), 0.0, 1.0)


def _stack_materials(scene: Scene):
    """Every material field stacked over objects, colours component-first `(3, objects)`."""
    materials = [obj.material for obj in scene.objects]
    return jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves, axis=-1), *materials)


def _light_direction(scene: Scene, world_position: Float[Array, "3 P"]) -> Float[Array, "3 P"]:
    if isinstance(scene.light, DirectionalLight):
        return jnp.broadcast_to(_unit_first(scene.light.direction)[:, None], world_position.shape)
    return _unit_first(scene.light.position[:, None] - world_position)


def _shade(scene: Scene, camera: Camera, surface: _Layer, world_rays: Float[Array, "3 P"]):
    """One layer's shading, the VBex planet shader's passes: `(opaque colour, shell, emissive, opaque)`.

    The opaque sphere: albedo lit, emission, the atmosphere's colour from the
    basic rim `1 - saturate(view . N)` (lit), night lights on the dark side;
    where the rim sharpened for clipping, `min(1, 10 * rim ** (30 * sharpness))`,
    reaches 1 the opaque pixel is discarded (only for materials with an
    atmosphere). The transparent shell: the atmosphere's colour times that
    sharpened rim, lit by `saturate(N . L)` in the shader (the article's glow
    is not lit by the deferred pass). The emissive part (emission and night
    lights: the engine's emissive light) also goes to the glow target.
    """
    materials = _stack_materials(scene)
    obj = jnp.maximum(surface.object_id, 0)
    to_world = jnp.stack(camera.basis())
    normal = _times(surface.normal, to_world)
    to_light = _light_direction(scene, camera.position[:, None] + _times(surface.position, to_world))
    n_dot_l = _dot(normal, to_light)
    lit = jnp.clip(n_dot_l, 0.0, 1.0)
    # Kept off 0 so that rim ** p has finite gradients for any p > 0.
    rim = 1.0 - jnp.clip(-_dot(_unit_first(world_rays), normal), 0.0, 1.0 - 1e-6)
    sharpened_rim = jnp.minimum(1.0, 10.0 * rim ** (30.0 * materials.atmosphere_sharpness[obj]))
    dark_side = jnp.clip(-n_dot_l * materials.night_sharpness[obj], 0.0, 1.0)
    atmosphere = materials.atmosphere_color[:, obj]
    emissive = materials.emission[:, obj] + materials.night_color[:, obj] * (_city_pattern(normal) * dark_side)
    opaque_colour = (
        materials.albedo[:, obj] * (scene.ambient[:, None] + scene.light.color[:, None] * lit)
        + atmosphere * (rim * lit)
        + emissive
    )
    clipped = jnp.any(atmosphere > 0, axis=0) & (sharpened_rim >= 1.0)
    return opaque_colour, atmosphere * (sharpened_rim * lit), emissive, jnp.where(clipped, 0.0, 1.0)


def _sun_direction(scene: Scene, camera: Camera) -> Float[Array, "3"]:
    if isinstance(scene.light, DirectionalLight):
        direction = scene.light.direction
    else:
        direction = scene.light.position - camera.position
    return direction / jnp.linalg.norm(direction)


def _sky(scene: Scene, camera: Camera, world_rays: Float[Array, "3 P"]) -> tuple[Float[Array, "3 P"], Float[Array, "P"]]:
    """Sky colour and the sun spot's intensity (the VBex article)."""
    unit = _unit_first(world_rays)
    height = jnp.clip(_dot(unit, (camera.up / jnp.linalg.norm(camera.up))[:, None]), 0.0, 1.0)
    sky = scene.sky
    cosine = _dot(unit, _sun_direction(scene, camera)[:, None])
    spot = sun_spot_intensity(cosine, sun_distance=sky.sun_distance, sun_sharpness=sky.sun_sharpness)
    color = sky.horizon_color[:, None] + (sky.zenith_color - sky.horizon_color)[:, None] * height + sky.sun_color[:, None] * spot
    return color, spot


def _object_weight(layers: _Layers, target: int) -> Float[Array, "H W"]:
    """Coverage of object `target` seen through the two layers."""
    front, behind = layers.front, layers.behind
    return front.coverage * (front.object_id == target) + (1.0 - front.coverage) * behind.coverage * (behind.object_id == target)


def _total_coverage(layers: _Layers) -> Float[Array, "H W"]:
    return layers.front.coverage + (1.0 - layers.front.coverage) * layers.behind.coverage


def render(
    scene: Scene,
    camera: Camera,
    *,
    glow_source_scale: float | Float[ArrayLike, ""] = GLOW_SOURCE_SCALE,
    glow_occluder_scale: float | Float[ArrayLike, ""] = GLOW_OCCLUDER_SCALE,
    glow_color: Float[ArrayLike, "4"] = GLOW_COLOR,
    with_glow_pass: bool = True,
    tile_size: int = 16,
    tile_capacity: int | None = None,
) -> Buffers:
    """Render every buffer the effects read.

    Args:
        scene: the `Scene`.
        camera: the `Camera` (image size, clipping planes).
        glow_source_scale: the sun-overcasting article's enlargement of the sun object (about its
            origin) in the glow pass.
        glow_occluder_scale: the sun-overcasting article's shrinking of every other object.
        glow_color: the glow pass colour, premultiplied RGBA in [0, 1] (the sun-overcasting article:
            `(0.8, 0.5, 0, 0.65)`).
        with_glow_pass: render the glow pass (a second rasterization, of the
            tiles near the sun object only: elsewhere it is zero); if False
            `glow_pass` is None.
        tile_size: fine tile side in pixels (static).
        tile_capacity: static cap on the triangles kept per fine tile; beyond
            it the farthest are dropped. Tiles are evaluated in buckets of
            0, 1, 2, 4, ... candidates, so a large cap costs only where tiles
            are that busy; each 4 x 4 block of tiles keeps up to 4 times as
            many. `None`: planned from the scene so that nothing is
            dropped (a power of two, to limit recompilation), or
            `DEFAULT_TILE_CAPACITY` when `render` runs under a JAX
            transformation (grad, jit, vmap); pass
            `plan_tile_capacity(scene, camera)` there for dense scenes.

    Returns:
        `Buffers` with `color` (H, W, 3) linear HDR (sky included), `depth`
        (distance along the camera ray, `+inf` on sky), `coverage` in [0, 1]
        (antialiased), `normal` (world space, zero on sky), `object_id` (-1 on
        sky), `light_pass` (the sun object white, everything else black, plus
        the sky's saturated sun spot where nothing covers it), `glow_pass`
        (H, W, 4) and `glow_target` (H, W, 3: the VBex article's glow target,
        the sky's sun spot in `sky.sun_color`, emission, night lights and the atmosphere's
        shell, see `Material`). Geometry off-screen or outside [near, far] is
        not drawn.
    """
    if not isinstance(scene, Scene):
        raise ValueError(f"render: scene must be a Scene, got {type(scene).__name__}")
    if not isinstance(camera, Camera):
        raise ValueError(f"render: camera must be a Camera, got {type(camera).__name__}")
    if not scene.objects:
        raise ValueError("render: scene.objects is empty")
    if isinstance(tile_size, bool) or not isinstance(tile_size, int) or tile_size < 1:
        raise ValueError(f"render: tile_size must be a positive int, got {tile_size!r}")
    glow_color = jnp.asarray(glow_color, jnp.float32)
    if glow_color.shape != (4,):
        raise ValueError(f"render: glow_color must have shape (4,), got {glow_color.shape}")
    if tile_capacity is None:
        traced = any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves((scene, camera)))
        tile_capacity = DEFAULT_TILE_CAPACITY if traced else plan_tile_capacity(
            scene, camera, tile_size=tile_size, glow_source_scale=glow_source_scale, glow_occluder_scale=glow_occluder_scale
        )
    if isinstance(tile_capacity, bool) or not isinstance(tile_capacity, int) or tile_capacity < 1:
        raise ValueError(f"render: tile_capacity must be None or a positive int, got {tile_capacity!r}")
    return _render(
        scene, camera, glow_source_scale, glow_occluder_scale, glow_color,
        with_glow_pass=with_glow_pass, tile_size=tile_size, capacity=tile_capacity,
    )


def plan_tile_capacity(
    scene: Scene,
    camera: Camera,
    *,
    tile_size: int = 16,
    glow_source_scale: float = GLOW_SOURCE_SCALE,
    glow_occluder_scale: float = GLOW_OCCLUDER_SCALE,
) -> int:
    """The smallest tile capacity (a power of two) that drops no triangle of
    `scene` seen by `camera`, in either pass, from a fine tile or from a
    coarse tile (which keeps `_COARSE_CAPACITY_FACTOR` times as many). Needs
    concrete values."""
    glow = tuple(glow_source_scale if i == scene.sun else glow_occluder_scale for i in range(len(scene.objects)))
    busiest = max(
        -(-int(_planned_loads(scene, camera, scales, size)[0]) // factor)
        for scales in (None, glow)
        for size, factor in ((tile_size, 1), (tile_size * _COARSE_TILES_PER_SIDE, _COARSE_CAPACITY_FACTOR))
    )
    return 1 << max(busiest - 1, 0).bit_length()


@eqx.filter_jit
def _planned_loads(scene: Scene, camera: Camera, scales, tile_size: int) -> Int[Array, "T"]:
    return _tile_loads(_flatten(scene, camera, scales), camera, tile_size)


def _glow_tiles(scene: Scene, camera: Camera, glow: _Geometry, sky_light: Float[Array, "H W"] | None, tile_size: int) -> Array:
    """(T,) booleans: the tiles where the glow pass can be non-zero. With a sun
    object, those its enlarged outline's bounds overlap (every other object is
    transparent black there); without one, those the sky's sun spot reaches."""
    tiles_y, tiles_x = _tile_grid(camera, tile_size)
    if scene.sun is None:
        padded = jnp.pad(sky_light, ((0, tiles_y * tile_size - camera.height), (0, tiles_x * tile_size - camera.width)))
        return padded.reshape(tiles_y, tile_size, tiles_x, tile_size).max(axis=(1, 3)).reshape(-1) > 0
    _, drawn = _triangle_setup(glow, camera)
    empty = jnp.array([1.0, 1.0, -1.0, -1.0]) * 1e9
    boxes = jnp.concatenate([
        jnp.where((glow.triangle_object == scene.sun)[:, None], _triangle_bounds(glow, camera, drawn), empty),
        jnp.where((glow.sphere_object == scene.sun)[:, None], _sphere_bounds(glow, camera), empty),
    ])
    union = jnp.concatenate([boxes[:, :2].min(axis=0), boxes[:, 2:].max(axis=0)])
    return _tiles_overlapping(jax.lax.stop_gradient(union)[None], tile_size, tiles_y, tiles_x)[:, 0]


def _world_rays(camera: Camera, px: Float[Array, "P"], py: Float[Array, "P"]) -> Float[Array, "3 P"]:
    """World directions through pixel positions, scaled to unit view depth, component first."""
    right, up, forward = (v[:, None] for v in camera.basis())
    f = camera.focal_px
    return ((px - 0.5 * camera.width) / f) * right + ((0.5 * camera.height - py) / f) * up + forward


@eqx.filter_jit
def _render(scene: Scene, camera: Camera, glow_source_scale, glow_occluder_scale, glow_color, *, with_glow_pass: bool, tile_size: int, capacity: int) -> Buffers:
    to_world = jnp.stack(camera.basis())

    def sky_light(world_rays):
        return jnp.clip(_sky(scene, camera, world_rays)[1], 0.0, 1.0)

    def finish(layers: _Layers | None, px, py) -> dict:
        """Every buffer but the glow pass, for P pixels."""
        world_rays = _world_rays(camera, px, py)
        sky_color, sun_spot = _sky(scene, camera, world_rays)
        light = jnp.clip(sun_spot, 0.0, 1.0)
        if layers is None:
            return dict(
                color=sky_color.T, depth=jnp.full(px.shape, jnp.inf), coverage=jnp.zeros(px.shape), normal=jnp.zeros((*px.shape, 3)),
                object_id=jnp.full(px.shape, -1, jnp.int32), light_pass=light if scene.sun is None else jnp.zeros(px.shape),
                glow_target=(scene.sky.sun_color[:, None] * sun_spot).T,
            )
        (front_color, front_shell, front_emissive, front_opaque), (behind_color, behind_shell, behind_emissive, behind_opaque) = (
            _shade(scene, camera, layer, world_rays) for layer in (layers.front, layers.behind)
        )
        # The shell covers the whole outline; the opaque surface only where its rim is not clipped.
        shell_f, shell_b = layers.front.coverage, layers.behind.coverage
        cf, cb = shell_f * front_opaque, shell_b * behind_opaque
        shell = shell_f * front_shell + (1.0 - shell_f) * shell_b * behind_shell
        coverage = cf + (1.0 - cf) * cb
        hit = layers.hit
        clipped_hit = (hit.object_id == layers.front.object_id) & (front_opaque == 0) & (cb == 0)
        has_hit = (hit.object_id >= 0) & ~clipped_hit
        # Sky pixels' positions are placeholders: keep the norm's gradient finite there.
        position = jnp.where(has_hit, hit.position, 1.0)
        depth = jnp.where(has_hit, jnp.sqrt(_dot(position, position)), jnp.inf)
        sky_glow = scene.sky.sun_color[:, None] * sun_spot
        return dict(
            color=(cf * front_color + (1.0 - cf) * (cb * behind_color + (1.0 - cb) * sky_color) + shell).T,
            depth=depth,
            coverage=coverage,
            normal=jnp.where(has_hit, _times(hit.normal, to_world), 0.0).T,
            object_id=jnp.where(has_hit, hit.object_id, -1),
            light_pass=(1.0 - coverage) * light if scene.sun is None else _object_weight(layers, scene.sun),
            glow_target=(cf * front_emissive + (1.0 - cf) * (cb * behind_emissive + (1.0 - cb) * sky_glow) + shell).T,
        )

    def finish_glow(layers: _Layers | None, px, py) -> Float[Array, "P"]:
        """How much of the glow colour each of P pixels gets."""
        if scene.sun is not None:
            return jnp.zeros(px.shape) if layers is None else _object_weight(layers, scene.sun)
        light = sky_light(_world_rays(camera, px, py))
        return light if layers is None else (1.0 - _total_coverage(layers)) * light

    buffers = _rasterize(_flatten(scene, camera, None), camera, finish, tile_size=tile_size, capacity=capacity)
    glow_pass = None
    if with_glow_pass:
        scales = tuple(glow_source_scale if i == scene.sun else glow_occluder_scale for i in range(len(scene.objects)))
        glow = _flatten(scene, camera, scales)
        if scene.sun is None:
            rows, columns = jnp.meshgrid(jnp.arange(camera.height) + 0.5, jnp.arange(camera.width) + 0.5, indexing="ij")
            light = sky_light(_world_rays(camera, columns.reshape(-1), rows.reshape(-1))).reshape(camera.height, camera.width)
        else:
            light = None
        tiles = _glow_tiles(scene, camera, glow, light, tile_size)
        glow_weight = _rasterize(glow, camera, finish_glow, tile_size=tile_size, capacity=capacity, tile_mask=tiles)
        glow_pass = glow_weight[..., None] * glow_color
    return Buffers(**buffers, glow_pass=glow_pass)


def light_pixel(scene: Scene, camera: Camera) -> tuple[Float[Array, "2"], Float[Array, ""], Array]:
    """Where the light is on screen: `project_point` of the sun object's centre
    (a mesh's translation), else of a point light, else of the camera position
    plus a directional light's direction (a light at infinity). Returns
    `(xy, view_depth, in_front)` as `project_point` does."""
    if scene.sun is not None:
        sun = scene.objects[scene.sun]
        point = sun.center if isinstance(sun, Sphere) else sun.translation
    elif isinstance(scene.light, DirectionalLight):
        point = camera.position + scene.light.direction / jnp.linalg.norm(scene.light.direction)
    else:
        point = scene.light.position
    return project_point(camera, point)


def light_distance(scene: Scene, camera: Camera) -> float:
    """The light's distance from the camera in scene units, as the depth buffer measures it (along the ray).

    The sun object's centre (a mesh's translation), else a point light's
    position; `inf` for a directional light without a sun object (a light at
    infinity). `render` stores it with the frame (`godrays:light_depth`): the
    XNA crepuscular-rays article's depth test and step clamp read it.
    """
    if scene.sun is not None:
        sun = scene.objects[scene.sun]
        point = sun.center if isinstance(sun, Sphere) else sun.translation
    elif isinstance(scene.light, DirectionalLight):
        return math.inf
    else:
        point = scene.light.position
    return float(np.linalg.norm(np.asarray(point, np.float64) - np.asarray(camera.position, np.float64)))
