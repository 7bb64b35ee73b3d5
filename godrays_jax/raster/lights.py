"""Where the scene's lights are: each one's pixel and its distance from the camera."""

import math

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from godrays_jax.primitives.camera import Camera, project_point
from godrays_jax.raster.scene import DirectionalLight, Scene, Sphere


def light_point(scene: Scene, index: int) -> Float[Array, "3"] | None:
    """The world position of `scene.lights[index]`: for the first light the sun object's centre (a mesh's
    translation), else a point light's position; None for a directional light without a sun object (a light at
    infinity)."""
    light = scene.lights[index]
    if index == 0 and scene.sun is not None:
        sun = scene.objects[scene.sun]
        return sun.center if isinstance(sun, Sphere) else sun.translation
    if isinstance(light, DirectionalLight):
        return None
    return light.position


def checked_light_index(scene: Scene, index: int) -> int:
    if not (isinstance(index, int) and 0 <= index < len(scene.lights)):
        raise ValueError(f"index must be a light of the scene's {len(scene.lights)}, got {index!r}")
    return index


def light_pixel(scene: Scene, camera: Camera, *, index: int = 0) -> tuple[Float[Array, "2"], Float[Array, ""], Array]:
    """Where a light of the scene (`scene.lights[index]`, the first by default) is on screen: `project_point` of
    the sun object's centre (a mesh's translation; the first light's), else of a point light, else of the camera
    position plus a directional light's direction (a light at infinity). Returns `(xy, view_depth, in_front)` as
    `project_point` does."""
    index = checked_light_index(scene, index)
    point = light_point(scene, index)
    if point is None:
        direction = scene.lights[index].direction
        point = camera.position + direction / jnp.linalg.norm(direction)
    return project_point(camera, point)


def light_distance(scene: Scene, camera: Camera, *, index: int = 0) -> float:
    """A light's distance from the camera in scene units (`scene.lights[index]`, the first by default), as the
    depth buffer measures it (along the ray).

    The sun object's centre (a mesh's translation; the first light's), else a
    point light's position; `inf` for a directional light without a sun object
    (a light at infinity). `render` stores it with the frame
    (`godrays:light_depth`): the XNA crepuscular-rays article's depth test and
    step clamp read it.
    """
    point = light_point(scene, checked_light_index(scene, index))
    if point is None:
        return math.inf
    return float(np.linalg.norm(np.asarray(point, np.float64) - np.asarray(camera.position, np.float64)))
