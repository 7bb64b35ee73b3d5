"""Where the scene's light is: its pixel and its distance from the camera."""

import math

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from godrays_jax.primitives.camera import Camera, project_point
from godrays_jax.raster.scene import DirectionalLight, Scene, Sphere


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
