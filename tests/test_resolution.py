"""Every preset gives the same picture at any resolution (sizes in frame units).

A frame drawn analytically in UV space (sky gradient, sun, pillars, ground,
every pass an effect reads) at 160x90 and at 480x270; each preset applied to
both; the large result box-downsampled 3x must agree with the small one to
35 dB (PSNR of `x / (1 + x)`), or within 3 dB of the two inputs' own
agreement. `benchmarks/bench_resolution.py` does the same on rendered scenes.
"""

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
from frames import slow_where

import godrays_jax as gr

SMALL = (90, 160)
FACTOR = 3
SAMPLES = 12  # coverage samples per small pixel and axis; the large frame takes the same points in UV
LIGHT_UV = np.array([0.41, 0.42])  # in the gap between the second and third pillars
LIGHT_DEPTH = 5000.0  # a far sun: the XNA preset's SunSize / z draws it .3 UV (at 50 its flare would fill the sky)
PILLARS = [(0.14 + 0.16 * k, 0.2 + 0.16 * k) for k in range(5)]


def _inside(u, v):
    """Which UV points are on a pillar or the ground (depth 10 and 15), else sky."""
    pillar = np.zeros(u.shape, bool)
    for left, right in PILLARS:
        pillar |= (u >= left) & (u < right) & (v >= 0.22)
    ground = v >= 0.78
    return pillar, ground


def _sun(u, v, aspect, radius):
    return np.hypot((u - LIGHT_UV[0]) * aspect, v - LIGHT_UV[1]) < radius


def frame(height: int, width: int) -> gr.Buffers:
    samples = SAMPLES * SMALL[1] // width
    aspect = width / height
    offsets = (np.arange(samples) + 0.5) / samples
    u = ((np.arange(width)[:, None] + offsets[None, :]).reshape(-1)) / width
    v = ((np.arange(height)[:, None] + offsets[None, :]).reshape(-1)) / height
    uu, vv = np.meshgrid(u, v)
    pillar, ground = _inside(uu, vv)

    def mean(values):
        return values.reshape(height, samples, width, samples, *values.shape[2:]).mean(axis=(1, 3))

    geometry = pillar | ground
    sky = (0.9 - 0.7 * vv)[..., None] * np.array([1.0, 0.7, 0.45]) + np.array([0.05, 0.1, 0.2])
    sun = _sun(uu, vv, aspect, 0.035) & ~geometry
    sky = sky + sun[..., None] * np.array([30.0, 24.0, 16.0])
    colour = np.where(pillar[..., None], 0.08, np.where(ground[..., None], 0.15 + 0.1 * uu[..., None], sky))
    glow = (_sun(uu, vv, aspect, 0.035 * 1.3) & ~_inside(uu, vv)[0])[..., None] * np.array([0.8, 0.5, 0.0, 0.65])
    centre_u = (np.arange(width) + 0.5) / width
    centre_v = (np.arange(height) + 0.5) / height
    cu, cv = np.meshgrid(centre_u, centre_v)
    centre_pillar, centre_ground = _inside(cu, cv)
    depth = np.where(centre_pillar, 10.0, np.where(centre_ground, 15.0, np.inf))
    return gr.Buffers(
        color=jnp.asarray(mean(colour), jnp.float32), depth=jnp.asarray(depth, jnp.float32),
        coverage=jnp.asarray(mean(geometry.astype(float)), jnp.float32),
        light_pass=jnp.asarray(mean(sun.astype(float)), jnp.float32),
        glow_pass=jnp.asarray(mean(glow), jnp.float32),
        glow_target=jnp.asarray(mean(sun[..., None] * np.array([30.0, 24.0, 16.0])), jnp.float32),
    )  # fmt: skip


def psnr(small, large) -> float:
    def display(image):
        image = np.maximum(np.asarray(image, np.float64)[..., :3], 0.0)
        return image / (1.0 + image)

    error = np.mean((display(small) - display(gr.downsample_box(jnp.asarray(large), FACTOR))) ** 2)
    return math.inf if error == 0 else 10 * math.log10(1.0 / error)


@pytest.fixture(scope="module")
def frames():
    (height, width) = SMALL
    return frame(height, width), frame(FACTOR * height, FACTOR * width)


def test_the_two_frames_agree(frames):
    small, large = frames
    assert psnr(small.color, large.color) > 40
    np.testing.assert_allclose(gr.downsample_box(large.coverage[..., None], FACTOR)[..., 0], small.coverage, atol=1e-6)


@eqx.filter_jit
def _apply(effect, buffers, light):
    # Compiled: the comparison is of resolutions, and an eager march dispatches (and compiles) each operation alone.
    return effect(buffers, light, light_depth=LIGHT_DEPTH), effect.layer(buffers, light, light_depth=LIGHT_DEPTH)


@pytest.mark.parametrize("name", slow_where(sorted(gr.PRESETS)))
def test_every_preset_gives_the_same_picture_at_three_times_the_resolution(frames, name):
    small, large = frames
    effect = gr.preset(name)
    results, layers = [], []
    for buffers in (small, large):
        light = jnp.asarray(LIGHT_UV * np.array([buffers.width, buffers.height]), jnp.float32)
        result, layer = _apply(effect, buffers, light)
        results.append(result)
        layers.append(layer)
    inputs = psnr(small.color, large.color)
    agreement = psnr(*results)
    assert agreement >= 35.0 or agreement >= inputs - 3.0, (name, agreement, inputs)
    assert float(jnp.max(jnp.abs(layers[0]))) > 1e-3  # each preset draws something here: the comparison is not vacuous


@pytest.mark.slow
def test_pixel_units_are_kept_for_a_caller_who_asks(frames):
    """`units="px"` holds sizes in pixels: the same numbers give a three times smaller flare on the large frame."""
    small, large = frames
    effect = gr.GodRays(flare_size=20.0, units="px", num_samples=16.0, max_samples=16)
    frame_units = gr.GodRays(flare_size=20.0 / small.width, num_samples=16.0, max_samples=16)
    light_small = jnp.asarray(LIGHT_UV * np.array([small.width, small.height]), jnp.float32)
    light_large = light_small * FACTOR
    pixels = psnr(effect.layer(small, light_small), effect.layer(large, light_large))
    frames_agree = psnr(frame_units.layer(small, light_small), frame_units.layer(large, light_large))
    assert frames_agree > pixels + 6
