"""Lens dirt, the dirt texture and the sky sun spot (seed 001) against slow NumPy loops."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import godrays_jax as gr
from godrays_jax.kernels import lens
from godrays_jax.primitives.camera import Camera, project_point
import reference

H, W = 9, 12
FOV = 60.0


def _direction(px, py, height, width, fov, forward=1.0):
    focal = 0.5 * width / math.tan(math.radians(fov) / 2)
    ray = np.array([(px - width / 2) / focal, (height / 2 - py) / focal, forward])
    return ray / np.linalg.norm(ray)


def _reference_lens_dirt(dirt, depth, light, fov, far, colour, power, scale, aberration, view="pixel", in_front=True):
    height, width = depth.shape
    toward = _direction(light[0], light[1], height, width, fov, 1.0 if in_front else -1.0)
    out = np.zeros((height, width, 3))
    for row in range(height):
        for col in range(width):
            ray = _direction(col + 0.5, row + 0.5, height, width, fov) if view == "pixel" else np.array([0, 0, 1.0])
            ldepth = 1.0 if not np.isfinite(depth[row, col]) else min(max(depth[row, col] / far, 0.0), 1.0)
            intensity = min(max(ray @ toward * max(ldepth, 0.8), 0.0), 1.0) ** power * scale
            u, v = (col + 0.5) / width, (row + 0.5) / height
            th, tw = dirt.shape[:2]
            texels = [
                reference.bilinear(dirt, u * tw, v * th)[0],
                reference.bilinear(dirt, u * tw, (v + aberration) * th)[0],
                reference.bilinear(dirt, (u + aberration) * tw, v * th)[0],
            ]
            out[row, col] = np.array(texels) * colour * intensity
    return out


def _reference_sun_spot(height, width, light, fov, distance, sharpness, in_front=True):
    toward = _direction(light[0], light[1], height, width, fov, 1.0 if in_front else -1.0)
    out = np.zeros((height, width, 1))
    for row in range(height):
        for col in range(width):
            cosine = max(_direction(col + 0.5, row + 0.5, height, width, fov) @ toward, 0.0)
            out[row, col, 0] = min(cosine ** (distance * 2000), 1.0) * sharpness * 30
    return out


@pytest.fixture
def scene(rng):
    dirt = rng.uniform(0, 1, (7, 10, 1))
    depth = rng.uniform(20, 150, (H, W))
    depth[:3] = np.inf
    return dirt, depth


@pytest.mark.parametrize("view", ["pixel", "axis"])
@pytest.mark.parametrize("light", [(7.3, 3.1), (-20.0, 40.0)])
def test_lens_dirt_matches_numpy_loop(scene, view, light):
    dirt, depth = scene
    options = dict(fov_x_deg=FOV, far_plane=100.0, tint=(1.0, 0.7, 0.4), power=3.0, scale=2.0, aberration=0.05)
    expected = _reference_lens_dirt(dirt, depth, light, FOV, 100.0, np.array([1.0, 0.7, 0.4]), 3.0, 2.0, 0.05, view)
    eager = gr.lens_dirt(jnp.asarray(dirt, jnp.float32), jnp.asarray(depth, jnp.float32), jnp.asarray(light), view=view, **options)
    np.testing.assert_allclose(eager, expected, rtol=2e-5, atol=1e-6)
    jitted = jax.jit(lambda lt: gr.lens_dirt(jnp.asarray(dirt, jnp.float32), jnp.asarray(depth, jnp.float32), lt, view=view, **options))
    np.testing.assert_allclose(jitted(jnp.asarray(light)), expected, rtol=2e-5, atol=1e-6)


def test_lens_dirt_seed_constants_and_behind_camera(scene):
    dirt, depth = scene
    light = (5.5, 4.5)
    expected = _reference_lens_dirt(dirt, depth, light, FOV, 100.0, np.ones(3), 20.0, 2.0, lens.LENS_DIRT_ABERRATION)
    got = gr.lens_dirt(jnp.asarray(dirt), jnp.asarray(depth), jnp.asarray(light), fov_x_deg=FOV, far_plane=100.0)
    np.testing.assert_allclose(got, expected, rtol=1e-4, atol=1e-6)
    options = dict(fov_x_deg=FOV, far_plane=100.0)
    near = gr.lens_dirt_intensity(jnp.full((H, W), 40.0), jnp.asarray(light), **options)
    sky = gr.lens_dirt_intensity(jnp.full((H, W), jnp.inf), jnp.asarray(light), **options)
    np.testing.assert_allclose(near, sky * 0.8**20, rtol=1e-4)  # occluders nearer than 0.8 * far
    behind = _reference_lens_dirt(dirt, depth, light, FOV, 100.0, np.ones(3), 20.0, 2.0, 0.002, in_front=False)
    got_behind = gr.lens_dirt(jnp.asarray(dirt), jnp.asarray(depth), jnp.asarray(light), fov_x_deg=FOV, far_plane=100.0, light_in_front=False)
    np.testing.assert_allclose(got_behind, behind, atol=1e-7)
    assert float(got_behind.max()) < 1e-6


def test_sun_spot_matches_numpy_loop_under_vmap():
    lights = np.array([[6.5, 4.5], [6.2, 4.1], [30.0, -5.0]])
    expected = np.stack([_reference_sun_spot(H, W, light, FOV, 0.05, 1.5) for light in lights])
    spots = jax.vmap(lambda lt: gr.sun_spot(H, W, lt, fov_x_deg=FOV, sun_distance=0.05, sun_sharpness=1.5))(jnp.asarray(lights))
    np.testing.assert_allclose(spots, expected, rtol=1e-4, atol=1e-6)
    assert float(spots[0].max()) == pytest.approx(45.0, rel=1e-4)  # on the light: saturate(1) * 1.5 * 30


def test_view_directions_match_the_camera():
    camera = Camera(position=(0, 0, 0), target=(0, 0, 1), up=(0, 1, 0), fov_x_deg=FOV, width=W, height=H)
    rays = camera.ray_directions()
    np.testing.assert_allclose(gr.view_directions(H, W, fov_x_deg=FOV), rays / jnp.linalg.norm(rays, axis=-1, keepdims=True), atol=1e-6)
    for point in ([1.0, -2.0, -5.0], [0.5, 0.3, 4.0]):
        xy, _, in_front = project_point(camera, jnp.array(point))
        view = camera.to_view(jnp.array(point))
        np.testing.assert_allclose(gr.light_direction(xy, H, W, fov_x_deg=FOV, light_in_front=in_front), view / jnp.linalg.norm(view), atol=1e-5)


def test_dirt_texture_is_deterministic_and_bounded():
    first = gr.dirt_texture(24, 40, seed=3)
    assert first.shape == (24, 40, 1) and float(first.min()) >= 0 and float(first.max()) <= 1
    np.testing.assert_array_equal(first, gr.dirt_texture(24, 40, seed=3))
    assert float(jnp.abs(first - gr.dirt_texture(24, 40, seed=4)).max()) > 0.1
    assert float(gr.dirt_texture(8, 8, num_smudges=0, num_specks=0, num_rings=0).max()) == 0.0
    with pytest.raises(ValueError, match="num_specks"):
        gr.dirt_texture(8, 8, num_specks=-1)


def test_argument_errors_name_the_argument(scene):
    dirt, depth = scene
    with pytest.raises(ValueError, match="dirt"):
        gr.lens_dirt(jnp.ones((4, 4, 3)), jnp.asarray(depth), jnp.zeros(2), fov_x_deg=FOV, far_plane=1.0)
    with pytest.raises(ValueError, match="tint"):
        gr.lens_dirt(jnp.asarray(dirt), jnp.asarray(depth), jnp.zeros(2), fov_x_deg=FOV, far_plane=1.0, tint=(1.0, 1.0))
    with pytest.raises(ValueError, match="view"):
        gr.lens_dirt_intensity(jnp.asarray(depth), jnp.zeros(2), fov_x_deg=FOV, far_plane=1.0, view="eye")


@pytest.mark.parametrize("in_front", [True, False])
def test_gradients(x64, scene, in_front):
    """check_grads on every fittable input, for a light exactly on the view axis, in front and behind the camera."""
    light = (W / 2, H / 2)
    dirt, depth = scene

    @jax.jit
    def dirt_layer(power, scale, aberration, far, fov, light_xy):
        return gr.lens_dirt(
            jnp.asarray(dirt), jnp.asarray(depth), light_xy, fov_x_deg=fov, far_plane=far, power=power, scale=scale,
            aberration=aberration, light_in_front=in_front,
        )  # fmt: skip

    arguments = (4.0, 2.0, 0.03, 100.0, FOV, jnp.asarray(light, jnp.float64))
    # rtol covers bilinear sampling's kinks at texel boundaries inside the finite-difference step.
    check_grads(dirt_layer, arguments, order=1, modes=["rev"], eps=1e-5, rtol=1e-3)

    @jax.jit
    def spot(distance, sharpness, fov, light_xy):
        return gr.sun_spot(H, W, light_xy, fov_x_deg=fov, sun_distance=distance, sun_sharpness=sharpness, light_in_front=in_front, dtype=jnp.float64)

    check_grads(spot, (0.01, 1.0, FOV, jnp.asarray(light, jnp.float64)), order=1, modes=["rev"], eps=1e-5, rtol=1e-3)
    for grads in (jax.grad(lambda a: dirt_layer(*a).sum())(arguments), jax.grad(lambda a: spot(*a).sum())((1.0, 1.0, FOV, jnp.asarray(light)))):
        assert all(bool(jnp.all(jnp.isfinite(g))) for g in jax.tree_util.tree_leaves(grads))


@pytest.mark.slow
def test_effects_are_differentiable_and_vanish_behind():
    depth = jnp.full((24, 40), jnp.inf).at[16:].set(30.0)
    buffers = gr.Buffers(color=jnp.full((24, 40, 3), 0.2), depth=depth, coverage=jnp.isfinite(depth) * 1.0)
    light = jnp.array([20.5, 8.5])
    for effect in (gr.preset("vbex_lens_dirt"), gr.preset("vbex_sun_spot")):
        layer = effect.layer(buffers, light)
        assert float(layer.max()) > 0.1 and bool(jnp.all(jnp.isfinite(layer)))
        assert float(jnp.abs(effect.layer(buffers, light, light_in_front=False)).max()) == 0.0
        grads = jax.jit(jax.grad(lambda e: e(buffers, light).sum()))(effect)
        leaves = jax.tree_util.tree_leaves(grads)
        assert all(bool(jnp.all(jnp.isfinite(g))) for g in leaves) and any(float(jnp.abs(g).max()) > 0 for g in leaves)
