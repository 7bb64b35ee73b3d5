"""Effects as text: JSON without float32 noise, and a repr that shows the values."""

import json

import jax
import numpy as np

import godrays_jax as gr
from godrays_jax.effects.base import plain_value


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
    assert text.startswith("GodRays(density=0.5, decay=0.95, weight=1.0, exposure=0.15,")
    assert "tint=[1.0, 0.85, 0.6]" in text and "source='disc'" in text and "f32[]" not in text
    assert str(gr.preset("xna_crepuscular")) == text
