"""`determination`: which fitted fields the frames pin down, on the case that motivated it (issue 18): a GodRays fit
whose sample count, decay and weight trade off against each other."""

import dataclasses
import math
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

import godrays_jax as gr
from godrays_jax.effects.fields import field_value
from godrays_jax.pipeline.determination import determination
from godrays_jax.pipeline.problem import fitted_bounds

SAMPLE = Path(__file__).resolve().parents[1] / "examples" / "data" / "sample_frame.exr"
TRUTH = gr.GodRays(
    num_samples=64.0, max_samples=128, density=0.5, decay=0.95, weight=1.0, exposure=0.3, flare_size=20.0, units="px",
    flare_shape="cone",
)


@pytest.fixture(scope="module")
def case():
    frame = gr.read_buffers(SAMPLE)
    light = jnp.asarray(gr.read_light(SAMPLE)[0])
    return frame, light, TRUTH(frame, light)


def rms_display(a, b):
    return float(np.sqrt(np.mean((gr.display_map(np.asarray(a)) - gr.display_map(np.asarray(b))) ** 2)))


def test_samples_decay_and_weight_trade_off_and_the_offsets_are_real(case):
    frame, light, target = case
    found = determination(TRUTH, frame, light, target, fitted=("density", "decay", "weight", "num_samples"))
    assert found.poorly_determined == ("num_samples",)
    assert found.sensitivity["density"] > 10 * found.sensitivity["num_samples"]
    steps = found.offsets["num_samples"]
    assert set(steps) == {"num_samples", "decay", "weight"} and steps["num_samples"] == pytest.approx(12.7)
    assert steps["decay"] > 0 > steps["weight"]  # more samples: a slower decay, a smaller weight
    moved = dataclasses.replace(TRUTH, **{name: float(getattr(TRUTH, name)) + step for name, step in steps.items()})
    alone = dataclasses.replace(TRUTH, num_samples=64.0 + steps["num_samples"])
    offset_change, alone_change = rms_display(moved(frame, light), target), rms_display(alone(frame, light), target)
    assert offset_change < 1e-3  # the linear estimate holds: a step nobody sees
    assert alone_change > 4 * offset_change  # the offsets are what hide it


def test_a_lone_scale_is_determined_and_a_field_the_image_ignores_is_not(case):
    frame, light, target = case
    found = determination(TRUTH, frame, light, target, fitted=("exposure",))
    assert found.poorly_determined == () and found.condition == pytest.approx(1.0) and found.offsets == {}
    # On screen the off-screen fade changes nothing: its column of the Jacobian is zero.
    found = determination(TRUTH, frame, light, target, fitted=("exposure", "offscreen_fade"))
    assert found.poorly_determined == ("offscreen_fade",) and found.sensitivity["offscreen_fade"] < 1e-12
    assert math.isinf(found.condition) and found.offsets["offscreen_fade"] == {"offscreen_fade": pytest.approx(0.999)}


def test_bad_arguments_are_named(case):
    frame, light, target = case
    with pytest.raises(ValueError, match="fitted"):
        determination(TRUTH, frame, light, target, fitted=("max_samples",))
    with pytest.raises(ValueError, match="change and threshold"):
        determination(TRUTH, frame, light, target, fitted=("exposure",), threshold=0.0)



FOG_SOLUTION = {
    "effect": "ScatteringFog", "medium.extinction": 5.543232e-05, "medium.max_distance": 238.63605,
    "medium.anisotropy": 0.9499991, "medium.ambient_color": [0.00047683716, 0.00086634967, 0.016395919],
    "medium.light_color": [1.6154666, 1.4604614, 1.1586595],
    "fov_x_deg": 55.907333, "shadow_strength": 0.9961381, "density": 1.009448, "decay": 0.97105277,
    "num_samples": 32.0, "offscreen_fade": 0.5, "max_samples": 32,
}  # fmt: skip
"""`godrays-jax fit` of the sample frame against `xna_crepuscular` applied to it (the default model, 36 steps)."""


def test_offsets_are_cut_off_at_the_jacobians_own_tolerance(case):
    """Shaft strength, density and sample count trade off at 1e-10 RMS here: those near-zero singular values must
    not offset the field of view (they did, by 1e4, when the triangular factor's own tolerance was used)."""
    frame, light, _ = case
    fog = gr.effect_from_dict(FOG_SOLUTION)
    target = gr.preset("xna_crepuscular")(frame, light)
    found = determination(fog, frame, light, target, fitted=tuple(gr.parameter_bounds(fog)))
    assert "fov_x_deg" in found.poorly_determined
    steps = found.offsets["fov_x_deg"]
    assert set(steps) == {"fov_x_deg", "medium.light_color[0]", "medium.light_color[1]"}, steps
    assert steps["fov_x_deg"] == pytest.approx(16.9, abs=0.1)


def test_every_offset_keeps_every_field_inside_its_range_and_fields_on_a_bound_are_named(case):
    """Issue 24 item 8: the fog solution has sample count 32 on its cap, anisotropy .9499991 on its bound .95 and
    extinction 5.5e-5 on 0; offsets of its poorly determined fields pushed the count to 43 and shadow strength past 1."""
    frame, light, _ = case
    fog = gr.effect_from_dict(FOG_SOLUTION)
    target = gr.preset("xna_crepuscular")(frame, light)
    found = determination(fog, frame, light, target, fitted=tuple(gr.parameter_bounds(fog)))
    bounds = fitted_bounds(fog)
    assert found.on_bound["num_samples"] == 32.0 and found.on_bound["medium.anisotropy"] == pytest.approx(0.95)
    assert found.on_bound["medium.extinction"] == 0.0 and "shadow_strength" not in found.on_bound  # .996: near, not on
    assert {"shadow_strength", "num_samples", "decay"} <= set(found.poorly_determined)
    for name in found.poorly_determined:
        for label, step in found.offsets[name].items():
            field, _, component = label.partition("[")
            value = np.asarray(field_value(fog, field), np.float64)
            value = value[int(component[:-1])] if component else float(value)
            low, high = bounds[field]
            assert low <= value + step <= high, (name, label, value, step)
        part_taken = abs(found.offsets[name][name]) / (0.1 * (bounds[name][1] - bounds[name][0]))
        assert part_taken <= 1 + 1e-9
        assert found.offset_change[name] == pytest.approx(found.sensitivity[name] * part_taken)
    # The count sits on its cap: its offset steps down, into the range.
    assert found.offsets["num_samples"]["num_samples"] < 0
    # A medium's reach is moved by ratios over the top decades of its range: ten units of 1e4 lie well inside them,
    # a hundredth of a unit on the bound.
    for reach, on_bound in ((9.9, False), (0.005, True)):
        near = gr.effect_from_dict({**FOG_SOLUTION, "medium.max_distance": reach})
        found = determination(near, frame, light, target, fitted=("medium.max_distance", "density"))
        assert ("medium.max_distance" in found.on_bound) == on_bound, (reach, found.on_bound)


@pytest.mark.slow
def test_after_a_coarse_phase_the_jacobian_is_the_polishs(case):
    """`coarse_factor`: the Jacobian as a fit's polish after a coarse phase takes it (the sharp stages at full
    resolution, the rest at the coarse one): for `VolumetricFog` the sensitivities stay near the full resolution's;
    an effect that names no sharp stages is examined at full resolution whatever the factor."""
    frame, light, target = case
    fitted = ("density", "decay", "weight", "num_samples")
    full, coarse = (determination(TRUTH, frame, light, target, fitted=fitted, coarse_factor=f) for f in (1, 2))
    assert coarse.sensitivity == full.sensitivity
    with pytest.raises(ValueError, match="coarse_factor"):
        determination(TRUTH, frame, light, target, fitted=fitted, coarse_factor=0)
    height, width = 12, 20
    depth = np.full((height, width), np.inf, np.float32)
    depth[height // 2 :] = 12.0
    depth[2:, 9:12] = 6.0
    color = np.where(np.isfinite(depth)[..., None], 0.05, 0.4).astype(np.float32) * np.ones(3, np.float32)
    coverage = jnp.asarray(np.isfinite(depth), jnp.float32)
    fog_frame = gr.Buffers(color=jnp.asarray(color), depth=jnp.asarray(depth), coverage=coverage)
    fog_light = jnp.asarray([10.3, 2.6], jnp.float32)
    fog = gr.VolumetricFog(medium=gr.Medium(extinction=0.03, max_distance=40.0), fov_x_deg=60.0, shadows="lines",
                           num_shadow_lines=16, num_shadow_bins=16, num_view_steps=2, resolution_factor=1)  # fmt: skip
    fog_target = fog(fog_frame, fog_light)
    fog_fitted = ("medium.extinction", "medium.anisotropy", "thickness", "edge_softness")
    full, coarse = (
        determination(fog, fog_frame, fog_light, fog_target, fitted=fog_fitted, coarse_factor=f) for f in (1, 2)
    )
    assert coarse.poorly_determined == full.poorly_determined
    ratio = {name: coarse.sensitivity[name] / full.sensitivity[name] for name in fog_fitted}
    # The slabs' columns are the full resolution's own, differences of its renders: on a frame this small, of 16
    # lines, a step's secant across the lines' bins reads up to 1.7 times forward mode's slope there. The extinction's
    # blocks are smooth: within 10 %. A row scaled by the blocks' size or its inverse (2 or 4) would miss. The
    # anisotropy's pattern around the light, on a 6 x 10 frame's blocks for a 12 x 20 one's pixels, reads about 1.9
    # times the full resolution's: between 1.2 and 2.8, which a row scaled by the blocks' size or its inverse (2 or 4
    # either way) leaves, and a column missing (0) too.
    assert 0.9 < ratio["medium.extinction"] < 1.1, ratio
    for name in ("thickness", "edge_softness"):
        assert 0.9 < ratio[name] < 2.0, (name, ratio)
    assert 1.2 < ratio["medium.anisotropy"] < 2.8, ratio
    assert coarse.sensitivity != full.sensitivity  # the coarse columns are the blocks'
