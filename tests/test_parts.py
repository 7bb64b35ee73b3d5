"""Effects built from parts: a part's fields named `part.field` in metadata, params files, fit, determination, tuner."""

import json
import warnings

import jax.numpy as jnp
import numpy as np
import pytest

import godrays_jax as gr
from godrays_jax.effects.fields import field_value, plain_value, replace_fields
from godrays_jax.pipeline.fit import fit
from godrays_jax.pipeline.problem import FitProblem, fitted_bounds, start_point
from godrays_jax.pipeline.reduced import pixel_fields, scale_pixel_fields
from frames import LIGHT, make_frame


def _spot(**bloom):
    return gr.SunSpot(sun_distance=0.2, bloom=gr.BloomBlur(**bloom))


def test_a_part_field_is_read_and_set_by_its_dotted_name():
    spot = _spot(intensity=0.5)
    assert float(gr.field_value(spot, "bloom.intensity")) == 0.5
    changed = gr.replace_fields(spot, {"bloom.intensity": 2.0, "sun_sharpness": 3.0})
    assert float(changed.bloom.intensity) == 2.0 and float(changed.sun_sharpness) == 3.0
    assert changed.bloom.blur_sigma is spot.bloom.blur_sigma, "the part's other fields stay"
    with pytest.raises(ValueError, match=r"BloomBlur\.intensity must lie in \[0, 10\]"):
        replace_fields(spot, {"bloom.intensity": 99.0})
    assert "bloom.threshold" not in gr.field_metadata(spot), "the spot's bloom blurs the spot: no bright pass"
    with pytest.raises(ValueError, match="SunSpot.bloom must be a BloomBlur,"):
        gr.SunSpot(bloom=gr.LensDirt())


FLAT_BLOOM = {"bloom_intensity": 0.5, "bloom_weights": [1.0, 0.5, 0.25, 0.125], "bloom_blur_sigma": 0.02,
              "bloom_blur_reach": 0.05, "units": "frame"}  # fmt: skip
"""`SunSpot`'s bloom as its own flat fields, as params files held it before the bloom was a part."""


def test_the_flat_bloom_names_load_into_the_part_with_one_warning_each(tmp_path):
    path = tmp_path / "spot.json"
    path.write_text(json.dumps({"effect": "SunSpot", **FLAT_BLOOM}))
    with pytest.warns(FutureWarning) as caught:
        spot = gr.load_effect(path)
    messages = [str(warning.message) for warning in caught]
    assert len(messages) == len(FLAT_BLOOM), messages
    for old in FLAT_BLOOM:
        new = "bloom." + old.removeprefix("bloom_")
        assert sum(f"SunSpot.{old} is now named {new}" in message for message in messages) == 1, messages
        if old != "units":
            np.testing.assert_allclose(np.asarray(plain_value(field_value(spot, new))), FLAT_BLOOM[old], rtol=1e-6)
    assert spot.bloom.method == "pyramid", "fields the file does not name keep the part's declared default"
    saved = gr.effect_to_dict(spot)
    assert "bloom.intensity" in saved and not set(FLAT_BLOOM) & set(saved)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert gr.effect_to_dict(gr.effect_from_dict(saved)) == saved


def test_a_fit_problem_maps_its_unknowns_onto_a_parts_field():
    start = _spot(intensity=1.0)
    fixed = [name for name in gr.parameter_bounds(start) if name not in ("bloom.intensity", "bloom.weights")]
    problem = FitProblem.of(start, fitted_bounds(start, fixed=fixed), [make_frame()], loss="mse", space="display")
    assert problem.names == ("bloom.intensity", "bloom.weights") and problem.shapes == ((), (4,))
    np.testing.assert_allclose(problem.positions(np.float32), [0.1] * 5, rtol=1e-6)
    started = problem.effect_at(start_point(problem, np.float32))
    np.testing.assert_allclose(started.bloom.intensity, start.bloom.intensity, rtol=1e-5)
    np.testing.assert_allclose(started.bloom.weights, start.bloom.weights, rtol=1e-5)
    moved = problem.effect_at_positions(jnp.asarray([0.3, 0.2, 0.2, 0.1, 0.1]))
    np.testing.assert_allclose(moved.bloom.intensity, 3.0, rtol=1e-6)
    np.testing.assert_allclose(moved.bloom.weights, [2.0, 2.0, 1.0, 1.0], rtol=1e-6)
    assert moved.bloom.blur_sigma is start.bloom.blur_sigma and moved.sun_distance is start.sun_distance


def test_the_tuner_scales_a_parts_pixel_sizes():
    spot = _spot(units="px", blur_sigma=4.0, blur_reach=12.0)
    assert pixel_fields(spot) == ("bloom.blur_sigma", "bloom.wide_blur_sigma", "bloom.blur_reach", "bloom.wide_blur_reach")
    half = scale_pixel_fields(spot, 0.5)
    assert float(half.bloom.blur_sigma) == 2.0 and half.bloom.blur_reach == 6.0
    assert gr.parameter_bounds(spot)["bloom.blur_sigma"] == (0.0, 100.0), "pixel bounds: the part's units"
    assert pixel_fields(_spot()) == ()
    assert scale_pixel_fields(spot, 1.0) is spot


FLAT_MEDIUM = {"extinction": 0.02, "max_distance": 60.0, "anisotropy": 0.5, "light_color": [2.0, 1.5, 1.0],
               "ambient_color": [0.1, 0.1, 0.2]}  # fmt: skip
"""The medium's fields as the media held them flat before `Medium` was a part."""


@pytest.mark.parametrize("kind", ["ScatteringFog", "VolumetricFog"])
def test_a_medium_round_trips_and_its_flat_names_load_with_one_warning_each(tmp_path, kind):
    path = tmp_path / "fog.json"
    path.write_text(json.dumps({"effect": kind, **FLAT_MEDIUM}))
    with pytest.warns(FutureWarning) as caught:
        fog = gr.load_effect(path)
    messages = [str(warning.message) for warning in caught]
    assert sorted(messages) == sorted(f"{kind}.{old} is now named medium.{old}: read as medium.{old}" for old in FLAT_MEDIUM)
    assert fog.medium == gr.Medium(**FLAT_MEDIUM)
    gr.save_effect(path, fog)
    saved = json.loads(path.read_text())
    assert {f"medium.{name}" for name in FLAT_MEDIUM} <= set(saved) and not set(FLAT_MEDIUM) & set(saved)
    assert gr.load_effect(path) == fog
    assert {f"medium.{name}" for name in FLAT_MEDIUM} <= set(gr.parameter_bounds(fog))


def test_a_fit_recovers_a_medium_field():
    frame = make_frame()
    start = gr.ScatteringFog(num_samples=2.0, max_samples=2, medium=gr.Medium(extinction=0.05))
    target = replace_fields(start, {"medium.extinction": 0.1})(frame, LIGHT)
    fixed = [name for name in gr.parameter_bounds(start) if name != "medium.extinction"]
    result = fit(start, frame, LIGHT, target, fixed=fixed, space="linear", max_steps=10)
    assert result.fitted == ("medium.extinction",)
    np.testing.assert_allclose(float(result.effect.medium.extinction), 0.1, rtol=1e-3)
