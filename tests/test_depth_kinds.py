"""Depth as renderers write it: planar depth (along the camera's axis) read as distance along each ray."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import godrays_jax as gr
from godrays_jax.primitives.buffers import Buffers
from godrays_jax.primitives.camera import Camera, planar_to_ray_depth


def _ray_depth_loop(planar, fov_x_deg):
    """Slow and obvious: each pixel centre's direction with forward component 1, times its planar depth."""
    height, width = planar.shape
    focal = (width / 2) / math.tan(math.radians(fov_x_deg) / 2)
    out = np.empty_like(planar, dtype=np.float64)
    for row in range(height):
        for col in range(width):
            direction = np.array([(col + 0.5 - width / 2) / focal, (height / 2 - row - 0.5) / focal, 1.0])
            out[row, col] = planar[row, col] * np.linalg.norm(direction)
    return out


def _planar(rng, height=7, width=12):
    depth = rng.uniform(0.5, 50.0, (height, width))
    depth[0, 3] = depth[-1, 0] = np.inf  # sky
    return depth


@pytest.mark.parametrize("fov", [20.0, 50.0, 120.0])
def test_matches_loop(rng, fov):
    planar = _planar(rng)
    expected = _ray_depth_loop(planar, fov)
    got = np.asarray(planar_to_ray_depth(jnp.asarray(planar, jnp.float32), fov_x_deg=fov))
    np.testing.assert_allclose(got, expected, rtol=2e-6)
    assert np.isposinf(got[0, 3]) and np.isposinf(got[-1, 0])
    # At the centre of an odd-sized frame the two kinds agree.
    centre = np.asarray(planar_to_ray_depth(jnp.full((3, 5), 4.0), fov_x_deg=fov))[1, 2]
    assert centre == pytest.approx(4.0)


def test_agrees_with_camera_rays(rng):
    """`Camera.ray_directions()` have forward component 1: their length is the conversion."""
    camera = Camera(position=[0, 0, 0], target=[0, 0, -1], up=[0, 1, 0], fov_x_deg=65.0, width=12, height=7)
    lengths = np.linalg.norm(np.asarray(camera.ray_directions()), axis=-1)
    planar = _planar(rng)
    expected = np.where(np.isinf(planar), np.inf, planar * lengths)
    got = np.asarray(planar_to_ray_depth(jnp.asarray(planar, jnp.float32), fov_x_deg=65.0))
    np.testing.assert_allclose(got, expected, rtol=2e-6)


def test_jit_vmap_and_grad(rng):
    planar = jnp.asarray(np.stack([_planar(rng), _planar(rng)]), jnp.float32)
    fovs = jnp.asarray([30.0, 70.0])
    batched = jax.jit(jax.vmap(lambda d, f: planar_to_ray_depth(d, fov_x_deg=f)))(planar, fovs)
    for index in range(2):
        np.testing.assert_allclose(
            np.asarray(batched[index]), _ray_depth_loop(np.asarray(planar[index]), float(fovs[index])), rtol=2e-6
        )

    def total(fov):
        depth = jax.vmap(lambda d: planar_to_ray_depth(d, fov_x_deg=fov))(planar)
        return jnp.sum(jnp.where(jnp.isfinite(depth), depth, 0.0))

    gradient = jax.grad(total)(jnp.float32(50.0))
    assert np.isfinite(float(gradient)) and float(gradient) > 0  # a wider view: the same plane lies farther along the off-centre rays


def test_check_grads(x64, rng):
    planar = jnp.asarray(_planar(rng, 4, 5))
    finite = jnp.where(jnp.isinf(planar), 3.0, planar)
    check_grads(lambda d, f: planar_to_ray_depth(d, fov_x_deg=f), (finite, 55.0), order=1, modes=["fwd", "rev"])
    # Sky pixels: finite gradients in the field of view and the depth.
    grads = jax.grad(lambda d, f: jnp.sum(jnp.where(jnp.isinf(planar), 0.0, planar_to_ray_depth(d, fov_x_deg=f))),
                     argnums=(0, 1))(planar, 55.0)  # fmt: skip
    assert all(np.all(np.isfinite(np.asarray(g))) for g in grads)


def _buffers(depth, kind):
    height, width = depth.shape
    color = jnp.full((height, width, 3), 0.3, jnp.float32)
    coverage = np.isfinite(depth).astype(np.float32)
    return Buffers(color=color, depth=jnp.asarray(depth, jnp.float32), coverage=jnp.asarray(coverage), depth_kind=kind)


def test_buffers_ray_depth(rng):
    planar = _planar(rng)
    np.testing.assert_array_equal(np.asarray(_buffers(planar, "ray").ray_depth(40.0)), planar.astype(np.float32))
    np.testing.assert_allclose(np.asarray(_buffers(planar, "planar").ray_depth(40.0)), _ray_depth_loop(planar, 40.0), rtol=2e-6)
    with pytest.raises(ValueError, match="fov_x_deg"):
        _buffers(planar, "planar").ray_depth()
    with pytest.raises(ValueError, match="depth_kind"):
        _buffers(planar, "z")


def test_fog_reads_ray_depth(rng):
    """A planar frame fogs as its ray-depth twin does, converted with the effect's own field of view."""
    planar = _planar(rng, 18, 32)
    fog = gr.preset("participating_media")
    light = jnp.asarray([20.0, 4.0])
    fov = float(fog.fov_x_deg)
    from_planar = fog(_buffers(planar, "planar"), light)
    from_ray = fog(_buffers(_ray_depth_loop(planar, fov), "ray"), light)
    np.testing.assert_allclose(np.asarray(from_planar), np.asarray(from_ray), rtol=1e-5, atol=1e-6)
    # ... and not as the planar depth read as ray depth would.
    misread = fog(_buffers(planar, "ray"), light)
    assert float(jnp.max(jnp.abs(misread - from_ray))) > 1e-3


def test_depth_test_reads_planar_depth_as_the_hardware_does(rng):
    """The XNA depth test compares hardware depth, which is planar: planar depth as stored, ray depth converted
    with the effect's `fov_x_deg` give the same picture; ray depth read as planar would not."""
    effect = dataclasses.replace(gr.preset("xna_crepuscular"), sun_size=3.0, threshold=0.0)  # a .3 UV flare
    planar = np.full((18, 32), 10.48)  # within the bias (.00025 in z/w) of a light at 10.5 along the axis
    planar[:, :8] = np.inf
    planar[:, 28:] = 4.0  # in front of the light: blanked
    light = jnp.asarray([16.0, 9.0])
    fov = float(effect.fov_x_deg)
    from_planar = effect(_buffers(planar, "planar"), light, light_depth=10.5)
    from_ray = effect(_buffers(_ray_depth_loop(planar, fov), "ray"), light, light_depth=10.5)
    np.testing.assert_allclose(np.asarray(from_planar), np.asarray(from_ray), rtol=1e-5, atol=1e-6)
    misread = effect(_buffers(planar, "ray"), light, light_depth=10.5)
    assert float(jnp.max(jnp.abs(misread - from_ray))) > 1e-3
    # A light at infinity (on the far plane) reads the same from either depth kind.
    at_infinity = effect(_buffers(planar, "planar"), light)
    np.testing.assert_allclose(np.asarray(at_infinity), np.asarray(effect(_buffers(planar, "ray"), light)))
