"""The scene flattened into view space, and the per-triangle and per-sphere terms the tile loop reads."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from godrays_jax.primitives.camera import Camera
from godrays_jax.raster.scene import Scene, Sphere

# Columns of the per-triangle setup table.
EDGE_X, EDGE_Y, EDGE_C = slice(0, 3), slice(3, 6), slice(6, 9)
INV_DEPTH = slice(9, 12)
AREA = 12
BOX = slice(13, 17)
# Rows of the per-triangle shading table (`triangle_table`), component first: the barycentric numerators as
# affine functions of the pixel position (3 per corner), then the corners, then the shading normals (3 each).
TABLE_CORNERS = 9
TABLE_NORMALS = 18
EMPTY_BOX = (1e9, 1e9, -1e9, -1e9)
"""The pixel box (x0, y0, x1, y1) of a culled primitive: it overlaps no tile."""


class Geometry(eqx.Module):
    """Everything flattened: triangles (N) then spheres (S), in view space."""

    corners: Float[Array, "N 3 3"]
    corner_normals: Float[Array, "N 3 3"]
    triangle_object: Int[Array, "N"]
    triangle_drawn: Array
    centers: Float[Array, "S 3"]
    radii: Float[Array, "S"]
    sphere_object: Int[Array, "S"]


def flatten(scene: Scene, camera: Camera, object_scales: tuple[float | None, ...] | None) -> Geometry:
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
    return Geometry(
        corners=jnp.concatenate(corners),
        corner_normals=jnp.concatenate(normals),
        triangle_object=jnp.concatenate(triangle_object),
        triangle_drawn=jnp.concatenate(triangle_drawn),
        centers=jnp.stack(centers) if centers else jnp.zeros((0, 3)),
        radii=jnp.stack(radii) if radii else jnp.zeros((0,)),
        sphere_object=jnp.asarray(sphere_object, jnp.int32),
    )


def pixel_affine(vectors: Float[Array, "*N 3"], camera: Camera) -> Float[Array, "*N 3"]:
    """Coefficients (a, b, c) with `v . d(px, py) = a px + b py + c`, where
    `d = ((px - W/2) / f, (H/2 - py) / f, 1)` is the view ray through pixel
    position (px, py)."""
    f = camera.focal_px
    a = vectors[..., 0] / f
    b = -vectors[..., 1] / f
    c = vectors[..., 2] - a * (0.5 * camera.width) - b * (0.5 * camera.height)
    return jnp.stack([a, b, c], axis=-1)


def triangle_setup(geometry: Geometry, camera: Camera) -> tuple[Float[Array, "N 13"], Array]:
    """Per-triangle edge, reciprocal-depth and area terms; and which are drawn."""
    v0, v1, v2 = geometry.corners[:, 0], geometry.corners[:, 1], geometry.corners[:, 2]
    edge_normals = jnp.stack([jnp.cross(v1, v2), jnp.cross(v2, v0), jnp.cross(v0, v1)], axis=1)
    plane = edge_normals.sum(axis=1)
    plane_offset = jnp.einsum("ni,ni->n", v0, plane, precision="highest")
    orientation = jnp.where(plane_offset < 0, -1.0, 1.0)
    edges = pixel_affine(edge_normals, camera)
    edge_gradient = jnp.sqrt(jnp.sum(edges[..., :2] ** 2, axis=-1, keepdims=True) + 1e-30)
    edges = edges * (orientation[:, None, None] / edge_gradient)
    safe_offset = jnp.where(plane_offset == 0, 1.0, plane_offset)
    inverse_depth = pixel_affine(plane / safe_offset[:, None], camera)

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
        [edges[..., 0], edges[..., 1], edges[..., 2], inverse_depth, area_px[:, None], triangle_bounds(geometry, camera, drawn, margin=0.0)],
        axis=1,
    )
    return setup, drawn


def triangle_bounds(geometry: Geometry, camera: Camera, drawn: Array, *, margin: float = 1.0) -> Float[Array, "N 4"]:
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
    return jnp.where(drawn[:, None], boxes, jnp.array(EMPTY_BOX))


def triangle_table(geometry: Geometry, camera: Camera) -> Float[Array, "N 27"]:
    """Per triangle: barycentric numerators as affine functions of the pixel
    position (9), corners (9) and shading normals turned to face the camera (9)."""
    v0, v1, v2 = geometry.corners[:, 0], geometry.corners[:, 1], geometry.corners[:, 2]
    edge_normals = jnp.stack([jnp.cross(v1, v2), jnp.cross(v2, v0), jnp.cross(v0, v1)], axis=1)
    # View space is left-handed, so a positive plane offset means the front face is seen.
    back_facing = jnp.einsum("ni,ni->n", v0, edge_normals.sum(axis=1), precision="highest") < 0
    normals = jnp.where(back_facing[:, None, None], -geometry.corner_normals, geometry.corner_normals)
    count = geometry.corners.shape[0]
    return jnp.concatenate(
        [pixel_affine(edge_normals, camera).reshape(count, 9), geometry.corners.reshape(count, 9), normals.reshape(count, 9)],
        axis=1,
    )


def sphere_bounds(geometry: Geometry, camera: Camera, *, margin: float = 2.0) -> Float[Array, "S 4"]:
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
    return jnp.where(visible[:, None], boxes, jnp.array(EMPTY_BOX))
