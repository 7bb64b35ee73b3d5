"""`VolumetricFog`: the kernel's terms composited, params files, presets and a fit that recovers the medium."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from frames import slow_where

import godrays_jax as gr
from godrays_jax.effects.serialization import load_effect, save_effect
from godrays_jax.effects import volumetric
from godrays_jax.effects.volumetric import march_factor
from godrays_jax.kernels import silhouettes
from godrays_jax.kernels.silhouettes import silhouette_mix
from godrays_jax.pipeline.compiled import render_compiled
from godrays_jax.pipeline.fit import fit
from godrays_jax.primitives.buffers import Silhouettes

HEIGHT, WIDTH = 12, 16


def _frame(rng):
    depth = np.full((HEIGHT, WIDTH), np.inf, np.float32)
    depth[7:] = np.linspace(8.0, 30.0, 5)[:, None]  # ground
    depth[2:, 6:8] = 12.0  # a post below the sun
    color = rng.uniform(0.0, 1.0, (HEIGHT, WIDTH, 3)).astype(np.float32)
    return gr.Buffers(color=jnp.asarray(color), depth=jnp.asarray(depth), coverage=jnp.asarray(np.isfinite(depth), jnp.float32))


MEDIUM = dict(extinction=0.04, max_distance=40.0, anisotropy=0.7, light_color=(2.0, 1.6, 1.2),
              ambient_color=(0.1, 0.12, 0.15))  # fmt: skip
EFFECT = dict(direct_fraction=0.6, fov_x_deg=60.0, num_view_steps=8, num_shadow_samples=12, resolution_factor=2)
LIGHT = (7.3, 1.6)


def _fog(**medium):
    return gr.VolumetricFog(medium=gr.Medium(**{**MEDIUM, **medium}), **EFFECT)


def test_effect_is_the_kernel_composited(rng):
    buffers = _frame(rng)
    effect = _fog()
    colours = {name: MEDIUM[name] for name in ("light_color", "ambient_color")}
    medium = gr.BoundedMedium(
        extinction=MEDIUM["extinction"], max_distance=MEDIUM["max_distance"], anisotropy=MEDIUM["anisotropy"],
        height_falloff=0.0, layer_top=1e4,
    )  # fmt: skip
    kernel = {name: EFFECT[name] for name in ("direct_fraction", "fov_x_deg", "num_view_steps", "resolution_factor")}
    expected = gr.apply_volumetric_fog(
        buffers.color, buffers.depth, jnp.asarray(LIGHT), light_depth=20.0, medium=medium,
        slabs=gr.Slabs(thickness=0.15, edge_softness=0.05), shadows=gr.ShadowSamples(EFFECT["num_shadow_samples"]),
        **dict(zip(("coverage", "uncovered_depth"), silhouette_mix(buffers.coverage, buffers.depth, buffers.color))),
        **colours, **kernel,
    )  # fmt: skip
    np.testing.assert_allclose(effect(buffers, jnp.asarray(LIGHT), light_depth=20.0), expected, rtol=1e-5)
    layer = effect.layer(buffers, jnp.asarray(LIGHT), light_depth=20.0)
    surface, _, _ = effect.terms(buffers, jnp.asarray(LIGHT), light_depth=20.0)
    np.testing.assert_allclose(buffers.color * surface[..., None] + layer, expected, rtol=1e-5, atol=1e-6)


def test_coverage_from_depth_alone_is_spread_like_a_pixel_filter(rng):
    buffers = _frame(rng)
    grey = jnp.full_like(buffers.color, 0.3)  # surface and sky alike: the colour cannot tell, the filter's spread stands in
    spread, uncovered = map(np.asarray, silhouette_mix(buffers.coverage, buffers.depth, grey))
    assert spread[6, 3] == pytest.approx(0.15) and spread[7, 3] == pytest.approx(0.85)  # the ground's edge
    assert spread[12 - 1, 0] == 1.0 and spread[0, 0] == 0.0
    # The post before the ground: its own depth, the rest the neighbour most unlike it (the ground below-left).
    assert spread[9, 6] == 1.0 and uncovered[9, 6] == pytest.approx(24.5)
    assert np.isinf(uncovered[6, 3]) and np.isinf(uncovered[0, 0])
    measured = buffers.coverage.at[6, 3].set(0.4)  # a coverage pass: kept as it is
    np.testing.assert_array_equal(silhouette_mix(measured, buffers.depth, grey)[0], measured)


def _filtered_edge(far_depth, covered):
    """A dark wall (columns 0-4) before a bright background at `far_depth` (`inf`: sky), column 4 blended by a
    pixel filter with the wall covering `covered` (per row) of it; its depth one sample's (Cycles' Z): the wall's
    where it covers half or more. A bright emitter among the background's pixels."""
    near, far = np.array([0.05, 0.04, 0.03]), np.array([0.8, 0.85, 0.9])
    depth = np.full((len(covered), 8), far_depth)
    depth[:, :4] = 5.0
    depth[:, 4] = np.where(covered >= 0.5, 5.0, far_depth)
    share = np.zeros(depth.shape)
    share[:, :4], share[:, 4] = 1.0, covered
    color = share[..., None] * near + (1 - share[..., None]) * far
    color[3, 5] = 50.0
    coverage = np.isfinite(depth)
    return tuple(jnp.asarray(a, jnp.float32) for a in (coverage, depth, color))


@pytest.mark.parametrize("read_pixels", [3, 1 << 16])
@pytest.mark.parametrize("band_pixels", slow_where([16, 24, 40], {16}))
def test_silhouettes_mixed_by_bands_of_rows_are_the_frames(rng, monkeypatch, band_pixels, read_pixels):
    """On a larger frame the silhouettes' sides are found a band of rows at a time, each with the rows around it,
    and their colours read a few silhouette pixels at a time: the same shares and depths as the whole frame at once
    (bands of 2, 3 and 5 rows of 8, the last one partly filled, and reads of 3 pixels, on a frame whose every row
    has a silhouette between two surfaces or the sky)."""
    covered = rng.uniform(0.1, 0.9, 13)
    coverage, depth, color = _filtered_edge(30.0, covered)
    depth = depth.at[2:5, 6].set(jnp.inf).at[9, 1].set(9.0)
    coverage = coverage.at[11, 2].set(0.4)
    # `silhouette_mix` is compiled once per shape: traced afresh for the whole frame and again with the bands patched in.
    jax.clear_caches()
    whole = silhouette_mix(coverage, depth, color)
    monkeypatch.setattr(silhouettes, "_BAND_PIXELS", band_pixels)
    monkeypatch.setattr(silhouettes, "_READ_PIXELS", read_pixels)
    jax.clear_caches()
    banded = silhouette_mix(coverage, depth, color)
    for got, expected in zip(banded, whole):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(expected))
    assert 0.0 < float(jnp.min(whole[0])) < 1.0 and np.isfinite(np.asarray(whole[1])).any()


@pytest.mark.parametrize("far_depth", [np.inf, 30.0])
def test_coverage_of_a_filtered_silhouette_is_read_from_its_colour(far_depth):
    covered = np.array([0.3, 0.6, 0.2, 0.7, 0.45, 0.55, 0.35, 0.65])
    estimate, uncovered = map(np.asarray, silhouette_mix(*_filtered_edge(far_depth, covered)))
    # The share of each pixel's surface (on sky, its nearest neighbour's: the wall), and what the rest sees.
    if np.isinf(far_depth):
        surface_share, other_side = covered, np.full(8, np.inf)
    else:
        surface_share = np.where(covered >= 0.5, covered, 1 - covered)
        other_side = np.where(covered >= 0.5, far_depth, 5.0)
    np.testing.assert_allclose(estimate[:, 4], surface_share, atol=1e-5)
    np.testing.assert_allclose(estimate[:, :4], 1.0, atol=1e-5)
    np.testing.assert_allclose(estimate[:, 6:], 0.0 if np.isinf(far_depth) else 1.0, atol=1e-5)
    np.testing.assert_allclose(uncovered[:, 4], other_side)


def _silhouette_mix_loop(coverage, depth, color):
    """`silhouette_mix` pixel by pixel: each pixel's surface, the other side, and the brightness's share where it tells."""
    hard = np.all(coverage == np.isfinite(depth))
    height, width = depth.shape
    brightness = color[..., :3].mean(axis=-1)
    display = lambda c: c / (1 + np.abs(c))  # noqa: E731
    clamp = lambda y, x: (min(max(y, 0), height - 1), min(max(x, 0), width - 1))  # noqa: E731
    on = lambda d, at: (not np.isfinite(d)) if not np.isfinite(at) else bool(np.isfinite(d) and abs(d - at) <= 0.05 * at)  # noqa: E731
    shares, uncovered = np.zeros((height, width)), np.full((height, width), np.inf)
    for y in range(height):
        for x in range(width):
            around = [clamp(y + dy, x + dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dy, dx) != (0, 0)]
            spread = sum(
                (0.7 if dy == 0 else 0.15) * (0.7 if dx == 0 else 0.15) * coverage[clamp(y + dy, x + dx)]
                for dy in (-1, 0, 1) for dx in (-1, 0, 1)
            )  # fmt: skip
            own = depth[y, x]
            finite = [depth[p] for p in around if np.isfinite(depth[p])]
            surface = own if np.isfinite(own) else min(finite, default=np.inf)
            beside_sky = not np.isfinite(own) or len(finite) < 8
            if beside_sky:
                other, fallback = np.inf, spread if hard else coverage[y, x]
            else:
                unlike = [abs(np.log(d / own)) for d in finite]
                other = finite[int(np.argmax(unlike))] if max(unlike) > np.log(1.1) else np.inf
                fallback = 1.0 if np.isfinite(other) else spread if hard else coverage[y, x]
            uncovered[y, x] = other
            shares[y, x] = fallback
            if not np.isfinite(surface) or not (hard or np.isfinite(other)):
                continue
            sides = []
            for at in (surface, other):
                members = [brightness[p] for p in around if on(depth[p], at)]
                if members:
                    median = np.median(members)
                    deviations = sorted(abs(display(m) - display(median)) for m in members)[:-1]
                    deviation = np.mean(deviations) if deviations else 0.0
                elif on(own, at):
                    median, deviation = brightness[y, x], 0.0
                else:
                    break
                sides.append((median, deviation))
            else:
                (first, first_dev), (second, second_dev) = sides
                share = np.clip((brightness[y, x] - second) / (first - second) if first != second else 0.0, 0, 1)
                contrast = abs(display(first) - display(second))
                trust = np.clip((contrast / (first_dev + second_dev + 0.002) - 3) / 3, 0, 1)
                shares[y, x] = trust * share + (1 - trust) * fallback
    return shares, uncovered


@pytest.mark.parametrize("with_pass", [False, True])
def test_silhouette_mix_matches_a_loop(rng, with_pass):
    buffers = _frame(rng)
    color = np.asarray(buffers.color, np.float64) * rng.choice([0.02, 1.0], (HEIGHT, WIDTH, 1))  # some contrasts too low
    depth, coverage = np.asarray(buffers.depth, np.float64), np.asarray(buffers.coverage, np.float64)
    if with_pass:
        coverage[6, 3] = 0.4
    expected = _silhouette_mix_loop(coverage, depth, color)
    arrays = [jnp.asarray(a, jnp.float32) for a in (coverage, depth, color)]
    for got in (silhouette_mix(*arrays), [a[0] for a in jax.jit(jax.vmap(silhouette_mix))(*(a[None] for a in arrays))]):
        np.testing.assert_allclose(got[0], expected[0], atol=2e-5)
        np.testing.assert_allclose(got[1], expected[1], rtol=1e-6)


def test_march_spacing_is_a_fraction_of_the_frame():
    """`resolution_factor` pixels up to 320 on the frame's larger side, beyond it as large a fraction of that side (at
    most 6 x: 1920 pixels), on any frame size; 1 too (every pixel's own ray up to 320)."""
    assert march_factor(180, 320, 4) == march_factor(90, 160, 4) == 4
    assert march_factor(270, 480, 4) == 6
    assert march_factor(360, 640, 4) == 8
    assert march_factor(181, 321, 8) == pytest.approx(8 * 321 / 320)
    assert march_factor(1080, 1920, 4) == 24
    assert march_factor(2160, 3840, 4) == 24
    assert march_factor(180, 320, 1) == march_factor(90, 160, 1) == 1
    assert march_factor(270, 480, 1) == 1.5
    assert march_factor(1080, 1920, 1) == 6


@pytest.mark.slow
def test_gradients_reach_every_medium_field_with_surfaces_beyond_the_medium(rng):
    """A surface beyond `max_distance` (its light's path starts outside the ball): reverse-mode gradients, which
    Levenberg-Marquardt's normal equations take, agree with forward mode (were NaN in `max_distance`)."""
    buffers = _frame(rng)
    effect = _fog(max_distance=10.0)  # the ground runs to 30, the post stands at 12
    names = ("extinction", "max_distance", "anisotropy")

    def loss(values):
        medium = gr.Medium(**{**MEDIUM, "max_distance": 10.0, **dict(zip(names, values))})
        return jnp.sum(gr.VolumetricFog(medium=medium, **EFFECT)(buffers, jnp.asarray(LIGHT)) ** 2)

    values = tuple(jnp.float32(getattr(effect.medium, name)) for name in names)
    reverse = jax.jit(jax.grad(loss))(values)
    along = jax.jit(lambda values, tangent: jax.jvp(loss, (values,), (tangent,))[1])  # compiled: eager is slow here
    for index, name in enumerate(names):
        tangent = tuple(jnp.float32(i == index) for i in range(len(names)))
        forward = along(values, tangent)
        np.testing.assert_allclose(float(reverse[index]), float(forward), rtol=1e-4, err_msg=name)


@pytest.mark.parametrize(
    "light",
    slow_where([(40.98, 18.01), (40.5, 18.5)], {(40.98, 18.01)}),
    ids=["near a pixel's corner", "on a pixel centre"],
)
def test_a_light_hidden_by_a_thin_surface_leaks_no_light_at_its_own_pixels(light):
    """The sun behind a thin trunk (the slabs a fit of `forest_low_sun` ends with): within a pixel or so of the light
    every point of a view ray lies below the lines' lowest bin of `s`, and so do the trunk's slabs; the pixels around
    the light read as shadowed as the rest of the trunk, where they read a bright spot (several times the trunk)."""
    height, width = 45, 80
    depth = np.full((height, width), np.inf, np.float32)
    depth[36:] = 4.0
    depth[:36, 36:46] = 2.4  # the trunk, in front of the light
    frame = gr.Buffers(color=jnp.full((height, width, 3), 0.012, jnp.float32), depth=jnp.asarray(depth),
                       coverage=jnp.asarray(np.isfinite(depth), jnp.float32))  # fmt: skip
    effect = gr.VolumetricFog(
        medium=gr.Medium(extinction=0.02, max_distance=60.0, anisotropy=0.8, light_color=(2.0, 2.0, 2.0)),
        thickness=0.09, edge_softness=0.12, fov_x_deg=50.0, shadows="lines", num_shadow_lines=64, num_shadow_bins=96,
        resolution_factor=1,
    )  # fmt: skip
    image = np.asarray(render_compiled(effect, frame, jnp.asarray(light, jnp.float32), True))[..., :3].mean(axis=-1)
    x, y = int(light[0]), int(light[1])
    trunk = np.median(image[:30, 38:44])
    assert image[y - 2 : y + 3, x - 2 : x + 3].max() <= 1.05 * trunk, (image[y - 2 : y + 3, x - 2 : x + 3], trunk)


@pytest.mark.slow
@pytest.mark.parametrize("preset", ["volumetric_haze", "physically_based"])  # shadows read along lines, by samples
def test_a_frame_at_the_eye_gives_finite_values_and_gradients(preset):
    """Depth 0 everywhere (a cleared depth buffer, a surface at the eye): the fog and its derivatives in every
    fittable field are finite. They were NaN where depths were divided by depths (the silhouettes' ratios), by a
    slab face's width or by a slab's softness, each 0 there; such a surface is a slab of no depth and casts nothing."""
    buffers = gr.Buffers(color=jnp.full((18, 32, 3), 0.2, jnp.float32), depth=jnp.zeros((18, 32), jnp.float32),
                         coverage=jnp.ones((18, 32), jnp.float32))  # fmt: skip
    effect = gr.preset(preset)
    names = tuple(gr.parameter_bounds(effect))

    def total(values):
        return jnp.sum(gr.replace_fields(effect, dict(zip(names, values)))(buffers, jnp.asarray([16.0, 4.0])))

    values = tuple(jnp.asarray(gr.field_value(effect, name), jnp.float32) for name in names)
    value, gradients = jax.jit(jax.value_and_grad(total))(values)
    assert np.isfinite(float(value))
    for name, gradient in zip(names, gradients):
        assert np.all(np.isfinite(np.asarray(gradient))), name


def test_frames_with_their_silhouettes_read_once_draw_the_same_frame_and_derivatives(rng):
    """`frames_read_once` reads each frame's silhouettes (`Buffers.silhouettes`), which the fog then takes instead of
    reading them again: the same frame eagerly and under `jit`, and the same derivatives in its fields (to float32
    rounding: XLA fuses the reads in other programs). A planar depth whose
    field of view is fitted keeps its frame as it is (its distances along the rays move with that field); a frame
    without depth too; and silhouettes of another size are refused, naming the field."""
    frame = _frame(rng)
    effect = gr.preset("volumetric_haze")
    (read,) = effect.frames_read_once([frame], fitted=("medium.extinction",))
    assert read.silhouettes is not None
    np.testing.assert_array_equal(read.silhouettes.coverage, silhouette_mix(frame.coverage, frame.depth, frame.color)[0])

    def drawn(extinction, buffers):
        fog = eqx.tree_at(lambda e: e.medium.extinction, effect, extinction)
        return fog(buffers, jnp.asarray(LIGHT))

    extinction = jnp.asarray(0.03, jnp.float32)
    for function in (drawn, jax.jit(drawn)):
        np.testing.assert_allclose(function(extinction, read), function(extinction, frame), rtol=1e-6, atol=1e-7)
    derivative = jax.jit(jax.jacfwd(drawn))  # compiled: eagerly, op by op, the slowest path of the suite's fast step
    np.testing.assert_allclose(derivative(extinction, read), derivative(extinction, frame), rtol=2e-5, atol=1e-7)
    planar = gr.Buffers(color=frame.color, depth=frame.depth, coverage=frame.coverage, depth_kind="planar")
    assert effect.frames_read_once([planar], fitted=("fov_x_deg",))[0] is planar
    assert effect.frames_read_once([planar], fitted=())[0].silhouettes is not None
    plate = gr.Buffers(color=frame.color, depth=None, coverage=frame.coverage)
    assert effect.frames_read_once([plate], fitted=())[0] is plate
    assert gr.preset("xna_crepuscular").frames_read_once([frame], fitted=())[0] is frame
    with pytest.raises(ValueError, match="silhouettes.coverage"):
        gr.Buffers(color=frame.color, depth=frame.depth, coverage=frame.coverage,
                   silhouettes=Silhouettes(coverage=frame.coverage[1:], uncovered_depth=frame.depth))  # fmt: skip


@pytest.mark.slow
def test_a_fit_reads_each_frames_silhouettes_once_and_never_in_a_step(rng, monkeypatch):
    """`fit` reads the silhouettes off each frame once per resolution (its coarse phase's frames and its own), before
    any step: no program it traces reads them again, and the fit ends where it ends reading them in every step. (Two
    fields, of the march's stage and the slabs': the Jacobian's other stages read the frame as these do.)"""
    frame = _frame(rng)
    effect = gr.preset("volumetric_haze")
    target = np.asarray(effect(frame, jnp.asarray(LIGHT)))[..., :3] * 1.1
    fixed = [name for name in gr.parameter_bounds(effect) if name not in ("medium.extinction", "thickness")]
    options = dict(max_steps=2, fixed=fixed, coarse_factor=2)
    reads = []

    def counted(coverage, depth, color):
        reads.append(isinstance(depth, jax.core.Tracer))
        return silhouette_mix(coverage, depth, color)

    monkeypatch.setattr(volumetric, "silhouette_mix", counted)
    once = fit(effect, frame, jnp.asarray(LIGHT), target, **options)
    assert reads == [False, False]  # the frame's and the coarse phase's, neither under a trace
    monkeypatch.setattr(type(effect), "frames_read_once", lambda self, frames, fitted: list(frames))
    every_step = fit(effect, frame, jnp.asarray(LIGHT), target, **options)
    assert reads[2:] and all(reads[2:])  # read inside the programs instead
    np.testing.assert_allclose(once.loss_history, every_step.loss_history, rtol=1e-4)  # to float32 rounding


@pytest.mark.parametrize("preset", ["volumetric_haze", "physically_based"])  # shadows read along lines, by samples
@pytest.mark.slow
def test_frames_where_nothing_casts_a_shadow_are_fitted_without_reading_shadows(preset):
    """`same_on` frames all sky (or at the eye) reads one shadow sample a segment, which draws them as the effect does (values and
    derivatives, the light on screen, off it and behind the camera); on a frame with a surface it is the effect
    itself. `fit` fits it in the effect's place and returns the effect's own statics."""
    sky = gr.Buffers(color=jnp.full((HEIGHT, WIDTH, 3), 0.3, jnp.float32), depth=jnp.full((HEIGHT, WIDTH), jnp.inf),
                     coverage=jnp.zeros((HEIGHT, WIDTH), jnp.float32))  # fmt: skip
    effect = gr.preset(preset)
    cheaper = effect.same_on([sky])
    assert (cheaper.shadows, cheaper.num_shadow_samples) == ("samples", 1)
    assert effect.same_on([sky, _frame(np.random.default_rng(0))]) is effect
    at_eye = gr.Buffers(color=sky.color, depth=jnp.zeros((HEIGHT, WIDTH)), coverage=jnp.ones((HEIGHT, WIDTH)))
    at_eye_too = effect.same_on([sky, at_eye])  # surfaces at the eye cast nothing either
    without_depth = gr.Buffers(color=sky.color, depth=None, coverage=sky.coverage)
    assert effect.same_on([sky, without_depth]) is effect  # which then says that it needs depth
    with pytest.raises(ValueError, match="depth"):
        fit(effect, without_depth, jnp.asarray(LIGHT), np.asarray(sky.color), max_steps=1)
    assert (at_eye_too.shadows, at_eye_too.num_shadow_samples) == ("samples", 1)

    def total(candidate, fov_x_deg, light, front):
        drawn = gr.replace_fields(candidate, {"fov_x_deg": fov_x_deg})(sky, light, light_in_front=front)
        return jnp.sum(drawn), drawn

    # One program per effect, the light and its side traced: eagerly each light compiled the preset's loops again.
    fov_gradient = eqx.filter_jit(jax.grad(total, argnums=1, has_aux=True))
    for light, front in [((7.3, 1.6), True), ((900.0, -400.0), True), ((7.3, 1.6), False)]:
        light, front = jnp.asarray(light, jnp.float32), jnp.asarray(front)
        (cheap_gradient, cheap), (gradient, drawn) = (fov_gradient(e, e.fov_x_deg, light, front) for e in (cheaper, effect))
        np.testing.assert_allclose(cheap, drawn, atol=1e-5)
        np.testing.assert_allclose(cheap_gradient, gradient, rtol=1e-4)
    if preset != "volumetric_haze":
        return  # the fit below restores any effect's statics alike; one compiles its programs
    target = np.asarray(effect(sky, jnp.asarray(LIGHT)))[..., :3] * 1.1
    fixed = [name for name in gr.parameter_bounds(effect) if name != "medium.extinction"]  # one field restores alike
    fitted = fit(effect, sky, jnp.asarray(LIGHT), target, max_steps=1, fixed=fixed).effect
    assert (fitted.shadows, fitted.num_shadow_samples, fitted.num_shadow_lines) == (
        effect.shadows, effect.num_shadow_samples, effect.num_shadow_lines)  # fmt: skip


def test_params_file_round_trip(tmp_path):
    effect = gr.preset("volumetric_haze")
    save_effect(tmp_path / "fog.json", effect)
    loaded = load_effect(tmp_path / "fog.json")
    assert type(loaded) is gr.VolumetricFog
    assert jax.tree.all(jax.tree.map(lambda a, b: bool(np.all(np.asarray(a) == np.asarray(b))), loaded, effect))


def test_static_counts_are_checked():
    with pytest.raises(ValueError, match="num_view_steps"):
        gr.VolumetricFog(num_view_steps=0)
    with pytest.raises(ValueError, match="thickness"):
        gr.VolumetricFog(thickness=-1.0)


@pytest.mark.slow
def test_fit_recovers_the_medium(rng):
    buffers = _frame(rng)
    truth = _fog()
    target = render_compiled(truth, buffers, jnp.asarray(LIGHT), True, 20.0)
    start = _fog(extinction=0.02, anisotropy=0.5, light_color=(1.0, 1.0, 1.0))
    fixed = ("fov_x_deg", "medium.max_distance", "height_falloff", "layer_top", "thickness", "edge_softness",
             "direct_fraction", "medium.ambient_color")  # fmt: skip
    result = fit(start, buffers, jnp.asarray(LIGHT), target, fixed=fixed, light_depth=20.0, max_steps=30)
    assert result.loss_after < 1e-3 * result.loss_before
    assert float(result.effect.medium.extinction) == pytest.approx(0.04, rel=0.02)
    assert float(result.effect.medium.anisotropy) == pytest.approx(0.7, rel=0.02)


@pytest.mark.slow
def test_light_depth_reaches_the_effect_through_fit(rng):
    buffers = _frame(rng)
    effect = _fog()
    near = render_compiled(effect, buffers, jnp.asarray(LIGHT), True, 15.0)
    sun = render_compiled(effect, buffers, jnp.asarray(LIGHT), True, math.inf)
    assert not np.allclose(near, sun)
    with pytest.raises(ValueError, match="light_depth"):
        fit(effect, buffers, jnp.asarray(LIGHT), sun, light_depth=-1.0, max_steps=1)
