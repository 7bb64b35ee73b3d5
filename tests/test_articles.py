"""Each article's whole pipeline, preset against a NumPy emulation of its shaders (`article_shaders`).

The emulation works in UV space with GPU sampler semantics (texel centres at
`(i + 0.5) / W`), independently of the library's pixel-space kernels: masks,
rays or flares, bright pass and blend, with the XNA article's step clamp and
depth test, kbEngine's low-resolution target and the VBex glow pyramid.
"""

import dataclasses
import math

import jax.numpy as jnp
import numpy as np
import pytest

import article_shaders as shaders
import godrays_jax as gr

HEIGHT, WIDTH = 48, 96  # a multiple of 16 both ways: the pyramid's levels tile exactly, as on the GPU
LIGHT = np.array([41.3, 17.6])
LIGHT_UV = (LIGHT[0] / WIDTH, LIGHT[1] / HEIGHT)
LIGHT_DEPTH = 20.0


def article_frame(seed=0) -> gr.Buffers:
    """Sky above, pillars nearer than the light, a wall beyond it, ground; every optional pass."""
    rng = np.random.default_rng(seed)
    depth = np.full((HEIGHT, WIDTH), np.inf)
    depth[34:, :] = 8.0  # ground
    depth[10:30, 60:80] = 40.0  # a wall beyond the light: the depth test lets the flare through
    for left in (20, 36, 52):
        depth[6:, left : left + 5] = 5.0  # pillars in front of the light
    sky = ~np.isfinite(depth)
    color = rng.uniform(0.0, 0.5, (HEIGHT, WIDTH, 3))
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH] + 0.5
    sun = (np.hypot(x - LIGHT[0], y - LIGHT[1]) < 6) & sky
    glow_pass = np.concatenate([np.clip(7 - np.hypot(x - LIGHT[0], y - LIGHT[1]), 0, 1)[..., None]] * 4, axis=-1)
    glow_pass *= np.array([0.8, 0.5, 0.0, 0.65]) * (depth > 5.0)[..., None]
    glow_target = rng.uniform(0.0, 1.0, (HEIGHT, WIDTH, 3)) * (rng.uniform(size=(HEIGHT, WIDTH, 1)) < 0.05) * 4
    return gr.Buffers(
        color=jnp.asarray(color, jnp.float32), depth=jnp.asarray(depth, jnp.float32),
        coverage=jnp.asarray(~sky, jnp.float32), light_pass=jnp.asarray(sun, jnp.float32),
        glow_pass=jnp.asarray(glow_pass, jnp.float32), glow_target=jnp.asarray(glow_target, jnp.float32),
    )  # fmt: skip


def host(buffers: gr.Buffers):
    return {name: None if getattr(buffers, name) is None else np.asarray(getattr(buffers, name), np.float64)
            for name in ("color", "depth", "coverage", "light_pass", "glow_pass", "glow_target")}  # fmt: skip


def asymmetric_texture(seed=1) -> np.ndarray:
    """A coloured texture with a black border and no symmetry: placement, flips and stretch all show."""
    rng = np.random.default_rng(seed)
    texture = rng.uniform(0.0, 1.0, (12, 9, 3)) * np.linspace(0.2, 1.0, 9)[None, :, None]
    texture[0], texture[-1], texture[:, 0], texture[:, -1] = 0, 0, 0, 0
    return texture.astype(np.float32)


@pytest.mark.parametrize("light_depth", [LIGHT_DEPTH, 0.3, math.inf])
@pytest.mark.parametrize("textured", [False, True])
def test_xna_crepuscular_is_the_articles_five_passes(light_depth, textured):
    buffers, frame = article_frame(), host(article_frame())
    effect = gr.preset("xna_crepuscular")
    flare = gr.procedural_flare()
    if textured:
        flare = asymmetric_texture()
        effect = dataclasses.replace(effect, flare_texture=flare)
    expected_frame, expected_layer = shaders.xna_crepuscular(
        frame["color"], frame["depth"], LIGHT_UV, light_depth, size=float(effect.flare_size), flare=flare,
        bias=effect.depth_bias, threshold=float(effect.threshold), tint=np.asarray(effect.tint),
        num_samples=128, density=0.5, decay=0.95, weight=1.0, exposure=0.15,
    )  # fmt: skip
    layer = effect.layer(buffers, jnp.asarray(LIGHT), light_depth=light_depth)
    np.testing.assert_allclose(layer, expected_layer, atol=2e-5)
    np.testing.assert_allclose(effect(buffers, jnp.asarray(LIGHT), light_depth=light_depth), expected_frame, atol=2e-5)
    assert float(np.max(expected_layer)) > 0.5  # the flare shows: not a comparison of two blank layers


def test_xna_depth_test_and_step_clamp_change_the_picture():
    """The wall beyond the light passes the depth test (not the sky test); a near light shortens the steps."""
    buffers = article_frame()
    effect = dataclasses.replace(gr.preset("xna_crepuscular"), threshold=0.0)  # the flare's faint edge shows too
    beyond = effect.layer(buffers, jnp.asarray(LIGHT), light_depth=LIGHT_DEPTH)
    at_infinity = effect.layer(buffers, jnp.asarray(LIGHT), light_depth=math.inf)
    wall = (slice(10, 30), slice(60, 64))
    assert float(jnp.min(beyond[wall] - at_infinity[wall])) >= 0
    assert float(jnp.max(beyond[wall] - at_infinity[wall])) > 5e-3
    near = effect.layer(buffers, jnp.asarray(LIGHT), light_depth=0.1)
    assert gr.step_clamp(0.1) == pytest.approx(0.1) and gr.step_clamp(LIGHT_DEPTH) == 0.5
    assert float(jnp.max(jnp.abs(near - beyond))) > 1e-3


def test_xna_bright_pass_saturates_only_the_core():
    buffers = article_frame()
    layer = np.asarray(gr.preset("xna_crepuscular").layer(buffers, jnp.asarray(LIGHT), light_depth=LIGHT_DEPTH))[..., 0]
    lit = layer > 1e-3
    assert lit.sum() > 100
    assert (layer >= layer.max() * 0.999).sum() < 0.25 * lit.sum()


def test_galaxy_vls_is_the_articles_pass():
    buffers, frame = article_frame(), host(article_frame())
    expected = shaders.galaxy_vls(frame["light_pass"][..., None], LIGHT_UV)
    layer = gr.preset("galaxy_vls").layer(buffers, jnp.asarray(LIGHT))  # white light: every channel alike
    np.testing.assert_allclose(layer, np.broadcast_to(expected, layer.shape), atol=1e-5)
    assert float(np.max(expected)) > 0.1


@pytest.mark.parametrize("textured", [False, True])
def test_kbengine_flares_are_the_articles_low_resolution_flare_outs(textured):
    buffers, frame = article_frame(), host(article_frame())
    effect = gr.preset("kbengine_flares")
    flare = gr.procedural_flare()
    if textured:
        flare = asymmetric_texture()
        effect = dataclasses.replace(effect, flare_texture=flare)
    factor = effect.resolution_factor
    assert factor > 1  # the article's low-resolution target
    side = max(HEIGHT, WIDTH)
    expected_frame, expected_layer = shaders.kbengine_flares(
        frame["color"], frame["depth"], LIGHT_UV, size=float(effect.flare_size), flare=flare, num_iters=20,
        scale_step=1.03, intensity=float(effect.intensity), sigma=float(effect.blur_sigma) * side / factor,
        radius=math.ceil(effect.blur_reach * side / factor - 1e-9), factor=factor, tint=np.asarray(effect.tint),
    )  # fmt: skip
    np.testing.assert_allclose(effect.layer(buffers, jnp.asarray(LIGHT)), expected_layer, atol=2e-5)
    np.testing.assert_allclose(effect(buffers, jnp.asarray(LIGHT)), expected_frame, atol=2e-5)
    assert float(np.max(expected_layer)) > 0.05


def test_sun_overcast_is_the_articles_blur_and_additive_sprite():
    buffers, frame = article_frame(), host(article_frame())
    expected_frame, expected_layer = shaders.sun_overcast(frame["color"], frame["glow_pass"], 0.015, passes=2)
    effect = gr.preset("sun_overcast")
    np.testing.assert_allclose(effect.layer(buffers, jnp.asarray(LIGHT)), expected_layer, atol=1e-5)
    np.testing.assert_allclose(effect(buffers, jnp.asarray(LIGHT)), expected_frame, atol=1e-5)
    assert float(np.max(expected_layer)) > 0.05


def _to_light(fov_x_deg):
    tan = math.tan(math.radians(fov_x_deg) / 2)
    ray = np.array([(2 * LIGHT_UV[0] - 1) * tan, (1 - 2 * LIGHT_UV[1]) * tan * HEIGHT / WIDTH, 1.0])
    return ray / np.linalg.norm(ray)


@pytest.mark.parametrize("in_power", [False, True])
def test_vbex_lens_dirt_is_the_articles_shader(in_power):
    buffers, frame = article_frame(), host(article_frame())
    effect = dataclasses.replace(gr.preset("vbex_lens_dirt"), depth_in_power=in_power, power=4.0)
    dirt = np.asarray(gr.dirt_texture(HEIGHT, WIDTH, seed=effect.dirt_seed), np.float64)
    expected = shaders.lens_dirt(
        dirt, frame["depth"], _to_light(50.0), 50.0, float(effect.far_plane), np.asarray(effect.tint), power=4.0,
        scale=2.0, offset=0.002, depth_in_power=in_power, floor=0.8,
    )  # fmt: skip
    np.testing.assert_allclose(effect.layer(buffers, jnp.asarray(LIGHT)), expected, atol=1e-5)
    open_sky = shaders.lens_dirt(
        dirt, np.full_like(frame["depth"], np.inf), _to_light(50.0), 50.0, float(effect.far_plane),
        np.asarray(effect.tint), power=4.0, scale=2.0, offset=0.002, depth_in_power=in_power, floor=0.8,
    )  # fmt: skip
    pillar = (20, 22)  # nearer than 0.8 * far_plane: dimmed to 0.8 after the power, 0.8 ** power inside it
    ratio = expected[pillar].sum() / open_sky[pillar].sum()
    assert ratio == pytest.approx(0.8 ** (4.0 if in_power else 1.0), rel=1e-6)


def test_vbex_sun_spot_adds_its_glow_at_full_strength():
    buffers, frame = article_frame(), host(article_frame())
    effect = gr.preset("vbex_sun_spot")
    assert float(effect.bloom_intensity) == 1.0
    spot = shaders.sun_spot(HEIGHT, WIDTH, _to_light(50.0), 50.0, 1.0, 1.0)
    spot = spot[..., None] * (frame["coverage"] == 0)[..., None] * np.asarray(effect.tint)
    side = max(HEIGHT, WIDTH)
    glow = shaders.bright_glow(spot, float(effect.bloom_blur_sigma) * side / 2, math.ceil(effect.bloom_blur_reach * side / 2 - 1e-9))
    np.testing.assert_allclose(effect.layer(buffers, jnp.asarray(LIGHT)), spot + glow, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("name", ["vbex_bloom", "gaussian_bloom"])
def test_vbex_bloom_blurs_the_glow_target(name):
    buffers, frame = article_frame(), host(article_frame())
    effect = gr.preset(name)
    side = max(HEIGHT, WIDTH)
    if effect.method == "pyramid":
        radius = math.ceil(effect.blur_reach * side / 2 - 1e-9)
        glow = shaders.bright_glow(frame["glow_target"], float(effect.blur_sigma) * side / 2, radius)
    else:
        glow = shaders.gaussian_blur(
            frame["glow_target"], float(effect.wide_blur_sigma) * side, math.ceil(effect.wide_blur_reach * side - 1e-9)
        )
    np.testing.assert_allclose(effect.layer(buffers, jnp.asarray(LIGHT)), float(effect.intensity) * glow, atol=1e-5)


def test_bloom_of_a_frame_keeps_the_hue():
    """Without a glow target the frame's bright part blooms by luminance: night lights stay orange, not red."""
    colour = jnp.zeros((32, 32, 3)).at[14:18, 14:18].set(jnp.array([1.57, 0.98, 0.40]))
    buffers = gr.Buffers(color=colour, depth=jnp.full((32, 32), jnp.inf), coverage=jnp.zeros((32, 32)))
    glow = np.asarray(gr.preset("vbex_bloom").layer(buffers, jnp.zeros(2)))[16, 16]
    np.testing.assert_allclose(glow / glow[0], np.array([1.57, 0.98, 0.40]) / 1.57, rtol=1e-4)
