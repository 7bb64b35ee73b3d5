"""A small differentiable rasterizer in JAX: scene description, loading, render passes."""

from godrays_jax.raster.glow_pass import GLOW_COLOR as GLOW_COLOR
from godrays_jax.raster.glow_pass import GLOW_OCCLUDER_SCALE as GLOW_OCCLUDER_SCALE
from godrays_jax.raster.glow_pass import GLOW_SOURCE_SCALE as GLOW_SOURCE_SCALE
from godrays_jax.raster.lights import light_distance as light_distance
from godrays_jax.raster.lights import light_pixel as light_pixel
from godrays_jax.raster.light_view import light_view as light_view
from godrays_jax.raster.loading import load_obj as load_obj
from godrays_jax.raster.loading import load_scene as load_scene
from godrays_jax.raster.loading import scene_from_dict as scene_from_dict
from godrays_jax.raster.loading import uv_sphere as uv_sphere
from godrays_jax.raster.rasterizer import plan_tile_capacity as plan_tile_capacity
from godrays_jax.raster.rasterizer import render as render
from godrays_jax.raster.scene import DirectionalLight as DirectionalLight
from godrays_jax.raster.scene import Material as Material
from godrays_jax.raster.scene import Mesh as Mesh
from godrays_jax.raster.scene import PointLight as PointLight
from godrays_jax.raster.scene import Scene as Scene
from godrays_jax.raster.scene import Sky as Sky
from godrays_jax.raster.scene import Sphere as Sphere
