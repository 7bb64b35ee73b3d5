"""The tile loop: tiles sorted by load, evaluated in batches with the smallest bucket of candidates, into images."""

import jax
import jax.numpy as jnp
from jaxtyping import Array

from godrays_jax.primitives.camera import Camera
from godrays_jax.raster.binning import bin_triangles, tile_grid, tiles_overlapping
from godrays_jax.raster.geometry import EDGE_C, Geometry, sphere_bounds, triangle_bounds, triangle_setup, triangle_table
from godrays_jax.raster.vectors import unit_first
from godrays_jax.raster.visibility import Layer, Layers, merge_picks, no_picks, sphere_picks, sphere_surface, triangle_picks, triangle_surface

# Fine tiles evaluated together; tile grids are multiples of 4 x 4 tiles.
_TILES_PER_BATCH = 16


def _bucket_sizes(limit: int) -> tuple[int, ...]:
    """The candidate counts a batch of tiles is evaluated with: 0 (nothing to
    test), then doubling up to `limit`; a batch takes the smallest that holds
    its busiest tile."""
    sizes = [0]
    while sizes[-1] < limit:
        sizes.append(min(max(1, 2 * sizes[-1]), limit))
    return tuple(sizes)


def rasterize(geometry: Geometry, camera: Camera, finish, *, tile_size: int, capacity: int, tile_mask: Array | None = None):
    """`finish(layers, px, py)` of every pixel, as (H, W, ...) images.

    `finish` turns the three layers of `P` pixels (a `Layers` of (P,) and
    component-first (3, P) arrays, or None where no geometry can touch them) at pixel
    positions `px`, `py` (P,) into a pytree of (P, ...) arrays. Tiles are sorted
    by how many triangles and spheres overlap them and evaluated
    `_TILES_PER_BATCH` at a time, each batch with the smallest bucket of
    candidates that holds its busiest tile (a `lax.switch`, so empty sky costs
    only `finish(None, ...)` and a few busy tiles do not pad the others). Tiles
    where `tile_mask` is False are treated as empty."""
    tiles_y, tiles_x = tile_grid(camera, tile_size)
    tile_count = tiles_y * tiles_x
    triangle_count, sphere_count = geometry.corners.shape[0], geometry.radii.shape[0]
    setup, drawn = triangle_setup(geometry, camera)
    triangle_lists = bin_triangles(
        jax.lax.stop_gradient(triangle_bounds(geometry, camera, drawn)),
        jax.lax.stop_gradient(geometry.corners[..., 2].min(axis=1)),
        tile_size=tile_size,
        tiles_y=tiles_y,
        tiles_x=tiles_x,
        capacity=capacity,
    ).reshape(tile_count, capacity)
    triangle_loads = jnp.sum(triangle_lists >= 0, axis=1)
    sphere_overlap = tiles_overlapping(jax.lax.stop_gradient(sphere_bounds(geometry, camera)), tile_size, tiles_y, tiles_x)
    sphere_loads = jnp.sum(sphere_overlap, axis=1)
    # Overlapping spheres first (a stable sort keeps them in scene order).
    sphere_lists = jnp.argsort(~sphere_overlap, axis=1, stable=True).astype(jnp.int32)
    if tile_mask is not None:
        triangle_loads, sphere_loads = (jnp.where(tile_mask.reshape(-1), loads, 0) for loads in (triangle_loads, sphere_loads))

    # Row / entry `count` of each table is a sentinel that never covers anything.
    setup = jnp.concatenate([setup, jnp.zeros((1, setup.shape[1])).at[0, EDGE_C].set(-1e9)])
    columns = jnp.concatenate([triangle_table(geometry, camera), jnp.zeros((1, 27))]).T
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
            triangle_picks(setup, triangle_objects, candidates[:, :size], px, py, camera, slot_bits) if size else no_picks(px.shape)
        )
        sphere_branch = lambda size: lambda candidates: (
            sphere_picks(centers, radii, sphere_objects, candidates[:, :size], px, py, camera, slot_bits) if size else no_picks(px.shape)
        )
        triangles = jax.lax.switch(triangle_size, [triangle_branch(size) for size in triangle_sizes], triangle_candidates)
        spheres = jax.lax.switch(sphere_size, [sphere_branch(size) for size in sphere_sizes], sphere_candidates)
        layers = merge_picks(triangles, spheres)

        px, py = px.reshape(-1), py.reshape(-1)
        f = camera.focal_px
        rays = jnp.stack([(px - 0.5 * camera.width) / f, (0.5 * camera.height - py) / f, jnp.ones_like(px)])

        def surface(from_triangles, index):
            from_triangles, index = from_triangles.reshape(-1), index.reshape(-1)
            found = index >= 0
            position, normal = triangle_surface(columns[:, jnp.where(from_triangles & found, index, triangle_count)], px, py)
            if sphere_count:
                sphere = jnp.where(~from_triangles & found, index, sphere_count)
                sphere_position, sphere_normal = sphere_surface(centers.T[:, sphere], radii[sphere], rays)
                position = jnp.where(from_triangles, position, sphere_position)
                normal = jnp.where(from_triangles, normal, sphere_normal)
            return position, unit_first(normal)

        # One copy of the surface code for the three layers keeps compilation short.
        positions, normals = jax.vmap(surface)(*(jnp.stack([layer[i] for layer in layers]) for i in (0, 2)))
        found = Layers(*(Layer(layer[3].reshape(-1), layer[4].reshape(-1), positions[i], normals[i]) for i, layer in enumerate(layers)))
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
