"""The tuner's page end to end in headless Chromium."""

import json
import shutil

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import OpenImageIO as oiio
import pytest

import godrays_jax as gr
import godrays_jax.app.tuner as tuner_module
from godrays_jax.app.server import TuneServer
from godrays_jax.app.tuner import Tuner

from tune_support import SAMPLE, browser, fit_until_cancelled, small_effect, small_frame  # noqa: F401, F811 (browser is a fixture)


SCREENSHOT_COPY = "/tmp/godrays_tune_screenshot.png"


@pytest.mark.slow
def test_page_end_to_end_in_chromium(browser, tmp_path):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    frame = gr.read_buffers(SAMPLE)
    light, in_front = gr.read_light(SAMPLE)
    save_path = tmp_path / "tuned.json"
    tuner = Tuner(frame, light, effect=gr.preset("xna_crepuscular"), light_in_front=in_front, save_path=save_path,
                  max_preview_pixels=14_400)  # fmt: skip
    with TuneServer(tuner) as running:
        running.warm_up()
        browser.get(running.url)
        wait = WebDriverWait(browser, 120)
        wait.until(lambda d: d.execute_script("return window.tuneStats.length") >= 1)
        first = browser.find_element(By.ID, "after").get_attribute("src")
        start_exposure = browser.execute_script("return params.exposure")

        slider = browser.find_element(By.CSS_SELECTOR, "input[aria-label=exposure]")
        ActionChains(browser).click_and_hold(slider).move_by_offset(30, 0).release().perform()
        wait.until(lambda d: d.execute_script(
            "return window.tuneStats.some((s, i) => i > 0 && s.quality === 'full')"))  # fmt: skip
        assert browser.find_element(By.ID, "after").get_attribute("src") != first
        exposure = browser.execute_script("return params.exposure")
        assert exposure > start_exposure  # dragged right

        image = browser.find_element(By.ID, "frame")
        ActionChains(browser).move_to_element_with_offset(image, -image.size["width"] // 4, 0).click().perform()
        wait.until(lambda d: d.execute_script("return light[0]") < frame.width / 2)
        wait.until(lambda d: d.execute_script("return window.tuneStats.filter((s) => s.quality === 'full').length") >= 3)

        browser.find_element(By.ID, "save").click()
        wait.until(lambda d: "saved" in d.find_element(By.ID, "save-status").text)
        saved = json.loads(save_path.read_text())
        assert saved["effect"] == "GodRays" and saved["exposure"] == pytest.approx(exposure, rel=1e-6)
        assert saved["max_samples"] == 128 and saved["use_bright_pass"] is True
        assert browser.find_element(By.ID, "error").text == ""

        screenshot = tmp_path / "tune_screenshot.png"
        browser.save_screenshot(str(screenshot))
        shutil.copy(screenshot, SCREENSHOT_COPY)
        stats = browser.execute_script("return window.tuneStats")
        console = [entry["message"] for entry in browser.get_log("browser")]
    assert not [line for line in console if "Content Security Policy" in line or "403" in line], console
    assert oiio.ImageBuf(str(screenshot)).spec().width > 0
    print("browser timings:", json.dumps(stats))


@pytest.mark.slow
def test_page_fits_and_cancels_in_chromium(browser, monkeypatch):
    """The page starts a fit, follows it to its result, and cancels one (the button becomes "cancel fit")."""
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    frame = small_frame()
    truth = gr.GodRays(num_samples=8.0, max_samples=8, flare_size=6.0, units="px", exposure=1.2)
    target = eqx.filter_jit(truth)(frame, jnp.asarray([32.0, 6.0]))
    tuner = Tuner(frame, (32.0, 6.0), effect=small_effect(), target=target, max_preview_pixels=300, fit_steps=3)
    with TuneServer(tuner) as running:
        browser.get(running.url)
        wait = WebDriverWait(browser, 300)
        wait.until(lambda d: d.execute_script("return window.tuneStats.length") >= 1)
        button = browser.find_element(By.ID, "fit")
        button.click()
        wait.until(lambda d: "fitted" in d.find_element(By.ID, "fit-status").text)
        assert button.text == "fit to target" and browser.find_element(By.ID, "error").text == ""
        assert browser.execute_script("return params.exposure") == pytest.approx(tuner.effect.exposure)

        monkeypatch.setattr(tuner_module, "fit", fit_until_cancelled(tuner))
        button.click()
        wait.until(lambda d: d.find_element(By.ID, "fit").text == "cancel fit")
        wait.until(lambda d: "step" in d.find_element(By.ID, "fit-status").text)
        button.click()
        wait.until(lambda d: "cancelled" in d.find_element(By.ID, "fit-status").text)
        assert button.text == "fit to target" and not tuner.fit_progress()["running"]


def test_page_drags_each_of_several_lights_in_chromium(browser):
    """A frame of several lights: a marker each, and a press moves the light nearest to it, which the frame is then
    rendered with (the other where it was)."""
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    frame = small_frame()
    lamp = gr.Light(np.asarray([10.0, 4.0], np.float32))
    tuner = Tuner(frame, (50.0, 6.0), effect=small_effect(), other_lights=[lamp], max_preview_pixels=300)
    with TuneServer(tuner) as running:
        browser.get(running.url)
        wait = WebDriverWait(browser, 300)
        wait.until(lambda d: d.execute_script("return window.tuneStats.length") >= 1)
        assert len(browser.find_elements(By.CLASS_NAME, "other-marker")) == 1
        image = browser.find_element(By.ID, "frame")
        width, height = image.size["width"], image.size["height"]
        # (12, 20) in the frame's pixels, nearer the lamp at (10, 4) than the light at (50, 6); offsets from the centre.
        at = (round(12 / frame.width * width - width / 2), round(20 / frame.height * height - height / 2))
        ActionChains(browser).move_to_element_with_offset(image, *at).click().perform()
        wait.until(lambda d: d.execute_script("return others[0][1]") > 10)
        assert browser.execute_script("return light") == pytest.approx([50.0, 6.0])
        full = "return window.tuneStats.filter((s) => s.quality === 'full').length"
        wait.until(lambda d: d.execute_script(full) >= 2)
        assert browser.find_element(By.ID, "error").text == ""
