"""Where the scene's light is: its pixel and its distance from the camera."""

import math

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from godrays_jax.primitives.camera import Camera, project_point
from godrays_jax.raster.scene import DirectionalLight, Scene, Sphere


def _light_point(scene: Scene) -> Float[Array, "3"] | None:
    """The light's world position: the sun object's centre (a mesh's translation), else a point light's
    position; None for a directional light without a sun object (a light at infinity)."""
    if scene.sun is not None:
        sun = scene.objects[scene.sun]
        return sun.center if isinstance(sun, Sphere) else sun.translation
    if isinstance(scene.light, DirectionalLight):
        return None
    return scene.light.position


def light_pixel(scene: Scene, camera: Camera) -> tuple[Float[Array, "2"], Float[Array, ""], Array]:
    """Where the light is on screen: `project_point` of the sun object's centre
    (a mesh's translation), else of a point light, else of the camera position
    plus a directional light's direction (a light at infinity). Returns
    `(xy, view_depth, in_front)` as `project_point` does."""
    point = _light_point(scene)
    if point is None:
        point = camera.position + scene.light.direction / jnp.linalg.norm(scene.light.direction)
    return project_point(camera, point)


def light_distance(scene: Scene, camera: Camera) -> float:
    """The light's distance from the camera in scene units, as the depth buffer measures it (along the ray).

    The sun object's centre (a mesh's translation), else a point light's
    position; `inf` for a directional light without a sun object (a light at
    infinity). `render` stores it with the frame (`godrays:light_depth`): the
    XNA crepuscular-rays article's depth test and step clamp read it.
    """
    point = _light_point(scene)
    if point is None:
        return math.inf
    return float(np.linalg.norm(np.asarray(point, np.float64) - np.asarray(camera.position, np.float64)))
