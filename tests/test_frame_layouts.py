"""Frames as Blender, Nuke and plain renderers write them, through `apply` and `batch`: channels found without
flags, every channel, format and attribute kept in the output, the sky threshold, and the warnings."""

from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest

import godrays_jax as gr
from godrays_jax.app.cli import main

SAMPLE = Path(__file__).resolve().parents[1] / "examples" / "data" / "sample_frame.exr"
H, W = 12, 20
LIGHT = (10.5, 2.5)


def scene(sky_value=np.inf):
    """Colour with a bright sky band on top, opaque ground below (depth 4), the sky's depth `sky_value`."""
    color = np.full((H, W, 3), 0.1, np.float32)
    color[:5] = (2.0, 1.5, 1.0)
    depth = np.full((H, W), 4.0, np.float32)
    depth[:5] = sky_value
    alpha = np.isfinite(depth).astype(np.float32) if np.isinf(sky_value) else (depth < sky_value).astype(np.float32)
    return color, depth, alpha


def write_layout(path, channels, formats=None, attributes=()):
    """An EXR with these channels (name -> (H, W) array) in file order, per-channel formats, and attributes."""
    names = tuple(channels)
    pixels = np.ascontiguousarray(np.stack([channels[n] for n in names], -1).astype(np.float32))
    spec = oiio.ImageSpec(W, H, len(names), oiio.FLOAT)
    spec.channelnames = names
    if formats:
        spec.channelformats = tuple(formats.get(n, oiio.TypeFloat) for n in names)
    spec.attribute("compression", "piz")
    for name, kind, value in attributes:
        spec.attribute(name, kind, value)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(pixels) and out.close()
    return path


def blender_multilayer(path, *, layers=("ViewLayer",)):
    color, depth, alpha = scene(1e10)  # Blender's background depth
    channels = {}
    for index, layer in enumerate(layers):
        channels |= {
            f"{layer}.Combined.R": color[..., 0] * (index + 1), f"{layer}.Combined.G": color[..., 1],
            f"{layer}.Combined.B": color[..., 2], f"{layer}.Combined.A": alpha,
            f"{layer}.Depth.Z": depth + index, f"{layer}.Normal.X": np.full((H, W), 0.25),
        }  # fmt: skip
    formats = {name: oiio.TypeHalf for name in channels if ".Combined." in name or ".Normal." in name}
    light = ("godrays:light_px", oiio.TypeFloat2, LIGHT)
    return write_layout(path, channels, formats, [light, ("Software", oiio.TypeString, "Blender 4.2")])


def read_all(path):
    inp = oiio.ImageInput.open(str(path))
    spec = inp.spec()
    pixels = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT).reshape(H, W, spec.nchannels)
    inp.close()
    return spec, dict(zip(spec.channelnames, np.moveaxis(pixels, -1, 0)))


def params(tmp_path):
    path = tmp_path / "params.json"
    gr.save_effect(path, gr.GodRays(num_samples=4.0, max_samples=4, flare_size=6.0, units="px", exposure=1.0))
    return str(path)


def test_blender_multilayer_through_apply_keeps_every_channel_format_and_attribute(tmp_path, capsys):
    frame = blender_multilayer(tmp_path / "blender.exr")
    out = tmp_path / "out.exr"
    assert main(["apply", str(frame), "--params", params(tmp_path), "-o", str(out)]) == 0
    assert capsys.readouterr().err == ""  # the 1e10 background is sky: no warning
    in_spec, before = read_all(frame)
    out_spec, after = read_all(out)
    assert out_spec.channelnames == in_spec.channelnames
    assert [str(f) for f in out_spec.channelformats] == [str(f) for f in in_spec.channelformats]
    assert out_spec.getattribute("Software") == "Blender 4.2"
    assert tuple(out_spec.getattribute("godrays:light_px")) == LIGHT
    for name in ("ViewLayer.Combined.A", "ViewLayer.Depth.Z", "ViewLayer.Normal.X"):
        np.testing.assert_array_equal(after[name], before[name])
    buffers = gr.read_buffers(frame)
    assert np.isposinf(np.asarray(buffers.depth)[:5]).all() and float(buffers.coverage[0, 0]) == 0.0
    expected = gr.load_effect(tmp_path / "params.json")(buffers, np.asarray(LIGHT, np.float32))
    colour = np.stack([after[f"ViewLayer.Combined.{c}"] for c in "RGB"], -1)
    np.testing.assert_allclose(colour, expected, rtol=2e-3, atol=1e-3)  # half storage
    assert float(np.abs(colour - np.stack([before[f"ViewLayer.Combined.{c}"] for c in "RGB"], -1)).max()) > 0.05


def test_several_view_layers_need_a_choice_and_the_overrides_make_it(tmp_path, capsys):
    frame = blender_multilayer(tmp_path / "two.exr", layers=("Fore", "Back"))
    out = tmp_path / "out.exr"
    assert main(["apply", str(frame), "--params", params(tmp_path), "-o", str(out)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "several colour layers (" in err and "--color-layer" in err
    assert "Back.Combined, Fore.Combined" in err  # OpenImageIO lists an EXR's layers alphabetically
    assert not out.exists()
    assert main(["apply", str(frame), "--params", params(tmp_path), "--color-layer", "Back.Combined", "-o", str(out)]) == 0
    _, after = read_all(out)
    _, before = read_all(frame)
    np.testing.assert_array_equal(after["Fore.Combined.R"], before["Fore.Combined.R"])
    assert not np.array_equal(after["Back.Combined.R"], before["Back.Combined.R"])
    back = gr.read_buffers(frame, color_layer="Back.Combined")
    np.testing.assert_array_equal(back.depth[6:], 5.0)  # Back.Depth.Z, beside its colour layer
    chosen = gr.read_buffers(frame, color_layer="Back.Combined", depth_channel="Fore.Depth.Z")
    np.testing.assert_array_equal(chosen.depth[6:], 4.0)
    with pytest.raises(ValueError, match=r"no colour layer 'Side'.*Back\.Combined, Fore\.Combined"):
        gr.read_buffers(frame, color_layer="Side")


def test_nuke_layout_through_batch_keeps_every_channel(tmp_path, capsys):
    color, depth, alpha = scene()
    (tmp_path / "in").mkdir()
    for number in (1001, 1002):
        channels = {"R": color[..., 0], "G": color[..., 1], "B": color[..., 2], "A": alpha, "depth.Z": depth,
                    "other.red": np.full((H, W), 0.5)}  # fmt: skip
        light = ("godrays:light_px", oiio.TypeFloat2, LIGHT)
        write_layout(tmp_path / "in" / f"comp.{number:04d}.exr", channels, {"R": oiio.TypeHalf}, [light])
    status = main(["batch", str(tmp_path / "in" / "comp.$F4.exr"), "-o", str(tmp_path / "out"),
                   "--params", params(tmp_path), "-q"])  # fmt: skip
    assert status == 0, capsys.readouterr().err
    for number in (1001, 1002):
        spec, after = read_all(tmp_path / "out" / f"comp.{number:04d}.exr")
        assert spec.channelnames == ("R", "G", "B", "A", "depth.Z", "other.red")
        assert str(spec.channelformats[0]) == "half" and str(spec.channelformats[1]) == "float"
        np.testing.assert_array_equal(after["depth.Z"], depth)
        assert float(after["R"][0].max()) > 2.0


def test_far_plane_without_alpha_warns_once_and_sky_depth_finds_the_sky(tmp_path, capsys):
    color, depth, _ = scene(1000.0)  # a renderer writing its camera's far plane, and no alpha
    frame = write_layout(tmp_path / "far.exr", {"R": color[..., 0], "G": color[..., 1], "B": color[..., 2], "Z": depth})
    out = tmp_path / "out.exr"
    base = ["apply", str(frame), "--params", params(tmp_path), "--light", "10.5,2.5", "-o", str(out)]
    assert main(base) == 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "warning" in err and "no sky pixel" in err and "--sky-depth" in err
    np.testing.assert_allclose(gr.read_image(out)[..., :3], color, atol=1e-6)  # no sky: nothing shines
    assert main([*base, "--sky-depth", "1000"]) == 0
    assert capsys.readouterr().err == ""
    assert float(np.abs(np.asarray(gr.read_image(out))[..., :3] - color).max()) > 0.05
    assert main(["batch", str(frame), "-o", str(tmp_path / "b"), "--params", params(tmp_path),
                 "--light", "10.5,2.5", "-q"]) == 0  # fmt: skip
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "1 frame(s) (first:" in err and "no sky pixel" in err


def test_half_depth_maximum_is_sky_and_bad_thresholds_are_refused(tmp_path, capsys):
    color, depth, _ = scene(65504.0)
    frame = write_layout(tmp_path / "half.exr", {"R": color[..., 0], "G": color[..., 1], "B": color[..., 2], "Z": depth},
                         {"Z": oiio.TypeHalf})  # fmt: skip
    assert np.isposinf(np.asarray(gr.read_buffers(frame).depth)[:5]).all()
    with pytest.raises(ValueError, match="sky_depth"):
        gr.read_buffers(frame, sky_depth=0.0)
    out = tmp_path / "out.exr"
    with pytest.raises(SystemExit) as exit_info:
        main(["apply", str(frame), "--sky-depth", "-1", "-o", str(out)])
    assert exit_info.value.code == 2 and "--sky-depth" in capsys.readouterr().err and not out.exists()


def test_light_pass_preset_falls_back_to_the_disc_on_the_shipped_frame(tmp_path, capsys):
    out = tmp_path / "galaxy.png"
    assert main(["apply", str(SAMPLE), "--preset", "galaxy_vls", "-o", str(out)]) == 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no light pass" in err and "disc" in err
    frame = gr.read_buffers(SAMPLE)
    difference = np.abs(np.asarray(gr.read_image(out)) - np.clip(np.asarray(frame.color), 0, 1))
    assert float(difference.max()) > 0.1


def test_batch_of_a_light_pass_preset_falls_back_once_for_the_run(tmp_path, capsys):
    (tmp_path / "in").mkdir()
    for number in (1, 2):
        (tmp_path / "in" / f"sample.{number:04d}.exr").write_bytes(SAMPLE.read_bytes())
    status = main(["batch", str(tmp_path / "in" / "sample.#.exr"), "-o", str(tmp_path / "out"), "--preset", "galaxy_vls", "-q"])
    captured = capsys.readouterr()
    assert status == 0, captured.err
    assert captured.err.count("\n") == 1 and "no light pass" in captured.err
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["sample.0001.exr", "sample.0002.exr"]
