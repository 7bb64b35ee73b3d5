"""Binning: which triangles and spheres each screen tile holds, in two levels of tiles."""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from godrays_jax.primitives.camera import Camera
from godrays_jax.raster.geometry import EMPTY_BOX, Geometry, triangle_bounds, triangle_setup

COARSE_TILES_PER_SIDE = 4
"""A coarse tile is this many fine tiles a side."""
# A coarse tile keeps up to this many times a fine tile's capacity: triangles
# span several fine tiles, so a coarse tile holds a few times its busiest fine tile's load.
COARSE_CAPACITY_FACTOR = 4


def tile_grid(camera: Camera, tile_size: int) -> tuple[int, int]:
    """Fine tiles down and across: the frame covered by whole coarse tiles."""
    coarse = tile_size * COARSE_TILES_PER_SIDE
    return -(-camera.height // coarse) * COARSE_TILES_PER_SIDE, -(-camera.width // coarse) * COARSE_TILES_PER_SIDE


def _overlaps(low: Array, high: Array, starts: Array, size: float) -> Array:
    """Whether the box sides `[low, high]` (pixels) meet the tiles `[start, start + size)`, broadcast together."""
    return (low < starts + size) & (high >= starts)


def _rows_and_columns(boxes: Float[Array, "N 4"], size: float, rows: int, columns: int) -> tuple[Array, Array]:
    """(rows, N) and (columns, N) booleans: which boxes (x0, y0, x1, y1) meet each row and column of tiles."""
    starts = lambda count: jnp.arange(count, dtype=jnp.float32)[:, None] * size
    return _overlaps(boxes[None, :, 1], boxes[None, :, 3], starts(rows), size), _overlaps(
        boxes[None, :, 0], boxes[None, :, 2], starts(columns), size
    )


def _first_overlapping(overlap: Array, capacity: int) -> Int[Array, "... K"]:
    """Indices of the first `capacity` True entries along the last axis, -1 past the end."""
    running = jnp.cumsum(overlap, axis=-1, dtype=jnp.int32)
    wanted = jnp.arange(1, capacity + 1, dtype=jnp.int32)
    flat = running.reshape(-1, running.shape[-1])
    found = jax.vmap(lambda row: jnp.searchsorted(row, wanted, side="left"))(flat)
    found = jnp.where(found < running.shape[-1], found, -1)
    return found.reshape(*running.shape[:-1], capacity)


def bin_triangles(
    boxes: Float[Array, "N 4"], order_key: Float[Array, "N"], *, tile_size: int, tiles_y: int, tiles_x: int, capacity: int
) -> Int[Array, "TY TX K"]:
    """Per fine tile, up to `capacity` triangle indices, nearest first, -1 for none.

    Two levels (coarse tiles of `COARSE_TILES_PER_SIDE` fine tiles a side,
    keeping up to `COARSE_CAPACITY_FACTOR * capacity` each, then fine tiles)
    keep the tile x triangle overlap table small."""
    coarse = tile_size * COARSE_TILES_PER_SIDE
    order = jnp.argsort(order_key)
    boxes = boxes[order]
    coarse_y, coarse_x = tiles_y // COARSE_TILES_PER_SIDE, tiles_x // COARSE_TILES_PER_SIDE

    overlap_y, overlap_x = _rows_and_columns(boxes, coarse, coarse_y, coarse_x)
    coarse_capacity = min(capacity * COARSE_CAPACITY_FACTOR, boxes.shape[0])
    coarse_lists = _first_overlapping(overlap_y[:, None, :] & overlap_x[None, :, :], coarse_capacity)

    fine_boxes = jnp.where((coarse_lists >= 0)[..., None], boxes[jnp.maximum(coarse_lists, 0)], jnp.array(EMPTY_BOX))
    offsets = jnp.arange(COARSE_TILES_PER_SIDE, dtype=jnp.float32) * tile_size
    starts_y = jnp.arange(coarse_y, dtype=jnp.float32)[:, None] * coarse + offsets[None, :]
    starts_x = jnp.arange(coarse_x, dtype=jnp.float32)[:, None] * coarse + offsets[None, :]
    # Axes: (coarse y, coarse x, fine y within, fine x within, coarse list slot).
    fine = lambda side: fine_boxes[:, :, None, None, :, side]
    in_y = _overlaps(fine(1), fine(3), starts_y[:, None, :, None, None], tile_size)
    in_x = _overlaps(fine(0), fine(2), starts_x[None, :, None, :, None], tile_size)
    local = _first_overlapping(in_y & in_x, capacity)
    coarse_slots = jnp.broadcast_to(coarse_lists[:, :, None, None, :], local.shape[:-1] + coarse_lists.shape[-1:])
    fine = jnp.where(local >= 0, jnp.take_along_axis(coarse_slots, jnp.maximum(local, 0), axis=-1), -1)
    fine = jnp.where(fine >= 0, order[jnp.maximum(fine, 0)], -1)
    return fine.transpose(0, 2, 1, 3, 4).reshape(tiles_y, tiles_x, capacity)


def tile_loads(geometry: Geometry, camera: Camera, tile_size: int) -> Int[Array, "T"]:
    """How many triangles overlap each fine tile, busiest first."""
    tiles_y, tiles_x = tile_grid(camera, tile_size)
    _, drawn = triangle_setup(geometry, camera)
    in_y, in_x = _rows_and_columns(triangle_bounds(geometry, camera, drawn), tile_size, tiles_y, tiles_x)
    # A product of the row and column tables counts the pairs without the (T, N) table.
    loads = jnp.matmul(in_y.astype(jnp.float32), in_x.astype(jnp.float32).T, precision="highest")
    return -jnp.sort(-loads.reshape(-1)).astype(jnp.int32)


def tiles_overlapping(boxes: Float[Array, "M 4"], tile_size: int, tiles_y: int, tiles_x: int) -> Array:
    """(T, M) booleans: which pixel boxes overlap which tile (row-major tiles)."""
    in_y, in_x = _rows_and_columns(boxes, tile_size, tiles_y, tiles_x)
    return (in_y[:, None, :] & in_x[None, :, :]).reshape(tiles_y * tiles_x, -1)
