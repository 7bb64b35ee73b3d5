"""fit: parameter recovery on tiny frames, several frames, bounds, rounding, errors, the `fit` command."""

import dataclasses
import functools
import json
import threading
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import godrays_jax as gr
from godrays_jax.app.cli import main
from godrays_jax.app.options import auto_coarse_factor
from godrays_jax.effects.fields import round_counts
from godrays_jax.pipeline import fit as fit_module
from godrays_jax.pipeline import fit_phases, fit_programs
from godrays_jax.pipeline.fit import fit
from godrays_jax.pipeline.fit_phases import plateaued, stalled
from godrays_jax.pipeline.fit_programs import (
    DIFFERENCE_STEP,
    CoarseLinearisation,
    objective_function,
    rendered_differences,
    residuals_and_jacobian,
)
from godrays_jax.pipeline.marquardt import LevenbergMarquardt, MarquardtState
from godrays_jax.pipeline.problem import (
    FOLD_ROUNDING,
    START_INSET,
    FitProblem,
    as_frames,
    fitted_bounds,
    folded_positions,
    from_unit,
    start_point,
    to_unit,
    warp_of,
    warped_start,
)
from godrays_jax.pipeline.reduced import downsample_frames, scale_pixel_fields
from godrays_jax.primitives.checks import ranges_are_guaranteed, ranges_guaranteed

HEIGHT, WIDTH = 24, 32


def _frame(seed=0):
    """A tiny frame: open sky on top, two pillars and the ground below."""
    rng = np.random.default_rng(seed)
    coverage = np.zeros((HEIGHT, WIDTH), np.float32)
    coverage[14:] = 1.0
    coverage[4:, 9:12] = 1.0
    coverage[6:, 22:24] = 1.0
    color = np.where(coverage[..., None] > 0, 0.05, 0.4).astype(np.float32) + 0.02 * rng.random((HEIGHT, WIDTH, 3))
    depth = np.where(coverage > 0, 10.0, np.inf).astype(np.float32)
    return gr.Buffers(color=jnp.asarray(color), depth=jnp.asarray(depth), coverage=jnp.asarray(coverage))


LIGHT = jnp.array([16.5, 5.0])


def _rays(**values):
    return gr.GodRays(**{"source": "disc", "flare_size": 6.0, "units": "px", "flare_shape": "cone", "max_samples": 8,
                         "num_samples": 8.0, **values})  # fmt: skip


# Also the XNA flare's SunSize and the camera's field of view: this disc has a fixed size, so neither moves the image.
FIXED_RAYS = ("weight", "flare_size", "threshold", "tint", "offscreen_fade", "num_samples", "sun_size", "fov_x_deg")


TRUTH = dict(density=0.8, decay=0.85, exposure=0.3)
START = dict(density=0.5, decay=0.97, exposure=0.15)
LIGHTS = [LIGHT, jnp.array([6.0, 3.0])]


@pytest.fixture(scope="module")
def two_frame_fit():
    """One compiled fit reused by several tests: two frames, two lights, one parameter set."""
    frames = [_frame(0), _frame(1)]
    truth = _rays(**TRUTH)
    targets = [truth(frame, light) for frame, light in zip(frames, LIGHTS)]
    result = fit(_rays(**START), frames, LIGHTS, targets, fixed=FIXED_RAYS, max_steps=30)
    return frames, targets, result


def test_several_frames_recover_one_parameter_set_from_another_start(two_frame_fit):
    frames, targets, result = two_frame_fit
    assert type(result.effect) is gr.GodRays and result.effect.max_samples == 8 and result.effect.source == "disc"
    assert result.fitted == ("density", "decay", "exposure")
    for name in result.fitted:
        np.testing.assert_allclose(getattr(result.effect, name), TRUTH[name], rtol=0.02, err_msg=name)
    assert result.converged and result.loss_after < 1e-3 * result.loss_before and not result.kept_start
    # Fixed fields are untouched.
    np.testing.assert_array_equal(result.effect.tint, _rays().tint)
    assert float(result.effect.num_samples) == 8.0


def test_a_frame_of_several_lights_is_fitted_under_all_of_them_with_their_tints():
    """`other_lights`: the frame is drawn under its first light and the others (`lit_by`), in the coarse phase (every
    light's position scaled), the descent on the coarse Jacobian and the polish alike, and the other lights' tints
    are fitted with the fields, from a wrong start; `determination` takes the lights too. The same fit through the
    first light alone, or with the tints held at a wrong start, cannot reach the frame."""
    frame = _frame(0)
    tint = np.array([0.5, 0.4, 0.3], np.float32)
    lamp = gr.Light(xy=jnp.array([6.0, 3.0]), tint=tint)
    truth = _rays(**TRUTH)
    target = gr.lit_by(truth, frame, [gr.Light(xy=LIGHT), lamp])
    untinted = dataclasses.replace(lamp, tint=(1.0, 1.0, 1.0))
    both = fit(_rays(**START), frame, LIGHT, target, other_lights=[untinted], fixed=FIXED_RAYS, max_steps=30,
               coarse_factor=2, coarse_jacobian=True)  # fmt: skip
    for name in both.fitted:
        np.testing.assert_allclose(getattr(both.effect, name), TRUTH[name], rtol=0.02, err_msg=name)
    np.testing.assert_allclose(both.light_tints, [tint], rtol=0.02)
    np.testing.assert_allclose(both.images_after[0], target, atol=2e-3)
    held = fit(_rays(**START), frame, LIGHT, target, other_lights=[untinted], fit_light_tints=False, fixed=FIXED_RAYS,
               max_steps=30, coarse_factor=2, coarse_jacobian=True)  # fmt: skip
    assert held.light_tints is None and held.loss_after > 100 * both.loss_after
    first = fit(_rays(**START), frame, LIGHT, target, fixed=FIXED_RAYS, max_steps=30, coarse_factor=2,
                coarse_jacobian=True)  # fmt: skip
    assert first.loss_after > 100 * both.loss_after
    # The second light's rays move with the fields too: the frame determines each more than the first's alone; the
    # tints, where the fit fitted them, are examined beside the fields.
    under_both = gr.determination(both.effect, frame, LIGHT, target, fitted=both.fitted, other_lights=[lamp],
                                  fit_light_tints=False)  # fmt: skip
    under_first = gr.determination(both.effect, frame, LIGHT, target, fitted=both.fitted)
    assert set(under_both.sensitivity) == set(both.fitted)
    for name in both.fitted:
        assert under_both.sensitivity[name] > 1.05 * under_first.sensitivity[name], name
    with_tints = gr.determination(both.effect, frame, LIGHT, target, fitted=both.fitted, other_lights=[lamp])
    assert set(with_tints.sensitivity) == {*both.fitted, "light_tints"} and with_tints.sensitivity["light_tints"] > 1e-3
    with pytest.raises(ValueError, match=r"other_lights\[0\]\[0\]\.tint"):
        fit(truth, frame, LIGHT, target, other_lights=[gr.Light(xy=(6.0, 3.0), tint=-1.0)], fixed=FIXED_RAYS)
    with pytest.raises(ValueError, match="one sequence of Light per frame"):
        fit(truth, [frame, frame], [LIGHT, LIGHT], [target, target], other_lights=[[lamp]], fixed=FIXED_RAYS)


@pytest.mark.slow
def test_the_fits_jacobian_by_stages_is_reverse_modes_on_volumetric_fog():
    """The fit linearises by a vmapped forward-mode Jacobian, one vectorised JVP per stage of the effect's fields
    (`fit_programs.forward_mode` by `FitProblem.lane_groups`, as optimistix's solvers take it: `objective_function`;
    VolumetricFog's in four: the march, the slabs' fields (the shadows, here read along lines), the medium's ends, the
    final sum), each stage's lanes with the other stages' unknowns held constant, and the field of view's column by
    central differences, within 2 % of reverse mode's there. Its gradient is reverse mode's: a column
    taken from another unknown, or a stage's columns missing, changes it. On VolumetricFog's chained read XLA once
    mixed the lanes (the display loss's `abs` with a select in the read; fine at 18x32, wrong at 36x64), and again on
    a read of both pieces by flat-index gathers (fine at 36x64, wrong at 90x160: docs/findings.md,
    "XLA and the vmapped forward-mode Jacobian"), so the frame is that large."""
    height, width = 90, 160
    depth = np.full((height, width), np.inf, np.float32)
    rows = np.arange(height - height // 2) + 0.5
    depth[height // 2 :] = (3.0 * height / rows)[:, None]  # the ground
    depth[height // 5 :, 65:95] = 6.0  # a pillar hiding the sun
    color = np.where(np.isfinite(depth)[..., None], 0.05, 0.4).astype(np.float32) * np.ones(3, np.float32)
    rows, cols = np.mgrid[:height, :width]
    color[((rows - 27.0) ** 2 + (cols - 80) ** 2 < 29.4) & ~np.isfinite(depth)] = 30.0
    frame = gr.Buffers(color=jnp.asarray(color), depth=jnp.asarray(depth), coverage=jnp.asarray(np.isfinite(depth), jnp.float32))
    light = jnp.asarray([80.8, 27.5], jnp.float32)
    medium = dict(light_color=(2.0, 2.0, 2.0), ambient_color=(0.1, 0.1, 0.1))
    # Every stage moves the frame: a layer top within the medium, a falloff with height, an ambient that rises.
    shape = dict(height_falloff=0.02, layer_top=8.0, ambient_rise=0.1, fov_x_deg=60.0, shadows="lines",
                 num_shadow_lines=96, num_shadow_bins=64)  # fmt: skip
    start = gr.VolumetricFog(medium=gr.Medium(extinction=0.013, max_distance=50.0, anisotropy=0.6, **medium), **shape)
    truth = gr.VolumetricFog(medium=gr.Medium(extinction=0.02, max_distance=40.0, anisotropy=0.7, **medium), **shape)
    target = truth(frame, light) + 0.01 * jnp.asarray(np.random.default_rng(0).normal(size=(height, width, 3)), jnp.float32)
    frame_data = as_frames(frame, light, target, True)
    problem = FitProblem.of(start, fitted_bounds(start), frame_data[0], loss="mse", space="display")
    stages = [{problem.stages[problem.names.index(n)] for n in problem.names if n in group} for group in
              [("medium.light_color", "ambient_rise"), ("medium.max_distance", "layer_top"), ("thickness", "edge_softness"),
               ("medium.extinction", "medium.anisotropy"), ("fov_x_deg",)]]  # fmt: skip
    assert len(problem.lane_groups) == 5 and all(len(stage) == 1 for stage in stages) and len(set.union(*stages)) == 5
    assert [problem.group_stages[index] for index in problem.differenced_groups] == ["camera"]
    y = start_point(problem, jnp.float32)
    assert sorted(i for group in problem.lane_groups for i in group) == list(range(y.size))

    def objective(flat, frame_data):
        return problem.objective(problem.effect_at(flat), frame_data)

    # Compiled as the command compiles them: XLA's older fusion emitters, which the suite compiles with
    # (conftest.py), mixed the march's lanes here (docs/findings.md, "XLA and the vmapped forward-mode Jacobian").
    compiled = functools.partial(jax.jit, compiler_options={"xla_cpu_use_fusion_emitters": True})
    reverse = compiled(lambda flat: jax.grad(objective)(flat, frame_data))(y)
    forward = compiled(lambda flat: jax.grad(lambda at: objective_function(at, (problem, frame_data))[0])(flat))(y)
    (fov,) = problem.stage_unknowns(("camera",))  # a difference (`Effect.DIFFERENCED_STAGES`): its secant's error
    others = np.asarray([index for index in range(y.size) if index != fov])
    np.testing.assert_allclose(forward[others], reverse[others], rtol=1e-4, atol=1e-6 * float(jnp.max(jnp.abs(reverse))))
    assert abs(forward[fov] - reverse[fov]) < 2e-2 * abs(reverse[fov])
    assert np.all(np.abs(np.asarray(reverse)) > 0)  # every unknown moves the loss


def _field_of_view_problem():
    """A small fog frame with a pillar, fitted in a march field, the field of view and a slab field, in float64."""
    height, width = 20, 36
    depth = np.full((height, width), np.inf)
    depth[height // 2 :] = (2.0 * height / (np.arange(height - height // 2) + 0.5))[:, None]  # the ground
    depth[4:, 15:20] = 5.0  # a pillar in the light
    frame = gr.Buffers(color=jnp.full((height, width, 3), 0.1), depth=jnp.asarray(depth),
                       coverage=jnp.asarray(np.isfinite(depth), jnp.float64))  # fmt: skip
    light = jnp.asarray([17.3, 3.4])
    effect = gr.VolumetricFog(medium=gr.Medium(extinction=0.05, light_color=(2.0, 2.0, 2.0)), fov_x_deg=60.0,
                              layer_top=6.0, shadows="lines", num_shadow_lines=24, num_shadow_bins=12)  # fmt: skip
    target = jnp.asarray(gr.replace_fields(effect, {"fov_x_deg": 55.0, "medium.extinction": 0.04})(frame, light))
    frame_data = as_frames(frame, light, target, True)
    fitted = ("medium.extinction", "fov_x_deg", "thickness")
    bounds = fitted_bounds(effect, fixed=[name for name in fitted_bounds(effect) if name not in fitted])
    problem = FitProblem.of(effect, bounds, frame_data[0], loss="mse", space="display")
    assert [problem.group_stages[index] for index in problem.differenced_groups] == ["camera"]
    (fov,) = problem.stage_unknowns(("camera",))
    return problem, frame_data, fov, np.asarray([index for index in range(len(fitted)) if index != fov])


@pytest.mark.slow
def test_the_field_of_views_column_is_a_central_difference_of_renders_without_derivatives(x64):
    """VolumetricFog's field of view moves every ray of the march and every shadow's line: its column of the fit's
    Jacobian (`residuals_and_jacobian`: Levenberg-Marquardt, the determination) is a central difference of two
    renders without derivatives (`Effect.DIFFERENCED_STAGES`), so that no forward-mode lane carries the lines' table
    for it. It is forward mode's column to within a percent (the difference's secant across the lines' bins, where
    forward mode takes their slope); every other column is forward mode's own."""
    problem, frame_data, fov, others = _field_of_view_problem()
    positions = problem.positions(jnp.float64)
    _, jacobian = residuals_and_jacobian(problem, positions, frame_data)
    # Compiled (eager, the effect would compile op by op), with the command's fusion emitters (the older ones mix a
    # vmapped march's lanes: docs/findings.md, "XLA and the vmapped forward-mode Jacobian").
    residuals = lambda at: problem.residuals_of(problem.effect_at_positions(at), frame_data)  # noqa: E731
    exact = jax.jit(jax.jacfwd(residuals), compiler_options={"xla_cpu_use_fusion_emitters": True})(positions)
    np.testing.assert_allclose(jacobian[:, others], exact[:, others], rtol=1e-9, atol=1e-12)
    assert np.linalg.norm(jacobian[:, fov] - exact[:, fov]) < 2e-2 * np.linalg.norm(exact[:, fov]) != 0


def test_every_stage_names_a_fittable_field():
    for effect_type in {type(gr.preset(name)) for name in gr.PRESETS}:
        infos = gr.field_metadata(effect_type)
        for name in effect_type.FIELD_STAGES:
            assert name in infos and infos[name].kind == "fittable", (effect_type.__name__, name)


def test_loss_history_starts_at_the_start_and_never_rises(two_frame_fit):
    frames, targets, result = two_frame_fit
    start_loss = np.mean([gr.mse_loss(_rays(**START)(f, light), t) for f, light, t in zip(frames, LIGHTS, targets)])
    assert result.loss_before == pytest.approx(start_loss, rel=1e-5)
    assert result.loss_history[0] == pytest.approx(result.loss_before)
    assert len(result.loss_history) == result.steps + 1 - (result.steps > 0)
    assert np.all(np.diff(result.loss_history) <= 1e-9)  # accepted losses never rise
    assert result.loss_history[-1] == pytest.approx(result.loss_after, rel=1e-3, abs=1e-12)


def test_gauss_newton_recovers_the_parameters_from_a_near_start():
    """Gauss-Newton keeps optimistix's QR; its full, undamped steps need a start near the solution.

    (From `START` it overshoots: density 1.92 after 30 steps, where Levenberg-Marquardt converges in 14.)
    """
    frame = _frame()
    target = _rays(**TRUTH)(frame, LIGHT)
    start = _rays(density=0.7, decay=0.9, exposure=0.25)
    result = fit(start, frame, LIGHT, target, solver="gauss_newton", fixed=FIXED_RAYS, max_steps=30)
    assert result.converged
    for name in result.fitted:
        np.testing.assert_allclose(getattr(result.effect, name), TRUTH[name], rtol=0.02, err_msg=name)


def test_a_second_fit_of_the_same_problem_reuses_the_compilation(two_frame_fit, caplog):
    """Another start of the same problem (same frames, effect type and fitted fields) compiles nothing."""
    frames, targets, _ = two_frame_fit
    with jax.log_compiles(), caplog.at_level("WARNING"):
        again = fit(_rays(density=0.6, decay=0.9, exposure=0.2), frames, LIGHTS, targets, fixed=FIXED_RAYS, max_steps=30)
    assert not [r.getMessage() for r in caplog.records if r.getMessage().startswith("Finished XLA")]
    np.testing.assert_allclose(again.effect.density, TRUTH["density"], rtol=0.02)


def test_a_weakly_typed_start_compiles_the_loss_once(caplog):
    """`eqx.tree_at(..., jnp.asarray(0.6))` gives a weakly typed field; the fitted effect's are not: the render that
    gives the losses before and after, and the solver's program, each compile once."""
    frame = _frame()
    effect = _rays(max_samples=6, num_samples=6.0)  # a problem no other test compiles
    target = eqx.tree_at(lambda e: e.density, effect, jnp.asarray(0.8))(frame, LIGHT)
    start = eqx.tree_at(lambda e: e.density, effect, jnp.asarray(0.6))
    assert start.density.aval.weak_type
    with jax.log_compiles(), caplog.at_level("WARNING"):
        result = fit(start, frame, LIGHT, target, fixed=FIXED_RAYS + ("decay", "exposure"), max_steps=5)
    for program in ("_render", "residuals_and_jacobian"):
        compiled = [r.getMessage() for r in caplog.records if f"XLA compilation of jit({program})" in r.getMessage()]
        assert len(compiled) == 1, compiled
    assert result.loss_after < result.loss_before


def test_a_fit_compiles_only_its_own_steps(caplog):
    """No operation outside the fit's compiled functions is compiled on its own (each costs a compilation): the
    start, the residuals and their Jacobian (every solver step's), the render and its loss (the losses before and
    after), the fitted effect."""
    frame = _frame()
    fixed = FIXED_RAYS + ("decay", "exposure")
    # optimistix and equinox build a few constants on their first use in a process: a first fit of
    # another size and other unknowns, whose operations compiled one by one would not serve the next.
    small = gr.Buffers(color=frame.color[:16], depth=frame.depth[:16], coverage=frame.coverage[:16])
    effect = _rays(max_samples=3, num_samples=3.0)
    fit(effect, small, LIGHT, effect(small, LIGHT), fixed=FIXED_RAYS + ("exposure",), max_steps=1)
    effect = _rays(max_samples=5, num_samples=5.0)  # a problem no other test compiles
    target = eqx.tree_at(lambda e: e.density, effect, jnp.asarray(0.8, jnp.float32))(frame, LIGHT)
    with jax.log_compiles(), caplog.at_level("WARNING"):
        fit(effect, frame, LIGHT, target, fixed=fixed, max_steps=3)
    compiled = {r.getMessage().split()[4] for r in caplog.records if r.getMessage().startswith("Finished XLA")}
    expected = ("start_point", "residuals_and_jacobian", "_render", "_image_loss", "_fitted_effects")
    assert compiled == {f"jit({name})" for name in expected}


def test_a_repeated_fit_traces_and_compiles_nothing(caplog, monkeypatch):
    frame = _frame()
    effect = _rays(max_samples=4, num_samples=4.0)  # a problem no other test compiles
    target = eqx.tree_at(lambda e: e.density, effect, jnp.asarray(0.8, jnp.float32))(frame, LIGHT)
    traced = []
    call = gr.GodRays.__call__
    monkeypatch.setattr(gr.GodRays, "__call__", lambda self, *args, **kwargs: traced.append(1) or call(self, *args, **kwargs))
    fit(effect, frame, LIGHT, target, fixed=FIXED_RAYS + ("decay", "exposure"), max_steps=3)
    assert traced
    traced.clear()
    with jax.log_compiles(), caplog.at_level("WARNING"):
        result = fit(effect, frame, LIGHT, target, fixed=FIXED_RAYS + ("decay", "exposure"), max_steps=3)
    assert not traced
    assert not [r.getMessage() for r in caplog.records if r.getMessage().startswith("Finished XLA")]
    assert result.loss_after < result.loss_before


def test_a_coarse_phase_then_the_full_resolution_recovers_the_parameters():
    """The coarse phase fits the frame halved (the light and the disc's pixel size halved too); the full resolution's
    descent goes on from its result, then the polish (Marquardt's scaling) ends it."""
    frame = _frame()
    target = _rays(**TRUTH)(frame, LIGHT)
    result = fit(_rays(**START), frame, LIGHT, target, fixed=FIXED_RAYS, max_steps=30, coarse_factor=2)
    assert result.coarse_steps > 0 and result.effect.flare_size == 6.0  # pixel sizes scaled back
    assert 0 < result.polish_steps < result.steps <= 60
    assert result.loss_history[0] == pytest.approx(result.loss_before)
    assert result.loss_history[1] < 0.1 * result.loss_history[0]  # the coarse phase's result, at full resolution
    for name in result.fitted:
        np.testing.assert_allclose(getattr(result.effect, name), TRUTH[name], rtol=0.02, err_msg=name)


def test_a_coarse_jacobian_fit_descends_on_the_coarse_jacobian_and_polishes_on_its_own(monkeypatch):
    """With `coarse_jacobian` the full resolution's descent takes the coarse Jacobian (each pixel's derivatives its
    block's) and only the polish the full resolution's; the fit still recovers the parameters, its losses and
    accepted steps the full resolution's own."""
    frame = _frame()
    effect = _rays(**START)
    target = _rays(**TRUTH)(frame, LIGHT)
    heights = []
    linearise = fit_programs.residuals_and_jacobian
    monkeypatch.setattr(fit_programs, "residuals_and_jacobian",
                        lambda problem, positions, frame_data: heights.append(frame_data[0][0].height) or linearise(problem, positions, frame_data))  # fmt: skip
    for coarse_jacobian in (True, False):
        heights.clear()
        result = fit(effect, frame, LIGHT, target, fixed=FIXED_RAYS, max_steps=30, coarse_factor=2,
                     coarse_jacobian=coarse_jacobian)  # fmt: skip
        fine_steps = result.steps - result.polish_steps
        assert result.coarse_steps > 0 and result.polish_steps > 0 and fine_steps > 0
        full = heights.count(HEIGHT)
        if coarse_jacobian:
            assert heights.count(HEIGHT // 2) > result.coarse_steps and full <= result.polish_steps + 1
        else:
            assert full >= fine_steps
        history = result.loss_history[1:]  # the full resolution's losses, each accepted step's
        assert np.all(np.diff(history) <= 1e-6 * history[:-1] + 1e-12)
        own_loss = float(jnp.mean((gr.display_map(result.effect(frame, LIGHT)) - gr.display_map(target)) ** 2))
        np.testing.assert_allclose(result.loss_after, own_loss, rtol=1e-4, atol=1e-12)
        for name in result.fitted:
            np.testing.assert_allclose(getattr(result.effect, name), TRUTH[name], rtol=0.02, err_msg=name)


def test_the_coarse_linearisation_is_the_full_resolutions_on_a_frame_of_blocks():
    """On a frame whose every 2 x 2 block is one colour and depth, seen by an effect that reads what lies around a
    pixel (the rays' samples toward the light), the coarse linearisation's normal equations are the full
    resolution's Jacobian's to within what the block's pixels see differently; a factor or a scale wrong by the
    blocks' size would miss by 4x."""
    coarse_frame = _frame()
    block = lambda a: jnp.repeat(jnp.repeat(jnp.asarray(a), 2, 0), 2, 1)  # noqa: E731
    frame = gr.Buffers(color=block(coarse_frame.color), depth=block(coarse_frame.depth), coverage=block(coarse_frame.coverage))
    effect = _rays(**START)
    target = _rays(**TRUTH)(frame, 2 * LIGHT)
    frame_data = as_frames(frame, 2 * LIGHT, target, True)
    bounds = fitted_bounds(effect, fixed=FIXED_RAYS)
    problem = FitProblem.of(effect, bounds, frame_data[0], loss="mse", space="display")
    positions = problem.positions(jnp.float32)
    residuals, jacobian = residuals_and_jacobian(problem, positions, frame_data)
    reduced = downsample_frames(frame_data, 2)
    coarse_problem = FitProblem.of(scale_pixel_fields(effect, 0.5), bounds, reduced[0], loss="mse", space="display")
    linearisation = CoarseLinearisation.of(coarse_problem, reduced, 2)
    normal, gradient = linearisation.normal_equations(positions, np.asarray(residuals), problem, frame_data)
    fine_normal = np.asarray(jacobian, np.float64).T @ np.asarray(jacobian, np.float64)
    fine_gradient = np.asarray(jacobian, np.float64).T @ np.asarray(residuals, np.float64)
    np.testing.assert_allclose(np.diag(normal), np.diag(fine_normal), rtol=0.2)
    np.testing.assert_allclose(gradient, fine_gradient, rtol=0.2, atol=0.05 * np.abs(fine_gradient).max())
    assert np.linalg.norm(normal - fine_normal) < 0.1 * np.linalg.norm(fine_normal)
    # Every stage sharp: the full resolution's own normal equations, to within its differences' error in float32.
    every = dataclasses.replace(linearisation, sharp=problem.group_stages)
    own_normal, own_gradient = every.normal_equations(positions, np.asarray(residuals), problem, frame_data)
    np.testing.assert_allclose(own_normal, fine_normal, rtol=2e-3, atol=1e-6 * np.abs(fine_normal).max())
    np.testing.assert_allclose(own_gradient, fine_gradient, rtol=2e-3, atol=1e-6 * np.abs(fine_gradient).max())
    with_pixels = FitProblem.of(effect, fitted_bounds(effect, fixed=[n for n in FIXED_RAYS if n != "flare_size"]),
                                frame_data[0], loss="mse", space="display")  # fmt: skip
    assert CoarseLinearisation.of(with_pixels, reduced, 2) is None  # a size in pixels is another value at each


def test_differences_on_a_bound_are_one_sided_and_render_only_values_in_range():
    """`rendered_differences` renders each field a step either side of its position, and only one side of it on a
    bound of its range (a value beyond one, such as a negative thickness, is refused): every column, central or
    one-sided, is forward mode's to within the step's error, the density's within the secant's across the samples'
    interpolation (a few percent), which forward mode takes the slope of."""
    frame = _frame()
    target = _rays(**TRUTH)(frame, LIGHT)
    frame_data = as_frames(frame, LIGHT, target, True)
    problem = FitProblem.of(_rays(**START), fitted_bounds(_rays(), fixed=FIXED_RAYS), frame_data[0], loss="mse",
                            space="display")  # fmt: skip
    positions = np.array(problem.positions(jnp.float32))
    positions[1:] = (0.0, 1.0)  # density inside, decay and exposure on their bounds
    columns = rendered_differences(problem, jnp.asarray(positions), frame_data, range(len(positions)))
    exact = np.asarray(jax.jacfwd(lambda at: problem.residuals_of(problem.effect_at_positions(at), frame_data))(
        jnp.asarray(positions)))  # fmt: skip
    for index in range(len(positions)):
        error = np.linalg.norm(columns[:, index] - exact[:, index]) / np.linalg.norm(exact[:, index])
        assert error < (0.1 if index == 0 else 1e-2), (index, error)
    assert problem.names == ("density", "decay", "exposure")


@pytest.mark.slow
def test_a_polish_linearisation_takes_the_sharp_stages_columns_at_full_resolution():
    """The polish's normal equations after a coarse phase are those of the Jacobian whose `SHARP_STAGES` columns
    are the full resolution's own, central differences of its renders (`rendered_differences`: no Jacobian of the
    full resolution to compile), and whose other columns are the coarse ones spread over their blocks (built here
    explicitly, on `VolumetricFog`, whose slabs' fields are its sharp stage)."""
    height, width = 12, 20
    depth = np.full((height, width), np.inf, np.float32)
    depth[height // 2 :] = 12.0
    depth[2:, 9:12] = 6.0
    color = np.where(np.isfinite(depth)[..., None], 0.05, 0.4).astype(np.float32) * np.ones(3, np.float32)
    frame = gr.Buffers(color=jnp.asarray(color), depth=jnp.asarray(depth), coverage=jnp.asarray(np.isfinite(depth), jnp.float32))
    light = jnp.asarray([10.3, 2.6], jnp.float32)
    shape = dict(fov_x_deg=60.0, shadows="lines", num_shadow_lines=16, num_shadow_bins=16, num_view_steps=2, resolution_factor=1)
    effect = gr.VolumetricFog(medium=gr.Medium(extinction=0.02, max_distance=40.0), **shape)
    target = gr.VolumetricFog(medium=gr.Medium(extinction=0.03, max_distance=40.0), thickness=0.3, **shape)(frame, light)
    frame_data = as_frames(frame, light, target, True)
    bounds = fitted_bounds(effect, fixed=["fov_x_deg", "medium.ambient_color", "layer_top", "height_falloff"])
    problem = FitProblem.of(effect, bounds, frame_data[0], loss="mse", space="display")
    assert len(problem.group_stages) > 1 and gr.VolumetricFog.SHARP_STAGES == ("shadows",)
    positions = problem.positions(jnp.float32)
    residuals = np.asarray(problem.residuals_of(problem.effect_at_positions(positions), frame_data), np.float64)
    reduced = downsample_frames(frame_data, 2)
    coarse_problem = FitProblem.of(effect, bounds, reduced[0], loss="mse", space="display")
    _, coarse = residuals_and_jacobian(coarse_problem, positions, reduced)
    spread = np.repeat(np.repeat(np.asarray(coarse, np.float64).reshape(height // 2, width // 2, 3, -1), 2, 0), 2, 1)
    mixed = 0.5 * spread.reshape(residuals.size, -1)  # a fine residual's scale over a coarse one's: sqrt(1 / 4)
    sharp = list(problem.stage_unknowns(("shadows",)))
    for index in sharp:  # differences of the differentiable render's residuals, which the fit's own renders equal
        step = DIFFERENCE_STEP * np.eye(len(positions), dtype=np.float32)[index]
        above, below = (
            np.asarray(problem.residuals_of(problem.effect_at_positions(positions + sign * step), frame_data), np.float64)
            for sign in (1, -1)
        )  # fmt: skip
        mixed[:, index] = (above - below) / (2 * DIFFERENCE_STEP)
    # Forward mode's sharp columns, by one JVP each (no Jacobian by stages of the full resolution to compile).
    residuals_at = lambda at: problem.residuals_of(problem.effect_at_positions(at), frame_data)  # noqa: E731
    tangents = jnp.eye(len(positions), dtype=jnp.float32)[jnp.asarray(sharp)]
    forward = jax.jit(jax.vmap(lambda tangent: jax.jvp(residuals_at, (positions,), (tangent,))[1]))(tangents)
    forward = np.asarray(forward, np.float64).T
    assert np.linalg.norm(mixed[:, sharp] - forward) < 0.5 * np.linalg.norm(forward)  # forward mode's
    linearisation = dataclasses.replace(CoarseLinearisation.of(coarse_problem, reduced, 2), sharp=("shadows",))
    normal, gradient = linearisation.normal_equations(positions, residuals, problem, frame_data)
    np.testing.assert_allclose(normal, mixed.T @ mixed, rtol=2e-3, atol=1e-6 * np.abs(mixed.T @ mixed).max())
    np.testing.assert_allclose(gradient, mixed.T @ residuals, rtol=2e-3, atol=1e-6 * np.abs(mixed.T @ residuals).max())
    # A polish keeps the sharp columns of its first point (`kept`): elsewhere the rest are that point's own.
    kept = dataclasses.replace(linearisation, kept={})
    kept.normal_equations(positions, residuals, problem, frame_data)
    moved = positions.at[sharp[0]].add(0.1)
    fresh, _ = linearisation.normal_equations(moved, residuals, problem, frame_data)
    normal_kept, _ = kept.normal_equations(moved, residuals, problem, frame_data)
    rest = [index for index in range(len(positions)) if index not in sharp]
    np.testing.assert_allclose(normal_kept[np.ix_(sharp, sharp)], normal[np.ix_(sharp, sharp)], rtol=1e-12)
    np.testing.assert_allclose(normal_kept[np.ix_(rest, rest)], fresh[np.ix_(rest, rest)], rtol=1e-12)
    assert not np.allclose(fresh[np.ix_(sharp, sharp)], normal[np.ix_(sharp, sharp)], rtol=1e-2)
    # Every field of the sharp stage held: the coarse columns alone, as without a sharp stage.
    held = fitted_bounds(effect, fixed=["fov_x_deg", "medium.ambient_color", "layer_top", "height_falloff", "thickness",
                                        "edge_softness"])  # fmt: skip
    problem, coarse_problem = (FitProblem.of(effect, held, frames[0], loss="mse", space="display")
                               for frames in (frame_data, reduced))  # fmt: skip
    assert not problem.stage_unknowns(("shadows",))
    positions = problem.positions(jnp.float32)
    residuals = np.asarray(problem.residuals_of(problem.effect_at_positions(positions), frame_data), np.float64)
    plain = CoarseLinearisation.of(coarse_problem, reduced, 2)
    for got, expected in zip(dataclasses.replace(plain, sharp=("shadows",)).normal_equations(
            positions, residuals, problem, frame_data), plain.normal_equations(positions, residuals, problem, frame_data)):
        np.testing.assert_array_equal(got, expected)


def test_the_fit_begins_from_the_start_with_the_lowest_loss():
    """The effect given and each of `starts` (their fitted fields, clipped to the fitting ranges) are fitted: the best wins."""
    frame = _frame()
    target = _rays(**TRUTH)(frame, LIGHT)
    far, truth = _rays(density=0.2, decay=0.5, exposure=0.9), _rays(**TRUTH, tint=(0.0, 0.0, 0.0))  # tint is fixed
    result = fit(_rays(**START), frame, LIGHT, target, fixed=FIXED_RAYS, max_steps=1, starts=[far, truth])
    assert result.start == 2 and result.loss_history[1] < 1e-9 < result.loss_before
    np.testing.assert_array_equal(result.effect.tint, _rays().tint)
    with pytest.raises(ValueError, match="starts"):
        fit(_rays(), frame, LIGHT, target, starts=[gr.preset("volumetric_haze")])


def test_starts_race_by_successive_halving():
    """Three starts take 2 steps each, the better two 4 in all, the best goes on to 10: 6 + 4 + 6 steps at most; a
    start that repeats the effect given is raced once (four would take 8 + 4 + 6)."""
    frame = _frame()
    target = _rays(**TRUTH)(frame, LIGHT)
    far, near = _rays(density=0.2, decay=0.5, exposure=0.9), _rays(density=0.78, decay=0.86, exposure=0.29)
    losses = []
    result = fit(
        _rays(**START), frame, LIGHT, target, fixed=FIXED_RAYS, max_steps=10, starts=[far, _rays(**START), near], probe_steps=2,
        plateau_steps=0, rtol=1e-12, atol=1e-15, progress=lambda step, value: losses.append(value),
    )  # fmt: skip
    assert result.start == 3 and len(losses) == result.steps and result.steps - result.polish_steps <= 16 < 3 * 10
    assert result.loss_after < 1e-3 * result.loss_before


def test_the_race_two_starts_at_a_time_ends_as_one_at_a_time(monkeypatch):
    """The race advances its starts on two threads: every start's losses, the winner and the fit are those of the
    starts advanced one after another, the steps reported once each and numbered in order."""
    frame = _frame()
    target = _rays(**TRUTH)(frame, LIGHT)
    far, near = _rays(density=0.2, decay=0.5, exposure=0.9), _rays(density=0.78, decay=0.86, exposure=0.29)
    threads, advance_together = set(), fit_phases.advance_two_at_a_time

    def recorded(runs, until, advance):
        def advance_recorded(run, until, stop=None):
            threads.add(threading.current_thread().name)
            advance(run, until, stop)

        advance_together(runs, until, advance_recorded)

    def one_at_a_time(runs, until, advance):
        for run in runs:
            advance(run, until)

    results = []
    for together in (recorded, one_at_a_time):
        monkeypatch.setattr(fit_module, "advance_two_at_a_time", together)
        steps = []
        results.append(fit(
            _rays(**START), frame, LIGHT, target, fixed=FIXED_RAYS, max_steps=10, starts=[far, near], probe_steps=2,
            plateau_steps=0, progress=lambda step, value: steps.append(step),
        ))  # fmt: skip
        assert steps == list(range(1, results[-1].steps + results[-1].coarse_steps + 1))
    assert threads == {"MainThread", "godrays-jax-race"}
    together, alone = results
    assert together.start == alone.start
    np.testing.assert_array_equal(together.loss_history, alone.loss_history)
    for name in ("density", "decay", "exposure"):
        np.testing.assert_array_equal(getattr(together.effect, name), getattr(alone.effect, name))


class _Steps:
    """A run of the race as `advance_two_at_a_time` sees it: its steps, each taking `seconds`."""

    def __init__(self, seconds=0.0):
        self.steps, self.seconds, self.seen = 0, seconds, []


def _advance(run, until, stop=None, fails_on=None):
    """`_descend`'s `advance` for `_Steps`, what each step's thread sees of the caller's settings recorded; its
    third step fails on the thread named `fails_on`."""
    while run.steps < until and not (stop is not None and stop.is_set()):
        thread = threading.current_thread().name
        run.seen.append((thread, jax.config.jax_default_matmul_precision, ranges_are_guaranteed()))
        if run.steps == 2 and thread == fails_on:
            raise ValueError(f"a step on {thread} failed")
        time.sleep(run.seconds)
        run.steps += 1


def test_the_race_two_at_a_time_runs_its_helper_in_the_callers_settings():
    """The helper thread traces as the caller's would: JAX's settings (kept per thread) and the context's carried."""
    runs = [_Steps(seconds=0.01) for _ in range(4)]
    with jax.default_matmul_precision("highest"), ranges_guaranteed():
        fit_phases.advance_two_at_a_time(runs, 3, _advance)
    assert [run.steps for run in runs] == [3] * 4
    seen = {entry for run in runs for entry in run.seen}
    assert {thread for thread, _, _ in seen} == {"MainThread", "godrays-jax-race"}
    assert {(precision, guaranteed) for _, precision, guaranteed in seen} == {("highest", True)}


@pytest.mark.parametrize("fails_on", ["MainThread", "godrays-jax-race"])
def test_an_error_on_either_of_the_races_threads_stops_both_and_is_raised(fails_on):
    """The other thread stops after its step, no run waiting is started, and the helper has ended."""
    runs = [_Steps(seconds=0.02) for _ in range(4)]
    with pytest.raises(ValueError, match=f"a step on {fails_on} failed"):
        fit_phases.advance_two_at_a_time(runs, 50, functools.partial(_advance, fails_on=fails_on))
    assert sorted(run.steps for run in runs)[:2] == [0, 0]  # two runs waiting, never started
    assert max(run.steps for run in runs) < 50  # the other thread's run stopped
    assert "godrays-jax-race" not in {thread.name for thread in threading.enumerate()}


def test_levenberg_marquardt_is_polished_with_marquardts_scaling_and_no_other_solver():
    """The polish goes on from where the descent stops (one loss history, never rising); BFGS and a solver the
    caller built run alone."""
    frame = _frame()
    target = _rays(**TRUTH)(frame, LIGHT)
    common = dict(fixed=FIXED_RAYS, max_steps=4, plateau_steps=0)
    polished = fit(_rays(**START), frame, LIGHT, target, **common)
    assert polished.polish_steps == 4 and polished.steps == 8 and len(polished.loss_history) == 8
    # never rising (the polish's first loss is the descent's last, evaluated by another program: float32 apart)
    assert np.all(np.diff(polished.loss_history) <= 1e-6 * polished.loss_history[:-1])
    descent = fit(_rays(**START), frame, LIGHT, target, solver=optx.LevenbergMarquardt(1e-4, 1e-7), **common)
    assert descent.polish_steps == 0 and descent.steps == 4
    assert polished.loss_after < descent.loss_after  # four more steps from where the descent stopped
    assert fit(_rays(**START), frame, LIGHT, target, solver="bfgs", **common).polish_steps == 0


def test_the_fit_stops_once_the_loss_stops_moving():
    """Any fall under 100 % of the loss over 2 steps counts as a plateau: the fit stops after its third step."""
    frame = _frame()
    target = _rays(**TRUTH)(frame, LIGHT)
    result = fit(_rays(**START), frame, LIGHT, target, fixed=FIXED_RAYS, max_steps=30, plateau_steps=2, plateau_rtol=1.0)
    assert result.plateaued and not result.converged and result.steps - result.polish_steps == 3  # the descent
    assert result.polish_steps == 3  # and the polish after it, each at its third step


def test_the_race_at_the_coarse_resolution_stops_on_its_own_plateau():
    """`coarse_plateau_steps` and `coarse_plateau_rtol` stop the coarse phase (any fall under 100 % over N steps: it
    stops at its step N + 1), `plateau_steps` the full resolution's after it."""
    frame = _frame()
    target = _rays(**TRUTH)(frame, LIGHT)
    common = dict(fixed=FIXED_RAYS, max_steps=30, coarse_factor=2, coarse_plateau_rtol=1.0)
    for steps in (2, 4):
        result = fit(_rays(**START), frame, LIGHT, target, coarse_plateau_steps=steps, **common)
        assert result.coarse_steps == steps + 1
    with pytest.raises(ValueError, match="coarse_plateau_steps"):
        fit(_rays(**START), frame, LIGHT, target, coarse_plateau_steps=-1, **common)


def test_a_rejected_step_that_leaves_little_to_gain_stalls_the_fit():
    """`stalled`: after a rejected step whose next proposal the linear model gives less than `plateau_rtol /
    plateau_steps` of the loss, once the loss has fallen; not after an accepted step, nor while a larger fall is
    predicted, nor before the loss first falls."""
    losses = [1.0, 0.5, 0.5]

    def state(slope, rejected=True):
        """At a loss of 0.5 with `J^T J = I`, the proposal the model's minimum along `slope`: half the loss falls by
        `slope^2 / 2` there, the loss by `2 slope^2` of itself."""
        y, gradient = np.zeros(2), np.asarray([-slope, 0.0])
        return MarquardtState(y=y, residuals=np.full(2, 0.5), normal=np.eye(2), gradient=gradient,
                              proposal=y - gradient, rejected=rejected)  # fmt: skip

    assert state(0.01).predicted_fall == pytest.approx(2e-4)
    assert stalled(state(0.01), losses, 5, 1.1e-3)
    assert not stalled(state(0.01), losses, 5, 0.9e-3)  # more than the model predicts is still asked
    assert not stalled(state(0.01, rejected=False), losses, 5, 1.1e-3)
    assert not stalled(state(0.1), losses, 5, 1.1e-3)
    assert not stalled(state(0.01), [1.0, 1.0, 1.0], 5, 1.1e-3)


def test_steps_rejected_before_the_loss_first_falls_are_no_plateau():
    """ground_fog from a layer top of 10: the solver's start loss, five rejected steps, then the fall (13:38 note)."""
    start, fallen = 0.012738488614559174, 0.011144778691232204
    assert not plateaued([start] * 6, 5, 1e-3)  # stopped here before: the loss evaluated first was 2e-6 higher
    assert not plateaued([start] * 6 + [fallen] * 5, 5, 1e-3)  # five steps since the fall, one of them the fall
    assert plateaued([start] * 6 + [fallen] * 6, 5, 1e-3)
    assert plateaued([start, fallen, fallen], 2, 1.0) and not plateaued([start, fallen], 2, 1.0)


def test_the_fit_command_fits_large_frames_at_a_reduced_resolution_first():
    """Every frame above 160x90 is raced at a reduced resolution of at most that many pixels."""
    sizes = ((90, 160), (100, 100), (180, 320), (256, 256), (270, 480), (1080, 1920))
    assert [auto_coarse_factor(h, w) for h, w in sizes] == [1, 1, 2, 3, 3, 12]


def test_minimiser_with_ssim_loss_improves_and_counts_round():
    frame = _frame()
    target = _rays(density=0.8, decay=0.9, exposure=0.3, num_samples=8.0)(frame, LIGHT)
    start = _rays(density=0.6, decay=0.95, exposure=0.2, num_samples=6.6)
    fixed = ("weight", "flare_size", "threshold", "tint", "offscreen_fade")
    # BFGS backtracks its first, identity-Hessian step a few times before it accepts one.
    result = fit(start, frame, LIGHT, target, loss="ssim", solver="bfgs", fixed=fixed, max_steps=10)
    assert result.loss_after < result.loss_before
    assert float(result.rounded.num_samples) == round(float(result.effect.num_samples))
    assert np.isfinite(result.loss_rounded)
    assert float(round_counts(start).num_samples) == 7.0


def _rounded_fold_loop(unit, rounding):
    """The map of unknowns into [0, 1] as the fit's docstring states it, one value at a time."""
    folded = unit % 2.0
    u = folded if folded <= 1.0 else 2.0 - folded
    stretch = 1.0 / (1.0 - rounding)
    if u < rounding:
        return stretch * u * u / (2.0 * rounding)
    if u > 1.0 - rounding:
        return 1.0 - stretch * (1.0 - u) ** 2 / (2.0 * rounding)
    return stretch * (u - rounding / 2.0)


def test_reparameterisation_stays_in_bounds_smoothly_and_a_start_on_a_bound_moves():
    units = np.linspace(-3.0, 4.0, 1401)
    values = np.asarray(from_unit(jnp.asarray(units), 0.5, 1.0))
    assert values.min() >= 0.5 and values.max() <= 1.0
    expected = [0.5 + 0.5 * _rounded_fold_loop(u, FOLD_ROUNDING) for u in units]
    np.testing.assert_allclose(values, expected, rtol=1e-6)
    # Smooth: the slope is continuous (no corner at a fold, where a field on its bound would zig-zag) and zero
    # only on the bounds themselves.
    slopes = np.asarray(jax.vmap(jax.grad(lambda u: from_unit(u, 0.5, 1.0)))(jnp.asarray(units)))
    assert np.max(np.abs(np.diff(slopes))) < 0.5 / (FOLD_ROUNDING * (1.0 - FOLD_ROUNDING)) * (units[1] - units[0]) * 1.01
    assert float(jax.grad(lambda u: from_unit(u, 0.5, 1.0))(0.0)) == 0.0
    for value in (0.5, 0.5 + 1e-4, 0.93, 1.0 - 1e-3, 1.0):
        np.testing.assert_allclose(from_unit(to_unit(value, 0.5, 1.0), 0.5, 1.0), value, rtol=1e-6)
    # A start on either bound (presets put decay on its upper bound, counts on their caps) starts inside, where
    # it has a quarter of the slope, its value moved by a tiny part of the range.
    problem = FitProblem.of(_rays(), fitted_bounds(_rays(), fixed=("tint",)), [_frame()], loss="mse", space="display")
    start = np.asarray(start_point(problem, jnp.float32))
    assert start.min() >= START_INSET and start.max() <= 1.0 - START_INSET
    for unit in (START_INSET, 1.0 - START_INSET):
        slope = float(jax.grad(lambda u: from_unit(u, 0.5, 1.0))(unit))
        assert slope == pytest.approx(0.5 * 0.25 / (1.0 - FOLD_ROUNDING), rel=1e-5)
        assert min(float(from_unit(unit, 0.5, 1.0)) - 0.5, 1.0 - float(from_unit(unit, 0.5, 1.0))) < 0.5 * FOLD_ROUNDING / 30


def test_the_race_runs_each_start_again_with_the_medium_reach_by_ratios(monkeypatch):
    """`medium.max_distance` (a room's tens of units, a sky's thousands) spans four decades: the race runs each start
    a second time with it moved by ratios, the fold's position `t` spread as `expm1(k t) / expm1(k)` on the host,
    each second run starting where its first does, whose residuals and Jacobian there it takes once."""
    fog = gr.ScatteringFog(num_samples=2.0, max_samples=2, medium=gr.Medium(extinction=0.05, max_distance=16.0))
    warp = warp_of(fog, "medium.max_distance")
    assert warp == pytest.approx(4.0 * np.log(10.0))
    assert warp_of(fog, "medium.extinction") == 0.0
    units = np.linspace(-1.5, 2.5, 801)
    spread = lambda u: np.expm1(warp * _rounded_fold_loop(u, FOLD_ROUNDING)) / np.expm1(warp)  # noqa: E731
    positions, slopes = folded_positions(units, np.full(units.shape, warp))
    np.testing.assert_allclose(positions, [spread(u) for u in units], rtol=1e-12, atol=1e-15)
    assert positions.min() >= 0.0 and positions.max() <= 1.0
    step = 1e-6
    differences = [(spread(u + step) - spread(u - step)) / (2 * step) for u in units]
    np.testing.assert_allclose(slopes, differences, rtol=1e-4, atol=1e-6)  # the fold's joins: differences across a kink
    # Equal steps along the fold's straight part scale the position (plus a constant) by one ratio.
    shifted = folded_positions(np.array([0.1, 0.2, 0.5, 0.6, 0.8, 0.9]), np.full(6, warp))[0] + 1.0 / np.expm1(warp)
    np.testing.assert_allclose(shifted[1::2] / shifted[::2], np.exp(warp * 0.1 / (1.0 - FOLD_ROUNDING)), rtol=1e-9)
    # Each start's run by ratios starts at its fields' own values, and both runs of it race.
    frame = _frame()
    target = fog(frame, LIGHT)
    frame_data = as_frames(frame, LIGHT, target, True)
    bounds = fitted_bounds(fog, fixed=("fov_x_deg", "num_samples"))
    problem = FitProblem.of(fog, bounds, frame_data[0], loss="mse", space="display")
    assert np.count_nonzero(problem.warps) == 1 and problem.warps[problem.unknowns_of(("medium.max_distance",))[0]] == warp
    linear = np.asarray(start_point(problem, jnp.float32), np.float64)
    np.testing.assert_array_equal(folded_positions(warped_start(linear, problem.warps), problem.warps)[0].astype(np.float32),
                                  folded_positions(linear)[0].astype(np.float32))  # fmt: skip
    common = dict(optimiser=LevenbergMarquardt(rtol=1e-6, atol=1e-9), least_squares=True, loss="mse", space="display",
                  max_steps=2, probe_steps=1, plateau_steps=0, plateau_rtol=0.0)  # fmt: skip
    counter = fit_phases.StepCounter(None)
    taken, call = [], fit_programs.exported.call

    def counted(name, function, *arguments):
        if name == "fit_jacobian":
            taken.append(np.asarray(arguments[1]).tobytes())
        return call(name, function, *arguments)

    monkeypatch.setattr(fit_programs.exported, "call", counted)
    for by_ratios, count in ((False, 1), (True, 2)):
        taken.clear()
        runs, winner = fit_module._descend([fog], bounds, frame_data, counter, by_ratios=by_ratios, **common)
        assert len(runs) == count and runs[0].warps is None and winner in range(count)
    assert np.array_equal(runs[1].warps, problem.warps)
    assert runs[1].history[0] == runs[0].history[0] and taken.count(taken[0]) == 1, taken
    assert runs[1].steps > 0 and runs[1].history[-1] <= runs[1].history[0]


def test_bounds_are_capped_by_static_loop_lengths():
    bounds = fitted_bounds(_rays(), fixed=("tint",))
    assert bounds["num_samples"] == (1.0, 8.0)
    assert "tint" not in bounds and "max_samples" not in bounds


def test_errors_name_the_argument():
    frame = _frame()
    target = frame.color
    with pytest.raises(ValueError, match="fixed"):
        fit(_rays(), frame, LIGHT, target, fixed=("max_samples",))
    with pytest.raises(ValueError, match="loss"):
        fit(_rays(), frame, LIGHT, target, loss="psnr")
    with pytest.raises(ValueError, match="bfgs"):
        fit(_rays(), frame, LIGHT, target, loss="ssim", solver="gauss_newton")
    with pytest.raises(ValueError, match="target"):
        fit(_rays(), frame, LIGHT, target[:-1])
    with pytest.raises(ValueError, match="light_xy"):
        fit(_rays(), [frame, frame], [LIGHT], [target, target])
    with pytest.raises(ValueError, match="num_samples"):
        fit(gr.GodRays(num_samples=200.0, max_samples=128), frame, LIGHT, target)
    with pytest.raises(ValueError, match="coarse_factor"):
        fit(_rays(), frame, LIGHT, target, coarse_factor=0)
    with pytest.raises(ValueError, match="plateau_steps"):
        fit(_rays(), frame, LIGHT, target, plateau_steps=-1)


def test_fit_command_fits_two_frames_and_apply_reproduces(tmp_path, capsys):
    truth = _rays(**TRUTH)
    paths = []
    for index, light in enumerate(LIGHTS):
        frame = _frame(index)
        frame_path, target_path = tmp_path / f"frame{index}.exr", tmp_path / f"target{index}.exr"
        gr.write_buffers(frame_path, frame, light_xy=tuple(np.asarray(light).tolist()))
        gr.write_image(target_path, truth(frame, light))
        paths.append((str(frame_path), str(target_path)))
    start_path = tmp_path / "start.json"
    gr.save_effect(start_path, _rays(**START))
    params, report, applied = tmp_path / "fitted.json", tmp_path / "report.png", tmp_path / "applied.exr"
    status = main([
        "fit", *paths[0], "--frames", *paths[1], "--params", str(start_path), "-o", str(params),
        "--report", str(report), "--fixed", ",".join(FIXED_RAYS), "--max-steps", "30",
    ])  # fmt: skip
    captured = capsys.readouterr()
    assert status == 0, captured.err
    assert "loss before" in captured.out and "/60 [" in captured.err and "step/s" in captured.err  # tqdm: steps of both phases, ETA
    metrics = next(line for line in captured.out.splitlines() if line.startswith("PSNR before"))
    assert "SSIM before" in metrics and "skimage.metrics" in metrics and "mean over 2 frames" in metrics
    assert "every fitted parameter is determined" in captured.out  # density, decay, exposure: the test's own set
    fitted = gr.load_effect(params)
    for name, value in TRUTH.items():
        np.testing.assert_allclose(getattr(fitted, name), value, rtol=0.02, err_msg=name)
    assert report.exists() and gr.read_image(report).shape[:2] == (2 * (26 + 240) + 46, 2 * 320 + 8)  # enlarged x10
    assert main(["apply", paths[1][0], "--params", str(params), "-o", str(applied)]) == 0
    np.testing.assert_allclose(gr.read_image(applied)[..., :3], fitted(_frame(1), LIGHTS[1]), rtol=1e-5, atol=1e-6)
    assert json.loads(params.read_text())["effect"] == "GodRays"


def test_a_start_at_the_frames_minimum_is_handed_back(tmp_path, capsys):
    """A coarse phase's minimum lies near the full resolution's, not at it: from the truth itself the fit's steps end
    above where it began, and the fit returns the start given with its own loss and images (`kept_start`); the
    command says so and writes the start's parameters."""
    frame, truth = _frame(0), _rays(**TRUTH)
    target = truth(frame, LIGHT)
    result = fit(truth, frame, LIGHT, target, fixed=FIXED_RAYS, max_steps=10, coarse_factor=2)
    assert result.kept_start and result.start == 0
    assert result.loss_after == result.loss_rounded == result.loss_before
    assert min(result.loss_history[1:-1]) > result.loss_before == result.loss_history[-1]  # the steps, then the start
    for name in result.fitted:
        assert float(getattr(result.effect, name)) == float(getattr(truth, name)), name
    np.testing.assert_array_equal(result.images_after[0], result.images_before[0])
    frame_path, target_path, start_path = tmp_path / "frame.exr", tmp_path / "target.exr", tmp_path / "start.json"
    gr.write_buffers(frame_path, frame, light_xy=tuple(np.asarray(LIGHT).tolist()))
    gr.write_image(target_path, target)
    gr.save_effect(start_path, truth)
    params = tmp_path / "fitted.json"
    status = main(["fit", str(frame_path), str(target_path), "--params", str(start_path), "-o", str(params),
                   "--fixed", ",".join(FIXED_RAYS), "--max-steps", "10", "--coarse-factor", "2"])  # fmt: skip
    captured = capsys.readouterr()
    assert status == 0, captured.err
    assert "the start given fits the frames better than where the fit ended" in captured.out
    fitted = gr.load_effect(params)
    for name in TRUTH:
        assert float(getattr(fitted, name)) == float(getattr(truth, name)), name


def test_fit_command_errors_are_one_line(tmp_path, capsys):
    frame_path = tmp_path / "frame.exr"
    gr.write_buffers(frame_path, _frame(), light_xy=(16.5, 5.0))
    output = tmp_path / "out.json"
    status = main(["fit", str(frame_path), str(tmp_path / "missing.exr"), "-o", str(output)])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 1 and len(err) == 1 and "missing.exr" in err[0]
    assert not output.exists()


@pytest.mark.slow
def test_volumetric_fog_read_along_lines_descends_as_its_stand_in_and_polishes_as_itself(monkeypatch):
    """`fit` races and descends `VolumetricFog` read along lines as its stand-in (the same reading, coarser: rays 4
    pixels apart, half the lines and bins), polishes it with the effect's own residuals (the stand-in's Jacobian)
    and returns it with its own counts, its losses the returned effect's; `stand_in=False` fits the effect itself
    throughout."""
    height, width = 24, 40
    depth = np.full((height, width), np.inf, np.float32)
    depth[height // 2 :] = 12.0
    depth[4:, 18:23] = 6.0  # a pillar hiding the sun
    color = np.where(np.isfinite(depth)[..., None], 0.05, 0.4).astype(np.float32) * np.ones(3, np.float32)
    frame = gr.Buffers(color=jnp.asarray(color), depth=jnp.asarray(depth), coverage=jnp.asarray(np.isfinite(depth), jnp.float32))
    light = jnp.asarray([20.3, 5.6], jnp.float32)
    shape = dict(fov_x_deg=60.0, shadows="lines", num_shadow_lines=48, num_shadow_bins=32, num_view_steps=4,
                 resolution_factor=1)  # fmt: skip
    medium = dict(max_distance=40.0, anisotropy=0.7, light_color=(2.0, 2.0, 2.0), ambient_color=(0.1, 0.1, 0.1))
    start = gr.VolumetricFog(medium=gr.Medium(extinction=0.01, **medium), **shape)
    target = gr.VolumetricFog(medium=gr.Medium(extinction=0.03, **medium), **shape)(frame, light)
    stand_in = start.fit_stand_in()
    assert (stand_in.shadows, stand_in.resolution_factor, stand_in.num_shadow_lines, stand_in.num_shadow_bins) == (
        "lines", 4, 24, 32
    )
    assert gr.VolumetricFog(resolution_factor=2).fit_stand_in().resolution_factor == 2  # from samples: itself
    fixed = tuple(name for name in fitted_bounds(start) if name != "medium.extinction")
    stood_in = []
    make_stand_in = gr.VolumetricFog.fit_stand_in
    monkeypatch.setattr(gr.VolumetricFog, "fit_stand_in", lambda self: stood_in.append(self) or make_stand_in(self))
    for through_stand_in in (True, False):
        stood_in.clear()
        result = fit(start, frame, light, target, fixed=fixed, max_steps=15, stand_in=through_stand_in)
        assert bool(stood_in) == through_stand_in
        assert (result.effect.shadows, result.effect.resolution_factor) == ("lines", 1)
        own_loss = float(jnp.mean((gr.display_map(result.effect(frame, light)) - gr.display_map(target)) ** 2))
        np.testing.assert_allclose(result.loss_after, own_loss, rtol=1e-4, atol=1e-9)
        assert result.loss_after < 1e-3 * result.loss_before
        assert result.polish_steps > 0  # the effect itself polished
