"""The fit's picture and metrics: labelled panels, a difference map in absolute units, scikit-image's PSNR/SSIM."""

import math

import numpy as np
import pytest
import skimage.metrics

from godrays_jax.pipeline.report import fit_report_image, image_metrics
from godrays_jax.primitives.color import display_map, srgb_encode


def grey(rng, height=36, width=64):
    return np.repeat(rng.uniform(0.0, 3.0, (height, width, 1)), 3, axis=-1)


def hot(picture):
    """Pixels of the heat map's red-to-yellow part (the grey frames and the blue curve have none)."""
    shown = srgb_encode(picture)
    return int(((shown[..., 0] > 0.5) & (shown[..., 2] < 0.3)).sum())


def test_metrics_are_scikit_images_in_display_space(rng):
    target = rng.uniform(0.0, 4.0, (24, 32, 3))
    image = target + rng.normal(0.0, 0.1, target.shape)
    psnr, ssim = image_metrics(image, target)
    shown, truth = display_map(np.maximum(image, 0.0)), display_map(target)
    assert psnr == pytest.approx(10 * math.log10(1.0 / np.mean((shown - truth) ** 2)), rel=1e-9)
    assert psnr == pytest.approx(skimage.metrics.peak_signal_noise_ratio(truth, shown, data_range=1.0), rel=1e-12)
    expected = skimage.metrics.structural_similarity(
        truth, shown, data_range=1.0, channel_axis=-1, gaussian_weights=True, sigma=1.5, use_sample_covariance=False
    )
    assert ssim == pytest.approx(expected, rel=1e-6) and 0.0 < ssim < 1.0  # computed in float32
    assert image_metrics(target, target) == (math.inf, 1.0)
    assert image_metrics(np.concatenate([target, target[..., :1]], -1), target) == (math.inf, 1.0)  # alpha ignored


def test_report_shape_range_and_enlarged_small_frames(rng):
    target = grey(rng)
    picture = fit_report_image(target, target * 1.1, [1e-2, 1e-3])
    assert picture.shape == (2 * (26 + 180) + 46, 2 * 320 + 8, 3)  # 64 px wide: enlarged x5
    assert picture.min() >= 0.0 and picture.max() <= 1.0
    wide = fit_report_image(grey(rng, 10, 400), grey(rng, 10, 400), [1.0])
    assert wide.shape == (2 * (26 + 10) + 46, 2 * 400 + 8, 3)


def test_difference_map_is_in_absolute_units_so_a_near_perfect_fit_stays_dark(rng):
    target = grey(rng)
    near = fit_report_image(target, target + 1e-6, [1e-3, 4.7e-8])
    poor = fit_report_image(target, target * 1.5, [1e-3, 1e-4])
    bar = 10 * (320 - 24)  # the colour bar's pixels, hot in every picture
    assert hot(near) < bar  # a map scaled to its own maximum would show the rings saturated
    assert hot(poor) > bar + 0.2 * 180 * 320


def test_titles_and_tick_labels_are_drawn(rng):
    target = grey(rng)
    picture = srgb_encode(fit_report_image(target, target, [1e-2, 1e-5]))
    title_strip = picture[:26, :320]
    assert (title_strip > 0.8).any()  # lettering on the dark title strip
    left_axis = picture[2 * 26 + 180 :, 328 : 328 + 50]
    assert (left_axis > 0.8).sum() > 50  # the decade labels 1e-5 ... 1e-2
