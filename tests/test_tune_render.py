"""The tuner's renders: preview resolution and sizes against block loops, and the coalescing render queue."""

import threading

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import godrays_jax as gr
from godrays_jax.app.tuner import RenderQueue, Superseded, preview_factor
from godrays_jax.pipeline.reduced import downsample_buffers, pixel_fields, scale_pixel_fields

from tune_support import next_waiting, small_frame


@pytest.mark.parametrize(("height", "width", "max_pixels", "factor"), [(540, 960, 40_000, 4), (36, 64, 40_000, 1),
                                                                       (180, 320, 14_400, 2), (7, 7, 1, 7)])  # fmt: skip
def test_preview_factor(height, width, max_pixels, factor):
    assert preview_factor(height, width, max_pixels=max_pixels) == factor
    assert -(-height // factor) * -(-width // factor) <= max_pixels


def test_downsample_buffers_matches_block_loops():
    frame = small_frame(9, 14)
    low = downsample_buffers(frame, 4)
    color, depth, coverage = (np.asarray(a) for a in (frame.color, frame.depth, frame.coverage))
    assert low.color.shape == (3, 4, 3)
    for j in range(3):
        for i in range(4):
            rows = [min(r, 8) for r in range(4 * j, 4 * j + 4)]  # ragged blocks repeat the edge
            cols = [min(c, 13) for c in range(4 * i, 4 * i + 4)]
            block = np.ix_(rows, cols)
            np.testing.assert_allclose(low.color[j, i], color[block].mean(axis=(0, 1)), rtol=1e-6)
            np.testing.assert_allclose(low.coverage[j, i], coverage[block].mean(), rtol=1e-6)
            assert low.depth[j, i] == depth[block].min()
    assert downsample_buffers(frame, 1) is frame


def test_scale_pixel_fields_scales_only_pixel_sizes():
    framed = gr.preset("kbengine_flares")
    assert scale_pixel_fields(framed, 0.25) is framed  # frame units: the same picture at any resolution
    effect = gr.FlareOuts(units="px", flare_size=40.0, blur_sigma=2.0, blur_reach=6.0)
    scaled = scale_pixel_fields(effect, 0.25)
    assert set(pixel_fields(effect)) == {"flare_size", "blur_sigma", "blur_reach"}
    assert scaled.blur_reach == 1.5
    for name in gr.parameter_bounds(effect):
        factor = 0.25 if name in pixel_fields(effect) else 1.0
        np.testing.assert_allclose(getattr(scaled, name), np.asarray(getattr(effect, name)) * factor)


def test_preview_render_approximates_the_downsampled_full_render():
    """The preview scales the light and pixel sizes with the resolution, so it looks like the full frame, smaller."""
    frame = small_frame(48, 80)
    effect = gr.GodRays(num_samples=8.0, max_samples=8, flare_size=12.0, units="px", flare_shape="cone", exposure=0.5)
    light = jnp.asarray([40.0, 8.0])
    layer = eqx.filter_jit(lambda effect, frame, light: effect.layer(frame, light))
    full = gr.downsample_box(layer(effect, frame, light), 4)
    preview = layer(scale_pixel_fields(effect, 0.25), downsample_buffers(frame, 4), light / 4)
    unscaled = layer(effect, downsample_buffers(frame, 4), light / 4)
    error = float(jnp.mean(jnp.abs(preview - full)))
    assert preview.shape == (12, 20, 3)
    assert error < 0.1 * float(jnp.mean(jnp.abs(full)))
    assert error < 0.1 * float(jnp.mean(jnp.abs(unscaled - full)))  # not scaling would be visibly wrong


def test_render_queue_coalesces_waiting_requests():
    queue = RenderQueue()
    started, release = threading.Event(), threading.Event()
    ran, answers = [], {}

    def job(name, block=False):
        def run():
            ran.append(name)
            if block:
                started.set()
                release.wait(10)
            return name

        return run

    def submit(name, **kwargs):
        try:
            answers[name] = queue.submit(job(name, **kwargs))
        except Superseded as error:
            answers[name] = error

    threads = [threading.Thread(target=submit, args=("first",), kwargs={"block": True})]
    threads[0].start()
    assert started.wait(10)
    waiting = None
    for name in ("second", "third", "fourth"):
        threads.append(threading.Thread(target=submit, args=(name,)))
        threads[-1].start()
        waiting = next_waiting(queue, waiting)  # each arrives while `first` is still rendering
    release.set()
    for thread in threads:
        thread.join(10)
    queue.close()
    assert ran == ["first", "fourth"]
    assert answers["first"] == "first" and answers["fourth"] == "fourth"
    assert isinstance(answers["second"], Superseded) and isinstance(answers["third"], Superseded)


def test_render_queue_hands_errors_back_and_keeps_working():
    queue = RenderQueue()
    with pytest.raises(ZeroDivisionError):
        queue.submit(lambda: 1 / 0)
    assert queue.submit(lambda: 42) == 42
    queue.close()
