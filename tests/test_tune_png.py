"""The tuner's frames as PNG: `encode_png` through OpenImageIO, display encoding against a loop."""


import jax.numpy as jnp
import numpy as np
import OpenImageIO as oiio
import pytest

from godrays_jax.app.tuner import display_encode
from godrays_jax.primitives.images import encode_png



def test_encode_png_round_trips_through_openimageio(tmp_path):
    pixels = np.random.default_rng(1).integers(0, 256, (5, 7, 3), dtype=np.uint8)
    path = tmp_path / "frame.png"
    path.write_bytes(encode_png(pixels))
    decoded = oiio.ImageBuf(str(path)).get_pixels(oiio.UINT8)
    np.testing.assert_array_equal(decoded, pixels)


def test_encode_png_rejects_other_channel_counts():
    with pytest.raises(ValueError, match="pixels must be uint8 of shape"):
        encode_png(np.zeros((2, 2, 4), np.uint8))


def _srgb8_loop(value):
    x = min(max(value, 0.0), 1.0)
    encoded = 12.92 * x if x <= 0.0031308 else 1.055 * x ** (1 / 2.4) - 0.055
    return int(np.floor(encoded * 255.0 + 0.5))


@pytest.mark.parametrize("tonemap", ["reinhard", "clip"])
def test_display_encode_matches_a_loop(tonemap):
    image = np.random.default_rng(2).uniform(-0.5, 20.0, (3, 4, 3)).astype(np.float32)
    image[0, 0] = (0.0, 1e-4, 1e4)
    got = np.asarray(display_encode(jnp.asarray(image), tonemap=tonemap))
    expected = np.zeros_like(got)
    for index in np.ndindex(image.shape):
        x = max(float(image[index]), 0.0)
        expected[index] = _srgb8_loop(x / (1.0 + x) if tonemap == "reinhard" else x)
    assert np.max(np.abs(got.astype(int) - expected.astype(int))) <= 1


def test_display_encode_shows_one_channel_grey_and_rejects_unknown_tonemaps():
    grey = np.asarray(display_encode(jnp.full((2, 2, 1), 0.5), tonemap="clip"))
    assert grey.shape == (2, 2, 3) and np.all(grey == grey[..., :1])
    with pytest.raises(ValueError, match="tonemap"):
        display_encode(jnp.zeros((2, 2, 3)), tonemap="filmic")
