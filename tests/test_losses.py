"""Losses: against slow NumPy loops and scikit-image's SSIM; jit, vmap, float64 gradients, degenerate inputs."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads
from skimage.metrics import structural_similarity

from godrays_jax.kernels.losses import LOSSES, charbonnier_loss, l1_loss, mse_loss, ssim, ssim_loss, to_space


def _images(seed=0, shape=(20, 24, 3), scale=4.0):
    rng = np.random.default_rng(seed)
    return (rng.random(shape) * scale).astype(np.float32), (rng.random(shape) * scale).astype(np.float32)


def _display_loop(image):
    out = np.empty_like(image, dtype=np.float64)
    for index in np.ndindex(image.shape):
        value = float(image[index])
        out[index] = value / (1.0 + abs(value))
    return out


def test_display_space_is_reinhard():
    image, _ = _images()
    np.testing.assert_allclose(to_space(jnp.asarray(image), "display"), _display_loop(image), rtol=1e-6)
    np.testing.assert_array_equal(to_space(jnp.asarray(image), "linear"), image)


@pytest.mark.parametrize("space", ["display", "linear"])
def test_pixel_losses_match_numpy_loops(space):
    image, target = _images()
    a, b = (_display_loop(image), _display_loop(target)) if space == "display" else (image, target)
    squared = absolute = charbonnier = 0.0
    for index in np.ndindex(a.shape):
        d = float(a[index]) - float(b[index])
        squared += d * d
        absolute += abs(d)
        charbonnier += np.sqrt(d * d + 0.01**2) - 0.01
    n = a.size
    np.testing.assert_allclose(mse_loss(image, target, space=space), squared / n, rtol=1e-5)
    np.testing.assert_allclose(l1_loss(image, target, space=space), absolute / n, rtol=1e-5)
    np.testing.assert_allclose(charbonnier_loss(image, target, space=space, epsilon=0.01), charbonnier / n, rtol=1e-4)


@pytest.mark.parametrize("space", ["display", "linear"])
def test_ssim_matches_skimage(space):
    image, target = _images(1, (23, 31, 3))
    target = 0.6 * image + 0.4 * target  # similar but not equal, SSIM well inside (0, 1)
    a, b = (_display_loop(image), _display_loop(target)) if space == "display" else (image, target)
    data_range = 1.0 if space == "display" else 4.0
    expected = structural_similarity(
        a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=data_range, channel_axis=-1
    )
    assert 0.2 < expected < 0.95
    np.testing.assert_allclose(ssim(image, target, space=space, data_range=data_range), expected, rtol=1e-5)


def test_ssim_loss_is_zero_for_identical_and_ranks_similarity():
    image, noise = _images(2)
    assert abs(float(ssim_loss(image, image))) < 1e-6
    closer = ssim_loss(image + 0.1 * noise, image)
    farther = ssim_loss(image + noise, image)
    assert 0 < closer < farther


def test_losses_jit_and_vmap():
    image, target = _images(3)
    batch_image = np.stack([image, target])
    batch_target = np.stack([target, image])
    for name, loss in LOSSES.items():
        eager = loss(image, target)  # eager: op by op
        np.testing.assert_allclose(jax.jit(loss)(image, target), eager, rtol=1e-5, err_msg=name)
        batched = jax.vmap(loss)(batch_image, batch_target)
        np.testing.assert_allclose(batched[0], eager, rtol=1e-5, err_msg=name)


@pytest.mark.parametrize(("name", "space"), [("mse", "linear"), ("charbonnier", "display"), ("ssim", "display")])
def test_gradients_float64(name, space):
    with jax.enable_x64(True):
        rng = np.random.default_rng(4)
        image = jnp.asarray(rng.random((13, 14, 2)) * 3 + 0.1)
        target = jnp.asarray(rng.random((13, 14, 2)) * 3 + 0.1)
        check_grads(jax.jit(lambda x: LOSSES[name](x, target, space=space)), (image,), order=1, modes=["fwd", "rev"], atol=1e-4, rtol=1e-4)


def test_degenerate_inputs_give_finite_values_and_gradients():
    black = jnp.zeros((12, 12, 3))
    for name, loss in LOSSES.items():
        value_and_grad = jax.jit(jax.value_and_grad(loss))
        for image, target in [(black, black), (black + 5.0, black + 5.0), (black, black + 1e4)]:
            value, gradient = value_and_grad(image, target)
            assert np.isfinite(value) and np.all(np.isfinite(gradient)), name


def test_errors_name_the_argument():
    image, target = _images()
    with pytest.raises(ValueError, match="space"):
        mse_loss(image, target, space="log")
    with pytest.raises(ValueError, match="target"):
        mse_loss(image, target[:-1])
    with pytest.raises(ValueError, match="epsilon"):
        charbonnier_loss(image, target, epsilon=0.0)
    with pytest.raises(ValueError, match="11x11"):
        ssim(image[:8], target[:8])
