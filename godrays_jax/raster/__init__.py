"""A small differentiable rasterizer in JAX: scene description, loading, render passes."""

from godrays_jax.raster.rasterizer import (
    GLOW_COLOR as GLOW_COLOR,
    GLOW_OCCLUDER_SCALE as GLOW_OCCLUDER_SCALE,
    GLOW_SOURCE_SCALE as GLOW_SOURCE_SCALE,
    light_pixel as light_pixel,
    plan_tile_capacity as plan_tile_capacity,
    render as render,
)
from godrays_jax.raster.scene import (
    DirectionalLight as DirectionalLight,
    Material as Material,
    Mesh as Mesh,
    PointLight as PointLight,
    Scene as Scene,
    Sky as Sky,
    Sphere as Sphere,
)
from godrays_jax.raster.loading import (
    load_obj as load_obj,
    load_scene as load_scene,
    scene_from_dict as scene_from_dict,
    uv_sphere as uv_sphere,
)
