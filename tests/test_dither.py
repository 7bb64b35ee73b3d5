"""8-bit outputs without banding: triangular dither of one code before rounding."""

import numpy as np
import pytest

from godrays_jax.primitives.color import quantize


def test_without_seed_rounds(rng):
    values = rng.uniform(-0.1, 1.1, (5, 7, 3))
    np.testing.assert_array_equal(quantize(values, bits=8), np.rint(np.clip(values, 0, 1) * 255).astype(np.uint8))
    assert quantize(values, bits=16).dtype == np.uint16
    with pytest.raises(ValueError, match="bits"):
        quantize(values, bits=10)


def test_deterministic_per_seed(rng):
    values = rng.uniform(0, 1, (16, 16, 3))
    first = quantize(values, bits=8, dither_seed=1001)
    np.testing.assert_array_equal(first, quantize(values, bits=8, dither_seed=1001))
    assert np.any(first != quantize(values, bits=8, dither_seed=1002))


def test_error_within_one_and_a_half_codes(rng):
    values = rng.uniform(0, 1, (64, 64))
    codes = quantize(values, bits=8, dither_seed=3).astype(np.float64)
    assert np.max(np.abs(codes - values * 255)) <= 1.5


def test_mean_is_the_true_value():
    """A flat area between two codes: rounding puts every pixel on one code, the dither's mean is the value."""
    value = 10.3 / 255
    flat = np.full((200, 200), value)
    assert np.mean(quantize(flat, bits=8)) == 10.0
    assert np.mean(quantize(flat, bits=8, dither_seed=7)) == pytest.approx(10.3, abs=0.02)


def test_black_and_white_stay_clean():
    image = np.array([[0.0, 1.0, -0.5, 2.0]] * 50)
    np.testing.assert_array_equal(quantize(image, bits=8, dither_seed=0), np.array([[0, 255, 0, 255]] * 50, np.uint8))


def test_no_bands_on_a_smooth_ramp():
    """A slow ramp of 4 codes over 512 pixels: averaged over columns of 8 pixels, the dithered codes follow it."""
    ramp = np.broadcast_to(np.linspace(20.0, 24.0, 512) / 255, (64, 512))
    truth = ramp * 255

    def band_error(codes):
        columns = (codes - truth).reshape(64, 64, 8).mean(axis=(0, 2))
        return float(np.max(np.abs(columns)))

    assert band_error(quantize(ramp, bits=8)) > 0.4
    assert band_error(quantize(ramp, bits=8, dither_seed=11)) < 0.1
