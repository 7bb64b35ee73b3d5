"""Each article's whole pipeline, preset against a NumPy emulation of its shaders (`article_shaders`).

The emulation is written from the articles' HLSL, in UV space with GPU sampler
semantics (texel centres at `(i + 0.5) / W`), independently of the library's
pixel-space kernels: the XNA article's light given in view space through its
projection matrix and its depth map in its own encoding (`1 - z/w`),
kbEngine's full-resolution masked texture drawn into its low-resolution
target, the VBex glow pyramid's render targets of whole-pixel sizes.
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
FOV_X_DEG = 60.0


def article_frame(seed=0) -> gr.Buffers:
    """Sky above, pillars nearer than the light, a wall beyond it, ground; every optional pass."""
    rng = np.random.default_rng(seed)
    depth = np.full((HEIGHT, WIDTH), np.inf)
    depth[34:, :] = 8.0  # ground
    depth[10:30, 60:80] = 40.0  # a wall beyond the light: the depth test lets the flare through
    depth[2:8, 28:56] = 1500.0  # a far ridge: in hardware depth within .00025 of a light at 2000, 25 % nearer
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


def light_view(light_depth):
    """The light in the XNA article's view space (x right, y up, -z forward) at `LIGHT` px, `light_depth` along its
    ray (a light at infinity: on the far plane, where the library draws it)."""
    focal = 0.5 * WIDTH / math.tan(math.radians(FOV_X_DEG) / 2)
    ray = np.array([(LIGHT[0] - WIDTH / 2) / focal, (HEIGHT / 2 - LIGHT[1]) / focal, -1.0])
    if math.isinf(light_depth):
        return ray * gr.XNA_FAR_PLANE
    return ray / np.linalg.norm(ray) * light_depth


def xna_camera():
    """The article's `matVP` for the frame: its field of view, aspect ratio and the preset's clip planes."""
    fov_y = 2 * math.atan(math.tan(math.radians(FOV_X_DEG) / 2) * HEIGHT / WIDTH)
    return shaders.xna_projection(fov_y, WIDTH / HEIGHT, gr.XNA_NEAR_PLANE, gr.XNA_FAR_PLANE)


def planar(depth):
    """Ray depth (the frame's) as distance along the axis, for the article's depth map."""
    focal = 0.5 * WIDTH / math.tan(math.radians(FOV_X_DEG) / 2)
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH] + 0.5
    return depth / np.sqrt(1 + ((x - WIDTH / 2) / focal) ** 2 + ((HEIGHT / 2 - y) / focal) ** 2)


def test_the_emulated_projection_puts_the_light_at_its_pixel():
    u, v, _, w = shaders.screen_position(light_view(LIGHT_DEPTH), xna_camera())
    assert (u * WIDTH, v * HEIGHT) == pytest.approx(tuple(LIGHT), abs=1e-9) and w > 0


# (light distance, SunSize): a far sun (the flare .3 UV), a nearer one (.75 UV; the far ridge passes the
# hardware-depth test), a light just past the near plane (the step clamp on clip-space z shortens the
# rays; SunSize small enough to see the flare), the frame's own light (pillars blanked, the wall beyond
# passes), a light at infinity (on the far plane: the sky passes, and the far ridge, within the bias of the far plane).
XNA_CASES = [(5000.0, 1500.0), (2000.0, 1500.0), (0.8, 0.1), (LIGHT_DEPTH, 6.0), (math.inf, 1500.0)]


@pytest.mark.parametrize(("light_depth", "sun_size"), XNA_CASES)
@pytest.mark.parametrize("textured", [False, True])
def test_xna_crepuscular_is_the_articles_five_passes(light_depth, sun_size, textured):
    buffers, frame = article_frame(), host(article_frame())
    effect = dataclasses.replace(gr.preset("xna_crepuscular"), sun_size=sun_size, fov_x_deg=FOV_X_DEG)
    flare = gr.procedural_flare()
    if textured:
        flare = asymmetric_texture()
        effect = dataclasses.replace(effect, flare_texture=flare)
    mat_vp = xna_camera()
    expected_frame, expected_layer = shaders.xna_crepuscular(
        frame["color"], shaders.article_depth_map(planar(frame["depth"]), mat_vp), light_view(light_depth), mat_vp,
        sun_size=sun_size, flare=flare, threshold=float(effect.threshold), tint=np.asarray(effect.tint),
        num_samples=128, density=0.5, decay=0.95, weight=1.0, exposure=0.15,
    )  # fmt: skip
    layer = effect.layer(buffers, jnp.asarray(LIGHT), light_depth=light_depth)
    np.testing.assert_allclose(layer, expected_layer, atol=2e-5)
    np.testing.assert_allclose(effect(buffers, jnp.asarray(LIGHT), light_depth=light_depth), expected_frame, atol=2e-5)
    assert float(np.max(expected_layer)) > 0.5  # the flare shows: not a comparison of two blank layers


def test_xna_flare_shrinks_with_the_lights_distance():
    """`SunSize / z`: a light twice as far draws a flare half as wide (the preset's own SunSize)."""
    effect = dataclasses.replace(gr.preset("xna_crepuscular"), fov_x_deg=FOV_X_DEG)
    near, far = (np.asarray(effect.flare_size_in_px(HEIGHT, WIDTH, LIGHT, d, jnp.float32)) for d in (2500.0, 5000.0))
    np.testing.assert_allclose(near, 2 * far, rtol=1e-3)
    np.testing.assert_allclose(far, np.array([WIDTH, HEIGHT]) * 0.3, rtol=1e-2)  # 1500 / 5000 UV (off axis: z < 5000)


def test_xna_depth_test_is_the_hardware_compare():
    """The far ridge 25 % nearer than a light at 2000 passes (.00025 in z/w is that much there); at a light at
    20 the wall at 40 passes and pillars at 5 are blanked."""
    buffers = article_frame()
    effect = dataclasses.replace(gr.preset("xna_crepuscular"), fov_x_deg=FOV_X_DEG, threshold=0.0)
    emitter_fn, args = gr.effects.base.emitter_inputs(effect, buffers, jnp.asarray(LIGHT), True, 2000.0)
    ridge = np.asarray(emitter_fn(*args))[2:6, 28:56]
    assert float(ridge.min()) > 0
    emitter_fn, args = gr.effects.base.emitter_inputs(
        dataclasses.replace(effect, sun_size=6.0), buffers, jnp.asarray(LIGHT), True, LIGHT_DEPTH
    )
    emitter = np.asarray(emitter_fn(*args))[..., 0]
    assert float(emitter[14:22, 60:64].min()) > 0 and float(emitter[6:, 36:41].max()) == 0


def test_xna_step_clamp_reads_clip_space_z():
    """A light under .3 units past the near plane (.5): the step clamp is its clip-space z, not .5 as its distance reads."""
    effect = dataclasses.replace(gr.preset("xna_crepuscular"), fov_x_deg=FOV_X_DEG)
    distance = float(np.linalg.norm(light_view(0.8)))
    clip_z = float(effect.light_clip_depth(HEIGHT, WIDTH, jnp.asarray(LIGHT), distance, jnp.float32))
    _, _, z_over_w, w = shaders.screen_position(light_view(0.8), xna_camera())
    assert clip_z == pytest.approx(w * z_over_w, rel=1e-5)
    assert gr.step_clamp(clip_z) == pytest.approx(w * z_over_w, rel=1e-5)
    assert w * z_over_w < 0.31


def test_xna_bright_pass_saturates_only_the_core():
    buffers = article_frame()
    layer = np.asarray(gr.preset("xna_crepuscular").layer(buffers, jnp.asarray(LIGHT), light_depth=5000.0))[..., 0]
    lit = layer > 1e-3
    assert lit.sum() > 100
    assert (layer >= layer.max() * 0.999).sum() < 0.25 * lit.sum()


def test_galaxy_vls_is_the_articles_pass():
    buffers, frame = article_frame(), host(article_frame())
    expected = shaders.galaxy_vls(frame["light_pass"][..., None], LIGHT_UV)
    layer = gr.preset("galaxy_vls").layer(buffers, jnp.asarray(LIGHT))  # white light: every channel alike
    np.testing.assert_allclose(layer, np.broadcast_to(expected, layer.shape), atol=1e-5)
    assert float(np.max(expected)) > 0.1


@pytest.mark.parametrize("texture", ["procedural", "asymmetric", "fine"])
def test_kbengine_flares_are_the_articles_low_resolution_flare_outs(texture):
    """Each flare-out samples the full-resolution masked texture (a fine texture shows it most)."""
    buffers, frame = article_frame(), host(article_frame())
    effect = gr.preset("kbengine_flares")
    flare = gr.procedural_flare()
    if texture != "procedural":
        flare = asymmetric_texture() if texture == "asymmetric" else np.random.default_rng(2).uniform(size=(64, 64, 1))
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


def test_vbex_lens_dirt_is_the_articles_shader():
    """The preset as printed (the depth factor inside the power), directions from the frame's field of view."""
    buffers, frame = article_frame(), host(article_frame())
    effect = dataclasses.replace(gr.preset("vbex_lens_dirt"), fov_x_deg=FOV_X_DEG)
    dirt = np.asarray(gr.dirt_texture(HEIGHT, WIDTH, seed=effect.dirt_seed), np.float64)
    expected = shaders.lens_dirt(dirt, frame["depth"], _to_light(FOV_X_DEG), FOV_X_DEG, float(effect.far_plane),
                                 np.asarray(effect.tint))  # fmt: skip
    np.testing.assert_allclose(effect.layer(buffers, jnp.asarray(LIGHT)), expected, atol=1e-5)
    open_sky = shaders.lens_dirt(dirt, np.full_like(frame["depth"], np.inf), _to_light(FOV_X_DEG), FOV_X_DEG,
                                 float(effect.far_plane), np.asarray(effect.tint))  # fmt: skip
    pillar = (20, 22)  # nearer than 0.8 * far_plane: the occluder dims the dirt by 0.8 ** 20
    assert expected[pillar].sum() / open_sky[pillar].sum() == pytest.approx(0.8**20, rel=1e-5)
    assert float(open_sky[pillar].sum()) > 0.05


def test_lens_dirt_depth_after_the_power_is_ours_and_dims_to_the_floor():
    buffers = article_frame()
    effect = dataclasses.replace(gr.preset("vbex_lens_dirt"), fov_x_deg=FOV_X_DEG, depth_in_power=False)
    open_frame = dataclasses.replace(buffers, depth=jnp.full((HEIGHT, WIDTH), jnp.inf))
    pillar = (20, 22)
    dimmed, open_sky = (float(effect.layer(b, jnp.asarray(LIGHT))[pillar].sum()) for b in (buffers, open_frame))
    assert dimmed / open_sky == pytest.approx(0.8, rel=1e-5)


def test_vbex_sun_spot_adds_its_glow_at_full_strength():
    buffers, frame = article_frame(), host(article_frame())
    effect = gr.preset("vbex_sun_spot")
    assert float(effect.bloom.intensity) == 1.0
    spot = shaders.sun_spot(HEIGHT, WIDTH, _to_light(50.0), 50.0, 1.0, 1.0)
    spot = spot[..., None] * (frame["coverage"] == 0)[..., None] * np.asarray(effect.tint)
    side = max(HEIGHT, WIDTH)
    glow = shaders.bright_glow(spot, float(effect.bloom.blur_sigma) * side / 2, math.ceil(effect.bloom.blur_reach * side / 2 - 1e-9))
    # float32 sums of a blur many pixels wide over a spot of about 25: their rounding, 1e-4 of the value, is the
    # code generator's order of summation.
    np.testing.assert_allclose(effect.layer(buffers, jnp.asarray(LIGHT)), spot + glow, rtol=2e-4, atol=1e-4)


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


@pytest.mark.parametrize(("height", "width"), [(45, 83), pytest.param(37, 200, marks=pytest.mark.slow)])
def test_vbex_bloom_levels_are_whole_pixel_render_targets_read_by_uv(height, width):
    """On a frame not divisible by 16 each level is `Fullsize / f` whole pixels, drawn and read back by UV."""
    rng = np.random.default_rng(5)
    glow = rng.uniform(0.0, 1.0, (height, width, 3)) * (rng.uniform(size=(height, width, 1)) < 0.08) * 4
    buffers = gr.Buffers(color=jnp.zeros((height, width, 3)), depth=jnp.full((height, width), jnp.inf),
                         coverage=jnp.zeros((height, width)), glow_target=jnp.asarray(glow, jnp.float32))  # fmt: skip
    effect = gr.preset("vbex_bloom")
    side = max(height, width)
    expected = float(effect.intensity) * shaders.bright_glow(
        glow, float(effect.blur_sigma) * side / 2, math.ceil(effect.blur_reach * side / 2 - 1e-9)
    )
    np.testing.assert_allclose(effect.layer(buffers, jnp.zeros(2)), expected, atol=1e-5)


def test_bloom_of_a_frame_keeps_the_hue():
    """Without a glow target the frame's bright part blooms by luminance: night lights stay orange, not red."""
    colour = jnp.zeros((32, 32, 3)).at[14:18, 14:18].set(jnp.array([1.57, 0.98, 0.40]))
    buffers = gr.Buffers(color=colour, depth=jnp.full((32, 32), jnp.inf), coverage=jnp.zeros((32, 32)))
    glow = np.asarray(gr.preset("vbex_bloom").layer(buffers, jnp.zeros(2)))[16, 16]
    np.testing.assert_allclose(glow / glow[0], np.array([1.57, 0.98, 0.40]) / 1.57, rtol=1e-4)


def test_render_writes_the_frames_camera(tmp_path):
    """A rendered frame carries its field of view and clip planes with the light's distance: what the XNA depth test
    and the VBex directions read."""
    import OpenImageIO as oiio

    from godrays_jax.app.cli import main

    scene = tmp_path / "tiny.json"
    scene.write_text(
        '{"camera": {"position": [0, 0, 5], "target": [0, 0, 0], "fov_x_deg": 37, "width": 32, "height": 18,'
        ' "up": [0, 1, 0], "near": 0.25, "far": 900},'
        ' "light": {"type": "point", "position": [0, 0, -20]},'
        ' "objects": [{"type": "sphere", "center": [0, 0, 0], "radius": 1}]}'
    )
    assert main(["render", str(scene), "-o", str(tmp_path / "frame.exr"), "--no-cache"]) == 0
    spec = oiio.ImageInput.open(str(tmp_path / "frame.exr")).spec()
    assert spec.getattribute("godrays:fov_x_deg") == pytest.approx(37.0)
    assert tuple(spec.getattribute("godrays:clip_planes")) == pytest.approx((0.25, 900.0))
    assert spec.getattribute("godrays:light_depth") == pytest.approx(25.0)
    # ... and the commands hand them to the effects that read them.
    from godrays_jax.primitives.camera_metadata import read_clip_planes

    planes = read_clip_planes(str(tmp_path / "frame.exr"))
    effect = gr.preset("xna_crepuscular").with_camera(clip_planes=planes)
    assert (effect.near_plane, effect.far_plane) == pytest.approx((0.25, 900.0))
    assert float(effect.with_camera(fov_x_deg=spec.getattribute("godrays:fov_x_deg")).fov_x_deg) == pytest.approx(37.0)
    assert gr.preset("vbex_bloom").with_camera(fov_x_deg=37.0, clip_planes=planes) == gr.preset("vbex_bloom")


def test_vbex_night_lights_are_towns_clustered_on_continents():
    """The planet's emissive night-light map: dark sea, lit land, towns clustered by region (not a regular grid)."""
    from godrays_jax.raster import shading

    rng = np.random.default_rng(0)
    normals = rng.normal(size=(3, 200_000))
    normals /= np.linalg.norm(normals, axis=0)
    lights = np.asarray(shading.city_lights(jnp.asarray(normals, jnp.float32)))
    land = np.asarray(shading.continents(jnp.asarray(normals, jnp.float32))) > shading.LAND_LEVEL
    assert 0.15 < land.mean() < 0.4  # continents, not the whole sphere
    assert lights[~land].max() == 0.0  # the sea is dark
    lit = lights > 0.5
    assert 0.002 < lit.mean() < 0.05  # scattered towns, not a glowing crust
    # Clustered: the lit share of land varies strongly between caps of ~10 degrees around random land points.
    centres = normals[:, np.flatnonzero(land)[:400]]
    cosine = centres.T @ normals
    shares = np.array([lit[(row > np.cos(0.17)) & land].mean() for row in cosine])
    assert shares.std() > 0.5 * shares.mean()  # towns spread evenly over land would give about 0.15
