"""The jitted rasterizer: `render(scene, camera) -> Buffers`; docs/rasterizer.md says how it works."""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Int

from godrays_jax.primitives.buffers import Buffers
from godrays_jax.primitives.camera import Camera
from godrays_jax.raster.binning import COARSE_CAPACITY_FACTOR, COARSE_TILES_PER_SIDE, tile_loads
from godrays_jax.raster.geometry import flatten
from godrays_jax.raster.glow_pass import GLOW_COLOR, GLOW_OCCLUDER_SCALE, GLOW_SOURCE_SCALE, glow_pass, glow_scales
from godrays_jax.raster.scene import Scene
from godrays_jax.raster.shading import shade_pixels
from godrays_jax.raster.tile_loop import rasterize

DEFAULT_TILE_CAPACITY = 128
"""The tile capacity under a JAX transformation, where it cannot be planned from the scene."""


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
    coarse tile (which keeps `COARSE_CAPACITY_FACTOR` times as many). Needs
    concrete values."""
    glow = glow_scales(scene, glow_source_scale, glow_occluder_scale)
    busiest = max(
        -(-int(_planned_loads(scene, camera, scales, size)[0]) // factor)
        for scales in (None, glow)
        for size, factor in ((tile_size, 1), (tile_size * COARSE_TILES_PER_SIDE, COARSE_CAPACITY_FACTOR))
    )
    return 1 << max(busiest - 1, 0).bit_length()


@eqx.filter_jit
def _planned_loads(scene: Scene, camera: Camera, scales, tile_size: int) -> Int[Array, "T"]:
    return tile_loads(flatten(scene, camera, scales), camera, tile_size)


@eqx.filter_jit
def _render(scene: Scene, camera: Camera, glow_source_scale, glow_occluder_scale, glow_color, *, with_glow_pass: bool, tile_size: int, capacity: int) -> Buffers:
    finish = lambda layers, px, py: shade_pixels(scene, camera, layers, px, py)
    buffers = rasterize(flatten(scene, camera, None), camera, finish, tile_size=tile_size, capacity=capacity)
    glow = None
    if with_glow_pass:
        glow = glow_pass(scene, camera, glow_source_scale, glow_occluder_scale, glow_color, tile_size=tile_size, capacity=capacity)
    return Buffers(**buffers, glow_pass=glow)
