"""The glow pass (the sun-overcasting article): the scaled geometry rasterized again, only in the tiles near the source."""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from godrays_jax.primitives.camera import Camera
from godrays_jax.raster.binning import tile_grid, tiles_overlapping
from godrays_jax.raster.geometry import EMPTY_BOX, Geometry, flatten, sphere_bounds, triangle_bounds, triangle_setup
from godrays_jax.raster.scene import Scene
from godrays_jax.raster.shading import sky, world_rays
from godrays_jax.raster.tile_loop import rasterize
from godrays_jax.raster.visibility import Layers, object_weight, total_coverage

GLOW_SOURCE_SCALE = 1.3
"""The sun-overcasting article's enlargement of the sun object in the glow pass."""
GLOW_OCCLUDER_SCALE = 0.8
"""... and its shrinking of every other object."""
GLOW_COLOR = (0.8, 0.5, 0.0, 0.65)
"""The glow pass's colour, premultiplied RGBA (the sun-overcasting article)."""


def glow_tiles(scene: Scene, camera: Camera, glow: Geometry, sky_light: Float[Array, "H W"] | None, tile_size: int) -> Array:
    """(T,) booleans: the tiles where the glow pass can be non-zero. With a sun
    object, those its enlarged outline's bounds overlap (every other object is
    transparent black there); without one, those the sky's sun spot reaches."""
    tiles_y, tiles_x = tile_grid(camera, tile_size)
    if scene.sun is None:
        padded = jnp.pad(sky_light, ((0, tiles_y * tile_size - camera.height), (0, tiles_x * tile_size - camera.width)))
        return padded.reshape(tiles_y, tile_size, tiles_x, tile_size).max(axis=(1, 3)).reshape(-1) > 0
    _, drawn = triangle_setup(glow, camera)
    empty = jnp.array(EMPTY_BOX)
    boxes = jnp.concatenate([
        jnp.where((glow.triangle_object == scene.sun)[:, None], triangle_bounds(glow, camera, drawn), empty),
        jnp.where((glow.sphere_object == scene.sun)[:, None], sphere_bounds(glow, camera), empty),
    ])
    union = jnp.concatenate([boxes[:, :2].min(axis=0), boxes[:, 2:].max(axis=0)])
    return tiles_overlapping(jax.lax.stop_gradient(union)[None], tile_size, tiles_y, tiles_x)[:, 0]


def glow_scales(scene: Scene, glow_source_scale, glow_occluder_scale) -> tuple:
    """Each object's scale in the glow pass: the sun object enlarged, every other shrunk."""
    return tuple(glow_source_scale if i == scene.sun else glow_occluder_scale for i in range(len(scene.objects)))


def glow_pass(
    scene: Scene, camera: Camera, glow_source_scale, glow_occluder_scale, glow_color: Float[Array, "4"], *, tile_size: int, capacity: int
) -> Float[Array, "H W 4"]:
    """The glow pass: `glow_color` times the sun object's coverage of the scaled scene (or, without a sun
    object, the sky's sun spot where the scaled scene leaves it open); transparent black elsewhere."""

    def sky_light(rays):
        return jnp.clip(sky(scene, camera, rays)[1], 0.0, 1.0)

    def finish_glow(layers: Layers | None, px, py) -> Float[Array, "P"]:
        """How much of the glow colour each of P pixels gets."""
        if scene.sun is not None:
            return jnp.zeros(px.shape) if layers is None else object_weight(layers, scene.sun)
        light = sky_light(world_rays(camera, px, py))
        return light if layers is None else (1.0 - total_coverage(layers)) * light

    glow = flatten(scene, camera, glow_scales(scene, glow_source_scale, glow_occluder_scale))
    if scene.sun is None:
        rows, columns = jnp.meshgrid(jnp.arange(camera.height) + 0.5, jnp.arange(camera.width) + 0.5, indexing="ij")
        light = sky_light(world_rays(camera, columns.reshape(-1), rows.reshape(-1))).reshape(camera.height, camera.width)
    else:
        light = None
    tiles = glow_tiles(scene, camera, glow, light, tile_size)
    glow_weight = rasterize(glow, camera, finish_glow, tile_size=tile_size, capacity=capacity, tile_mask=tiles)
    return glow_weight[..., None] * glow_color
