"""The commands on frames as renderers and cameras write them: Blender's planar depth and camera, photographs
without depth, 8-bit outputs dithered."""

import base64
import dataclasses
import json
import math
import os
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
from frames import slow_where

import godrays_jax as gr
from godrays_jax.app.cli import main
from godrays_jax.effects.fields import replace_fields
from godrays_jax.primitives.color import quantize, srgb_encode

DATA = Path(__file__).resolve().parent / "data"
BLENDER = DATA / "blender_planar_z.exr"  # tests/data/blender_planar_z.py: planar Z, a 30 mm lens stamped
BLENDER_FOV = 2 * math.degrees(math.atan(18 / 30))
LIGHT = (40.0, 8.0)


def _flat_frame(depth: np.ndarray, grey: float) -> gr.Buffers:
    """A frame of one grey over `depth` (`inf` is sky), covered where the depth is finite."""
    return gr.Buffers(color=jnp.full((*depth.shape, 3), grey), depth=jnp.asarray(depth),
                      coverage=jnp.asarray(np.isfinite(depth).astype(np.float32)))  # fmt: skip


def _photo(path, height=18, width=32):
    """A photograph: a bright sky with a sun at (16, 5), dark trunks, dark ground; sRGB 8-bit."""
    colour = np.full((height, width, 3), 0.45, np.float32) * np.asarray([1.0, 0.9, 0.75], np.float32)
    colour[3:7, 14:18] = 1.0
    colour[:, 8:10] = colour[:, 22:24] = 0.01
    colour[12:] = 0.02
    gr.write_image(path, colour)
    return path


def test_apply_photo_without_depth(tmp_path):
    photo = _photo(tmp_path / "photo.png")
    output = tmp_path / "rays.png"
    assert main(["apply", str(photo), "--light", "16,5", "--preset", "gpu_gems", "--no-dither", "-o", str(output)]) == 0
    plate = gr.buffers_without_depth(gr.read_image(photo), (16.0, 5.0))
    expected = gr.preset("gpu_gems")(plate, jnp.asarray([16.0, 5.0]))
    written = np.asarray(gr.read_image(output))
    codes = quantize(srgb_encode(np.asarray(expected)), bits=8)
    np.testing.assert_array_equal(np.rint(srgb_encode(written) * 255), codes)
    assert float(np.mean(written[:12, 10:22] - np.asarray(gr.read_image(photo))[:12, 10:22])) > 0.01  # shafts added


def test_apply_photo_with_an_effect_that_needs_depth(tmp_path, capsys):
    photo = _photo(tmp_path / "photo.png")
    assert main(["apply", str(photo), "--light", "16,5", "--preset", "participating_media", "-o", str(tmp_path / "o.png")]) == 1
    line = capsys.readouterr().err.strip()
    assert "\n" not in line and "photo.png has no depth channel and ScatteringFog" in line
    assert "presets that run without depth: " in line and "gpu_gems" in line and "participating_media" not in line
    assert sorted(os.listdir(tmp_path)) == ["photo.png"]


def test_apply_dithers_8_bit_outputs(tmp_path):
    frame = DATA / "colonnade_buffers.exr"
    runs = {}
    for name, extra in (("a.png", []), ("b.png", []), ("round.png", ["--no-dither"]), ("c.jpg", []), ("d.tif", [])):
        assert main(["apply", str(frame), "--light", "160,40", "--preset", "gpu_gems", *extra, "-o", str(tmp_path / name)]) == 0
        runs[name] = np.rint(srgb_encode(np.asarray(gr.read_image(tmp_path / name))) * 255)
    np.testing.assert_array_equal(runs["a.png"], runs["b.png"])  # deterministic
    difference = runs["a.png"] - runs["round.png"]
    assert np.max(np.abs(difference)) <= 2 and np.mean(difference != 0) > 0.2  # grain of about a code
    np.testing.assert_array_equal(runs["d.tif"], runs["a.png"])  # 8-bit TIFF dithered the same way
    assert np.mean(np.abs(runs["c.jpg"] - runs["round.png"])) > 0.1


def test_apply_blender_frame_reads_ray_depth_and_the_frames_camera(tmp_path):
    output = tmp_path / "fog.exr"
    assert main(["apply", str(BLENDER), "--light", "40,8", "--preset", "participating_media", "-o", str(output)]) == 0
    fog = gr.preset("participating_media")
    assert float(fog.fov_x_deg) != pytest.approx(BLENDER_FOV)  # the preset's own differs from the frame's
    frame = gr.read_buffers(BLENDER)  # planar Z converted to ray depth with the header's field of view
    expected = dataclasses.replace(fog, fov_x_deg=BLENDER_FOV)(frame, jnp.asarray(LIGHT))
    np.testing.assert_allclose(np.asarray(gr.read_buffers(output).color), np.asarray(expected), rtol=1e-5, atol=1e-6)
    # --fov-x-deg overrides the header, for the effect and the depth alike.
    output = tmp_path / "fog40.exr"
    assert main(["apply", str(BLENDER), "--light", "40,8", "--preset", "participating_media", "--fov-x-deg", "40",
                 "-o", str(output)]) == 0  # fmt: skip
    expected = dataclasses.replace(fog, fov_x_deg=40.0)(
        gr.read_buffers(BLENDER, fov_x_deg=40.0), jnp.asarray(LIGHT)
    )
    np.testing.assert_allclose(np.asarray(gr.read_buffers(output).color), np.asarray(expected), rtol=1e-5, atol=1e-6)
    # --depth-kind ray reads Blender's Z as stored.
    output = tmp_path / "as_ray.exr"
    assert main(["apply", str(BLENDER), "--light", "40,8", "--preset", "participating_media", "--depth-kind", "ray",
                 "-o", str(output)]) == 0  # fmt: skip
    assert not np.allclose(np.asarray(gr.read_buffers(output).color), np.asarray(gr.read_buffers(tmp_path / "fog.exr").color))


def test_fit_keeps_the_frames_field_of_view(tmp_path, capsys):
    fog = gr.preset("participating_media")
    truth = replace_fields(fog, {"fov_x_deg": BLENDER_FOV, "medium.extinction": 0.05})
    target = tmp_path / "target.exr"
    gr.write_image(target, truth(gr.read_buffers(BLENDER), jnp.asarray(LIGHT)))
    params = tmp_path / "params.json"
    assert main(["fit", str(BLENDER), str(target), "--light", "40,8", "--preset", "participating_media", "--max-steps", "2",
                 "-o", str(params)]) == 0  # fmt: skip
    fitted = json.loads(params.read_text())
    assert fitted["fov_x_deg"] == pytest.approx(BLENDER_FOV, rel=1e-6)
    assert "fov_x_deg =" not in capsys.readouterr().out  # fixed, not fitted


def test_batch_photos_without_depth_dithered_per_frame(tmp_path):
    folder = tmp_path / "in"
    folder.mkdir()
    for number in (1, 2):
        _photo(folder / f"plate.{number:04d}.png")
    out = tmp_path / "out"
    assert main(["batch", str(folder / "plate.####.png"), "-o", str(out), "--light", "16,5", "--preset", "gpu_gems", "-q"]) == 0
    assert main(["batch", str(folder / "plate.####.png"), "-o", str(tmp_path / "round"), "--light", "16,5",
                 "--preset", "gpu_gems", "--no-dither", "-q"]) == 0  # fmt: skip
    codes = {p.name: np.rint(srgb_encode(np.asarray(gr.read_image(p))) * 255) for p in sorted(out.iterdir())}
    rounded = np.rint(srgb_encode(np.asarray(gr.read_image(tmp_path / "round" / "plate.0001.png"))) * 255)
    first, second = codes["plate.0001.png"], codes["plate.0002.png"]
    assert np.any(first != second)  # the same picture, each frame's own grain
    assert np.max(np.abs(first - rounded)) <= 2 and np.any(first != rounded)
    plate = gr.buffers_without_depth(gr.read_image(folder / "plate.0001.png"), (16.0, 5.0))
    expected = gr.preset("gpu_gems")(plate, jnp.asarray([16.0, 5.0]))
    np.testing.assert_array_equal(rounded, quantize(srgb_encode(np.asarray(expected)), bits=8))


def test_batch_frames_without_depth_and_a_medium_fail_each_frame(tmp_path, capsys):
    folder = tmp_path / "in"
    folder.mkdir()
    _photo(folder / "plate.0001.png")
    status = main(["batch", str(folder / "plate.####.png"), "-o", str(tmp_path / "out"), "--light", "16,5",
                   "--preset", "participating_media", "-q"])  # fmt: skip
    assert status == 1
    assert "has no depth channel and ScatteringFog measures distance in it" in capsys.readouterr().err


@pytest.mark.parametrize("command", slow_where(["apply", "batch"], {"apply"}))
def test_vbex_presets_take_the_frames_field_of_view(tmp_path, command):
    """The VBex sun spot is drawn with the frame's field of view (`godrays:fov_x_deg`), not the preset's 50 degrees."""
    from godrays_jax.primitives.camera_metadata import FOV_X_ATTR

    height, width = 18, 32
    depth = np.full((height, width), np.inf, np.float32)
    depth[12:] = 4.0
    frame = _flat_frame(depth, 0.1)
    folder = tmp_path / "in"
    folder.mkdir()
    path = folder / "frame.0001.exr"
    gr.write_buffers(path, frame, light_xy=(20.0, 6.0), metadata={FOV_X_ATTR: 80.0})
    if command == "apply":
        output = tmp_path / "out.exr"
        assert main(["apply", str(path), "--preset", "vbex_sun_spot", "-o", str(output)]) == 0
    else:
        assert main(["batch", str(path), "-o", str(tmp_path / "out"), "--preset", "vbex_sun_spot", "-q"]) == 0
        output = tmp_path / "out" / path.name
    spot = gr.preset("vbex_sun_spot")
    expected = dataclasses.replace(spot, fov_x_deg=80.0)(gr.read_buffers(path), jnp.asarray([20.0, 6.0]))
    written = np.asarray(gr.read_buffers(output).color)
    # The command's compiled program and the eager effect round differently; the spot's twentieth power turns that
    # into about 1e-4 of its value. The preset's own 50 degrees differ by far more (the check below).
    np.testing.assert_allclose(written, np.asarray(expected), rtol=1e-3, atol=1e-6)
    assert not np.allclose(written, np.asarray(spot(gr.read_buffers(path), jnp.asarray([20.0, 6.0]))), atol=1e-4)


def test_fit_reads_the_lights_distance(tmp_path, capsys):
    """`fit` renders with the light's distance the frame stores (`godrays:light_depth`), as `apply` does."""
    from godrays_jax.pipeline.compiled import render_compiled
    from godrays_jax.pipeline.fit import fit

    height, width = 18, 32
    depth = np.full((height, width), np.inf, np.float32)
    depth[10:, :] = 2.0
    depth[:, 20:23] = 0.2  # a post nearer than the light: the XNA depth test blanks it
    frame = _flat_frame(depth, 0.2)
    effect = gr.preset("xna_crepuscular")
    light = jnp.asarray([21.0, 5.0])
    target = render_compiled(effect, frame, light, True, 0.4)
    assert float(jnp.max(jnp.abs(target - render_compiled(effect, frame, light, True)))) > 1e-3
    result = fit(effect, frame, light, target, fixed=[n for n in gr.parameter_bounds(effect) if n != "exposure"],
                 max_steps=1, light_depth=0.4)  # fmt: skip
    assert result.loss_before < 1e-10
    with pytest.raises(ValueError, match="light_depth"):
        fit(effect, frame, light, target, max_steps=0, light_depth=[0.4, 1.0])
    path = tmp_path / "frame.exr"
    gr.write_buffers(path, frame, light_xy=(21.0, 5.0), metadata={"godrays:light_depth": 0.4})
    gr.write_image(tmp_path / "target.exr", target)
    assert main(["fit", str(path), str(tmp_path / "target.exr"), "--preset", "xna_crepuscular", "--fixed",
                 ",".join(n for n in gr.parameter_bounds(effect) if n != "exposure"), "--max-steps", "1",
                 "-o", str(tmp_path / "params.json")]) == 0  # fmt: skip
    out = capsys.readouterr().out
    assert "loss before 0," in out


def test_tuner_renders_with_the_lights_distance(tmp_path):
    import OpenImageIO as oiio

    from godrays_jax.app.tuner import TONEMAPS, Tuner, display_encode

    height, width = 18, 32
    depth = np.full((height, width), np.inf, np.float32)
    depth[:, 20:23] = 0.2
    frame = _flat_frame(depth, 0.2)
    effect = gr.preset("xna_crepuscular")
    light = jnp.asarray([21.0, 5.0])
    tonemap = TONEMAPS[0]

    def shown(light_depth):
        """The pixels of the full-resolution view a tuner started with the light at `light_depth` sends the page."""
        tuner = Tuner(frame, (21.0, 5.0), effect=effect, light_depth=light_depth)
        try:
            answer = tuner.render({"quality": "full", "view": "after", "tonemap": tonemap})
        finally:
            tuner.close()
        path = tmp_path / "view.png"
        path.write_bytes(base64.b64decode(answer["image"].removeprefix("data:image/png;base64,")))
        return oiio.ImageBuf(str(path)).get_pixels(oiio.UINT8)

    view = shown(0.4)
    expected = np.asarray(display_encode(effect(frame, light, light_depth=0.4), tonemap=tonemap))
    np.testing.assert_array_equal(view, expected)
    assert np.any(view != shown(math.inf))


def test_targets_read_a_renders_colour_layer(tmp_path):
    """A multilayer reference: its Combined layer is the colour, not whichever pass comes first in the file."""
    import OpenImageIO as oiio

    from godrays_jax.app.options import read_target

    names = ("ViewLayer.AO.R", "ViewLayer.AO.G", "ViewLayer.AO.B", "ViewLayer.Combined.R", "ViewLayer.Combined.G",
             "ViewLayer.Combined.B", "ViewLayer.Combined.A")  # fmt: skip
    pixels = np.zeros((4, 6, 7), np.float32)
    pixels[..., :3] = 0.9
    pixels[..., 3:6] = np.asarray([0.1, 0.2, 0.3])
    pixels[..., 6] = 1.0
    spec = oiio.ImageSpec(6, 4, 7, oiio.FLOAT)
    spec.channelnames = names
    path = tmp_path / "reference.exr"
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), spec)
    out.write_image(pixels)
    out.close()
    np.testing.assert_allclose(np.asarray(read_target(str(path))), np.broadcast_to([0.1, 0.2, 0.3], (4, 6, 3)))


def test_batch_says_when_frames_store_other_light_distances(tmp_path, capsys):
    height, width = 9, 16
    depth = np.full((height, width), np.inf, np.float32)
    depth[6:] = 3.0
    frame = _flat_frame(depth, 0.2)
    folder = tmp_path / "in"
    folder.mkdir()
    for number, distance in ((1, 10.0), (2, 10.0), (3, 12.5)):
        gr.write_buffers(folder / f"f.{number:04d}.exr", frame, light_xy=(8.0, 2.0), metadata={"godrays:light_depth": distance})
    pattern = str(folder / "f.####.exr")
    assert main(["batch", pattern, "-o", str(tmp_path / "out"), "--preset", "gpu_gems", "-q"]) == 0
    err = capsys.readouterr().err
    assert "f.0003.exr stores the light's distance 12.5, the first frame 10" in err
    assert main(["batch", pattern, "-o", str(tmp_path / "again"), "--preset", "gpu_gems", "-q", "--light-depth", "11"]) == 0
    assert "light's distance" not in capsys.readouterr().err


def test_batch_adds_the_same_several_lights_to_every_frame(tmp_path, capsys):
    """`batch --light 'A;B' --light-tint ...`: every frame is `lit_by` of those lights."""
    height, width = 9, 16
    depth = np.full((height, width), np.inf, np.float32)
    depth[6:] = 3.0
    depth[:, 7:9] = 2.0
    folder = tmp_path / "in"
    folder.mkdir()
    frames = [_flat_frame(depth, grey) for grey in (0.2, 0.3)]
    for number, frame in enumerate(frames, 1):
        gr.write_buffers(folder / f"f.{number:04d}.exr", frame, light_xy=(8.0, 2.0))
    pattern = str(folder / "f.####.exr")
    arguments = ["batch", pattern, "-o", str(tmp_path / "out"), "--preset", "gpu_gems", "-q",
                 "--light", "8,2;3,4,behind", "--light-tint", "1,0.5,0.25;2"]  # fmt: skip
    assert main([*arguments, "--layer-only"]) != 0  # one line, as apply says it
    assert "--layer-only draws one light as the effect has it" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
    multiply = tmp_path / "multiply.json"
    gr.save_effect(multiply, dataclasses.replace(gr.preset("gpu_gems"), blend_mode="multiply"))
    assert main([*arguments[:4], "--params", str(multiply), *arguments[6:]]) == 1  # refused before any frame
    assert capsys.readouterr().err.strip().endswith("several or tinted lights take effects blended 'add' or 'screen'")
    assert not (tmp_path / "out").exists()
    assert main([*arguments, "--dry-run"]) == 0
    assert "every frame also lit by the light at (3, 4), behind the camera, distance inf" in capsys.readouterr().out
    assert main(arguments) == 0
    effect = gr.preset("gpu_gems")
    lights = [gr.Light(jnp.asarray([8.0, 2.0]), tint=(1.0, 0.5, 0.25)),
              gr.Light(jnp.asarray([3.0, 4.0]), in_front=False, tint=(2.0, 2.0, 2.0))]  # fmt: skip
    for number, frame in enumerate(frames, 1):
        written = np.asarray(gr.read_buffers(tmp_path / "out" / f"f.{number:04d}.exr").color)
        expected = np.asarray(gr.lit_by(effect, gr.read_buffers(folder / f"f.{number:04d}.exr"), lights))
        np.testing.assert_allclose(written, expected, rtol=1e-3, atol=1e-5)
    assert not np.allclose(expected, np.asarray(effect(frames[-1], jnp.asarray([8.0, 2.0]))), atol=1e-3)
