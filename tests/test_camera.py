import json
import math
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from godrays_jax.primitives.camera import Camera, project_point

SCENES_JSON = Path(__file__).resolve().parent / "data" / "scenes.json"  # a path tracer's camera (tests/data/README.md)


def _camera(**overrides):
    arguments = dict(position=[0, 0, 0], target=[0, 0, -1], up=[0, 1, 0], fov_x_deg=50.0, width=320, height=180)
    arguments.update(overrides)
    return Camera(**arguments)


def _project_reference(position, target, up, fov_x_deg, width, height, point):
    forward = np.subtract(target, position, dtype=np.float64)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    relative = np.subtract(point, position, dtype=np.float64)
    x, y, z = relative @ right, relative @ true_up, relative @ forward
    focal = width / 2 / math.tan(math.radians(fov_x_deg) / 2)
    return np.array([width / 2 + focal * x / z, height / 2 - focal * y / z]), z


def test_reproduces_reference_light_position():
    scene = json.loads(SCENES_JSON.read_text())["colonnade"]
    camera = _camera(fov_x_deg=scene["fov_x_deg"], width=scene["width"], height=scene["height"])
    xy, depth, in_front = project_point(camera, jnp.asarray(scene["light_world"]))
    np.testing.assert_allclose(np.asarray(xy), scene["light_px"], atol=1e-4)
    assert bool(in_front) and float(depth) == pytest.approx(100.0)


@pytest.mark.parametrize("use_jit", [False, True])
def test_matches_numpy_for_general_pose(use_jit):
    rng = np.random.default_rng(0)
    position, target, up = [1.0, 2.0, 3.0], [-2.0, 0.5, -4.0], [0.1, 1.0, 0.2]
    camera = _camera(position=position, target=target, up=up, fov_x_deg=70.0, width=64, height=48)
    points = rng.normal(size=(20, 3)) * 3 + np.array(target)
    project = jax.jit(project_point) if use_jit else project_point
    xy, depth, in_front = project(camera, jnp.asarray(points, jnp.float32))
    for i, point in enumerate(points):
        expected_xy, expected_depth = _project_reference(position, target, up, 70.0, 64, 48, point)
        assert float(depth[i]) == pytest.approx(expected_depth, abs=1e-4)
        assert bool(in_front[i]) == (expected_depth > 0)
        if expected_depth > 0.5:
            np.testing.assert_allclose(np.asarray(xy[i]), expected_xy, rtol=1e-4, atol=1e-3)


def test_target_projects_to_image_centre():
    camera = _camera(position=[3, 1, 2], target=[0, 0, 0], width=40, height=30)
    xy, _, _ = project_point(camera, camera.target)
    np.testing.assert_allclose(np.asarray(xy), [20.0, 15.0], atol=1e-4)


def test_behind_camera_and_camera_plane_are_finite():
    camera = _camera()
    points = jnp.asarray([[0.0, 1.0, 5.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    xy, depth, in_front = project_point(camera, points)
    assert np.all(np.isfinite(np.asarray(xy)))
    assert not np.any(np.asarray(in_front))
    gradient = jax.grad(lambda p: project_point(camera, p)[0].sum())(jnp.asarray([1.0, 0.0, 0.0]))
    assert np.all(np.isfinite(np.asarray(gradient)))


def test_gradient_with_respect_to_fov_is_finite_and_signed():
    camera = _camera()
    point = jnp.asarray([-5.0, 1.5, -100.0])

    def light_x(fov):
        return project_point(eqx.tree_at(lambda c: c.fov_x_deg, camera, fov), point)[0][0]

    gradient = jax.grad(light_x)(jnp.float32(50.0))
    # A wider field of view pulls an off-centre point towards the centre.
    assert np.isfinite(float(gradient)) and float(gradient) > 0


@pytest.mark.parametrize(
    "overrides, field",
    [
        (dict(up=[0, 0, -1]), "up"),
        (dict(target=[0, 0, 0]), "target"),
        (dict(fov_x_deg=180.0), "fov_x_deg"),
        (dict(width=0), "width"),
        (dict(near=2.0, far=1.0), "near"),
        (dict(position=[0, 0]), "position"),
    ],
)
def test_bad_camera_raises_naming_the_field(overrides, field):
    with pytest.raises(ValueError, match=field):
        _camera(**overrides)
