"""Effects as text: JSON without float32 noise, and a repr that shows the values."""

import json
from pathlib import Path

import jax
import numpy as np
import pytest

import godrays_jax as gr
from godrays_jax.effects.base import effect_class
from godrays_jax.effects.fields import field_value, plain_value, renamed_fields


def test_saved_json_holds_the_shortest_decimals_that_read_back_to_the_same_float32(tmp_path):
    effect = gr.preset("sun_overcast")
    path = tmp_path / "params.json"
    gr.save_effect(path, effect)
    text = path.read_text()
    assert '"blur_power": 0.015,' in text and "\n    0.65\n" in text
    assert "0.01499999" not in text and "0.800000011920929" not in text
    loaded = gr.load_effect(path)
    for name in gr.parameter_bounds(effect):
        np.testing.assert_array_equal(np.asarray(getattr(loaded, name)), np.asarray(getattr(effect, name)))


def test_plain_values_round_trip_every_float32(rng):
    numbers = np.concatenate([rng.standard_normal(2000), 10.0 ** rng.uniform(-30, 30, 2000)]).astype(np.float32)
    text = json.dumps(plain_value(numbers))
    np.testing.assert_array_equal(np.asarray(json.loads(text), np.float32), numbers)
    assert all(len(repr(x)) <= len(repr(float(x))) for x in plain_value(numbers))
    assert plain_value(np.float32(0.95)) == 0.95 and plain_value("disc") == "disc"
    assert plain_value(np.asarray([3, 4], np.int32)) == [3, 4]


def test_float64_values_keep_their_precision():
    with jax.enable_x64(True):
        value = plain_value(jax.numpy.asarray(0.1, jax.numpy.float64) * 3)
    assert value == 0.1 * 3


def test_an_effect_prints_its_values():
    text = repr(gr.preset("xna_crepuscular"))
    assert text.startswith("GodRays(flare_size=") and "density=0.5, decay=0.95, weight=1.0, exposure=0.15," in text
    assert "tint=[1.0, 0.85, 0.6]" in text and "source='disc'" in text and "f32[]" not in text
    assert str(gr.preset("xna_crepuscular")) == text


OLD_NAMES = {
    "ScatteringFog": {"sun_irradiance": [0.5, 0.4, 0.3], "ambient": [0.01, 0.02, 0.03], "shaft_strength": 0.6},
    "SunOvercast": {"passes": 1.0, "glow_color": [0.8, 0.5, 0.0, 0.65]},
    "FlareOuts": {"target_factor": 2},
    "Bloom": {"sigma": 0.02, "reach": 0.05, "gaussian_sigma": 0.03, "gaussian_reach": 0.09},
    "LensDirt": {"far": 50.0, "sun_color": [1.0, 0.9, 0.8]},
    "SunSpot": {"sun_color": [1.0, 0.9, 0.8], "glow_intensity": 0.5, "glow_weights": [1.0, 0.5, 0.25, 0.125],
                "glow_sigma": 0.02, "glow_reach": 0.05},
}  # fmt: skip
"""Every renamed field of every effect, with a value other than its default."""


@pytest.mark.parametrize("kind", sorted(OLD_NAMES))
def test_a_params_file_with_old_names_loads_and_warns_with_the_new_name(tmp_path, kind):
    renamed = renamed_fields(effect_class(kind))
    assert set(OLD_NAMES[kind]) <= set(renamed)
    path = tmp_path / "old.json"
    path.write_text(json.dumps({"effect": kind, **OLD_NAMES[kind]}))
    with pytest.warns(FutureWarning) as caught:
        effect = gr.load_effect(path)
    messages = [str(warning.message) for warning in caught]
    for old, value in OLD_NAMES[kind].items():
        new = renamed[old]
        assert any(f"{kind}.{old} is now named {new}" in message for message in messages), messages
        np.testing.assert_allclose(np.asarray(plain_value(field_value(effect, new)), np.float64), value, rtol=1e-6)
    saved = gr.effect_to_dict(effect)
    assert not set(OLD_NAMES[kind]) & set(saved), "files are written with the new names"


def test_a_part_saves_as_part_dot_field_and_names_its_fields_from_the_effect(tmp_path):
    spot = gr.SunSpot(bloom=gr.BloomBlur(intensity=0.5, blur_sigma=0.02, method="gaussian"))
    saved = gr.effect_to_dict(spot)
    assert saved["bloom.intensity"] == 0.5 and saved["bloom.blur_sigma"] == 0.02 and "bloom" not in saved
    gr.save_effect(tmp_path / "spot.json", spot)
    loaded = gr.load_effect(tmp_path / "spot.json")
    assert float(loaded.bloom.intensity) == 0.5 and loaded.bloom.method == "gaussian"
    assert {"bloom.intensity", "bloom.blur_sigma", "bloom.blur_reach"} <= set(gr.field_metadata(gr.SunSpot))
    with pytest.raises(ValueError, match=r"SunSpot\.bloom\.intensity must lie in \[0, 10\]"):
        gr.effect_from_dict({"effect": "SunSpot", "bloom.intensity": 99})
    with pytest.raises(ValueError, match="unknown parameter.*bloom.sigmaa"):
        gr.effect_from_dict({"effect": "SunSpot", "bloom.sigmaa": 1})


def test_an_old_name_beside_its_new_name_is_refused():
    with pytest.raises(ValueError, match="'ambient' and its new name 'medium.ambient_color'"):
        gr.effect_from_dict({"effect": "ScatteringFog", "ambient": [0, 0, 0], "medium.ambient_color": [0, 0, 0]})


def test_the_cli_names_the_new_name_in_one_warning_line(tmp_path, capsys):
    from godrays_jax.app.cli import main

    params = tmp_path / "old.json"
    params.write_text(json.dumps({"effect": "Bloom", "sigma": 0.02}))
    sample = Path(__file__).resolve().parents[1] / "examples" / "data" / "sample_frame.exr"
    output = tmp_path / "out.exr"
    assert main(["apply", str(sample), "--params", str(params), "--layer-only", "-o", str(output)]) == 0
    lines = [line for line in capsys.readouterr().err.splitlines() if "sigma" in line]
    assert lines == ["godrays-jax apply: warning: Bloom.sigma is now named blur_sigma: read as blur_sigma"]
