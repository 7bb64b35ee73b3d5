"""Tests for the frame and image files (godrays_jax.primitives: frame_reading, frame_files, images, light_metadata): round trips, channel names, metadata, errors, atomic writes."""

import os
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest

from godrays_jax import Buffers, check_buffers, read_buffers, read_image, read_light, srgb_decode, srgb_encode, write_buffers, write_image
from godrays_jax import StoredLight, lights_metadata, read_lights

COLONNADE = Path(__file__).resolve().parent / "data" / "colonnade_buffers.exr"  # tests/data/README.md
SAMPLE = Path(__file__).resolve().parents[1] / "examples" / "data" / "sample_frame.exr"


def _frame(h: int = 6, w: int = 8, seed: int = 0) -> Buffers:
    rng = np.random.default_rng(seed)
    depth = rng.uniform(1.0, 50.0, (h, w)).astype(np.float32)
    depth[0, :] = np.inf
    coverage = np.where(np.isfinite(depth), rng.uniform(0.2, 1.0, (h, w)), 0.0).astype(np.float32)
    return Buffers(
        color=rng.uniform(0.0, 30.0, (h, w, 3)).astype(np.float32),
        depth=depth,
        coverage=coverage,
    )


def _write_exr(path: Path, channels: dict[str, np.ndarray], attributes: dict | None = None) -> None:
    """An EXR with arbitrary channel names, written directly with OIIO."""
    names = tuple(channels)
    pixels = np.ascontiguousarray(np.stack([channels[n] for n in names], -1).astype(np.float32))
    spec = oiio.ImageSpec(pixels.shape[1], pixels.shape[0], len(names), oiio.FLOAT)
    spec.channelnames = names
    for key, value in (attributes or {}).items():
        spec.attribute(key, value)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(pixels) and out.close()


def _rgb_depth(depth_name: str, h: int = 4, w: int = 5) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(1)
    depth = rng.uniform(1, 9, (h, w))
    depth[0, 0] = np.inf
    return {"R": rng.random((h, w)), "G": rng.random((h, w)), "B": rng.random((h, w)), depth_name: depth}


# ------------------------------------------------------------------------ round trips


@pytest.mark.parametrize("half", [False, True])
def test_buffers_round_trip(tmp_path, half):
    frame = _frame()
    path = tmp_path / "f.exr"
    write_buffers(path, frame, half=half)
    back = read_buffers(path)
    assert back.color.dtype == np.float32 and back.depth.dtype == np.float32
    tol = 1e-3 if half else 0.0  # half: 11-bit mantissa, relative error <= 2**-11
    np.testing.assert_allclose(back.color, frame.color, rtol=tol, atol=0)
    np.testing.assert_allclose(back.coverage, frame.coverage, rtol=tol, atol=0)
    np.testing.assert_array_equal(back.depth, frame.depth)  # float32 always, +inf kept
    assert np.isposinf(np.asarray(back.depth)[0]).all()
    assert back.normal is None and back.light_pass is None and back.glow_pass is None


def test_optional_passes_round_trip(tmp_path):
    frame = _frame()
    h, w = frame.depth.shape
    rng = np.random.default_rng(3)
    full = Buffers(
        color=frame.color,
        depth=frame.depth,
        coverage=frame.coverage,
        normal=rng.normal(size=(h, w, 3)).astype(np.float32),
        object_id=np.where(np.isfinite(frame.depth), rng.integers(0, 7, (h, w)), -1).astype(np.int32),
        light_pass=rng.random((h, w)).astype(np.float32),
        glow_pass=rng.random((h, w, 4)).astype(np.float32),
    )
    path = tmp_path / "full.exr"
    write_buffers(path, full)
    inp = oiio.ImageInput.open(str(path))
    names = tuple(inp.spec().channelnames)
    inp.close()
    assert sorted(names) == sorted(("R", "G", "B", "A", "Z", "N.X", "N.Y", "N.Z", "object_id", "light.Y",
                                    "glow.R", "glow.G", "glow.B", "glow.A"))
    back = read_buffers(path)
    for field in ("normal", "object_id", "light_pass", "glow_pass"):
        np.testing.assert_array_equal(getattr(back, field), getattr(full, field), err_msg=field)
    assert back.object_id.dtype == np.int32


def test_lightpass_alternative_name(tmp_path):
    channels = _rgb_depth("Z")
    channels["lightpass"] = np.full_like(channels["R"], 0.25)
    _write_exr(tmp_path / "lp.exr", channels)
    np.testing.assert_array_equal(read_buffers(tmp_path / "lp.exr").light_pass, 0.25)


@pytest.mark.parametrize(
    ("ext", "kwargs", "step"),
    [
        (".exr", {}, 0.0),
        (".exr", {"dtype": "half"}, 2.0**-11),
        (".png", {}, 1 / 255),
        (".png", {"bit_depth": 16}, 1 / 65535),
        (".tif", {"bit_depth": 16}, 1 / 65535),
        (".jpg", {}, None),
    ],
)
def test_image_round_trip(tmp_path, ext, kwargs, step):
    y, x = np.mgrid[0:16, 0:24] / 24.0  # smooth once encoded, so that JPEG keeps it well
    image = srgb_decode(np.stack([x, y, 0.5 * (x + y)], -1)).astype(np.float32)
    if ext == ".exr":
        image[0, 0] = [100.0, 0.0, 5.0]  # unclipped HDR
    path = tmp_path / f"img{ext}"
    write_image(path, image, **kwargs)
    back = np.asarray(read_image(path))
    assert back.shape == image.shape and back.dtype == np.float32
    if ext == ".exr":
        np.testing.assert_allclose(back, image, rtol=step, atol=0)
    elif step is not None:
        # within half a code step, in the encoded (sRGB) space where the codes are uniform
        np.testing.assert_allclose(srgb_encode(back), srgb_encode(image), atol=0.51 * step)
    else:  # JPEG: lossy; a smooth image comes back within a few codes
        assert np.abs(srgb_encode(back) - srgb_encode(image)).max() < 6 / 255


def test_display_encoding_is_srgb_and_clipped(tmp_path):
    # Premultiplied RGBA: straight colour (0, 0.5, 4) at alpha 0.5; alpha stays linear.
    image = np.array([[[0.0, 0.25, 2.0, 0.5]]], np.float32)
    write_image(tmp_path / "p.png", image)
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    inp = oiio.ImageInput.open(str(tmp_path / "p.png"), config)
    codes = inp.read_image(oiio.UINT8).reshape(-1)
    inp.close()
    assert codes.tolist() == [0, 188, 255, 128]  # sRGB(0.5) = 0.7354 -> 188
    a = 128 / 255
    np.testing.assert_allclose(np.asarray(read_image(tmp_path / "p.png"))[0, 0], [0, 0.5029 * a, a, a], atol=1e-3)


@pytest.mark.parametrize("shape", [(4, 5), (4, 5, 1), (4, 5, 4)])
def test_image_channel_counts(tmp_path, shape):
    image = np.random.default_rng(0).random(shape).astype(np.float32)
    write_image(tmp_path / "c.exr", image)
    np.testing.assert_array_equal(np.asarray(read_image(tmp_path / "c.exr")).reshape(shape), image)


# ------------------------------------------------------------------------ channel names


@pytest.mark.parametrize("name", ["Z", "depth.Z", "depth"])
def test_depth_channel_variants(tmp_path, name):
    channels = _rgb_depth(name)
    _write_exr(tmp_path / "d.exr", channels)
    frame = read_buffers(tmp_path / "d.exr")
    np.testing.assert_array_equal(frame.depth, channels[name].astype(np.float32))
    # No A: coverage from depth.
    np.testing.assert_array_equal(frame.coverage, np.isfinite(channels[name]).astype(np.float32))


def test_caller_named_depth_channel(tmp_path):
    channels = _rgb_depth("dist")
    channels["Z"] = np.zeros_like(channels["R"])
    _write_exr(tmp_path / "d.exr", channels)
    np.testing.assert_array_equal(read_buffers(tmp_path / "d.exr", depth_channel="dist").depth,
                                  channels["dist"].astype(np.float32))
    with pytest.raises(ValueError, match=r"looked for nope\); channels found: R, G, B, Z, dist"):
        read_buffers(tmp_path / "d.exr", depth_channel="nope")


def test_far_sentinel_is_sky(tmp_path):
    channels = _rgb_depth("Z")
    channels["Z"][1, 1] = 1e30
    channels["Z"][1, 2] = 3e38
    _write_exr(tmp_path / "s.exr", channels)
    depth = np.asarray(read_buffers(tmp_path / "s.exr").depth)
    assert np.isposinf(depth[0, 0]) and np.isposinf(depth[1, 1]) and np.isposinf(depth[1, 2])


def test_coverage_from_alpha_and_opaque_background(tmp_path):
    channels = _rgb_depth("Z")
    channels["A"] = np.full_like(channels["R"], 0.5)
    _write_exr(tmp_path / "a.exr", channels)
    np.testing.assert_array_equal(read_buffers(tmp_path / "a.exr").coverage, 0.5)
    # Alpha 1 on the sky pixel: an opaque background, not coverage -> from depth (auto) ...
    channels["A"] = np.ones_like(channels["R"])
    _write_exr(tmp_path / "o.exr", channels)
    expected = np.isfinite(channels["Z"]).astype(np.float32)
    np.testing.assert_array_equal(read_buffers(tmp_path / "o.exr").coverage, expected)
    # ... unless the caller insists.
    np.testing.assert_array_equal(read_buffers(tmp_path / "o.exr", coverage="alpha").coverage, 1.0)


# ------------------------------------------------------------------------ metadata


def test_light_metadata_round_trip(tmp_path):
    path = tmp_path / "l.exr"
    write_buffers(path, _frame(), light_xy=(12.25, -3.5), light_in_front=False,
                  metadata={"godrays:note": "hi", "godrays:n": 3, "godrays:v": [1.0, 2.0, 3.0]})
    assert read_light(path) == ((12.25, -3.5), False)
    inp = oiio.ImageInput.open(str(path))
    spec = inp.spec()
    inp.close()
    assert spec.getattribute("godrays:note") == "hi" and spec.getattribute("godrays:n") == 3
    assert spec.getattribute("compression") == "zip"
    write_buffers(path, _frame())
    assert read_light(path) is None


def test_several_lights_round_trip(tmp_path):
    """`lights_metadata` beside the first light's `light_xy` is what `read_lights` reads back, each light whole; a
    frame of one light stores no `godrays:lights`."""
    lights = [StoredLight((12.25, -3.5)), StoredLight((300.5, 40.0), False, 12.0, (2.0, 1.0, 0.5))]
    path = tmp_path / "l.exr"
    write_buffers(path, _frame(), light_xy=lights[0].xy, metadata=lights_metadata(lights))
    assert read_lights(path) == lights and read_light(path) == ((12.25, -3.5), True)
    write_buffers(path, _frame(), light_xy=(1.0, 2.0))
    assert read_lights(path) is None
    with pytest.raises(ValueError, match=r"lights\[1\] must have a distance > 0"):
        lights_metadata([lights[0], lights[1]._replace(depth=0.0)])


@pytest.mark.parametrize(
    "attributes, message",
    [
        ({"godrays:lights": "1,2;3"}, r"godrays:lights holds '3' where 2 numbers go"),
        ({"godrays:lights": "1,2,above"}, r"godrays:lights: a side is front or behind"),
        ({"godrays:lights": "1,2;3,4", "godrays:lights_depth": "inf"}, r"godrays:lights_depth gives 1 lights"),
        ({"godrays:lights": "1,2", "godrays:lights_tint": "1,-1,1"}, r"godrays:lights_tint must hold .* tints >= 0"),
        ({"godrays:lights": "1,2", "godrays:lights_depth": "0"}, r"godrays:lights_depth must hold distances > 0"),
    ],
)
def test_malformed_lights_name_the_attribute(tmp_path, attributes, message):
    _write_exr(tmp_path / "m.exr", _rgb_depth("Z"), attributes)
    with pytest.raises(ValueError, match=r"m\.exr.*" + message):
        read_lights(tmp_path / "m.exr")


def test_light_as_string(tmp_path):
    _write_exr(tmp_path / "s.exr", _rgb_depth("Z"), {"godrays:light_px": "10.5, 20"})
    assert read_light(tmp_path / "s.exr") == ((10.5, 20.0), True)
    _write_exr(tmp_path / "b.exr", _rgb_depth("Z"), {"godrays:light_px": "ten"})
    with pytest.raises(ValueError, match="b.exr.*two numbers"):
        read_light(tmp_path / "b.exr")


def test_sample_frame():
    frame = read_buffers(SAMPLE)
    assert frame.color.shape == (180, 320, 3)
    (x, y), in_front = read_light(SAMPLE)
    assert in_front and 0 < x < 320 and 0 < y < 180
    depth, color = np.asarray(frame.depth), np.asarray(frame.color)
    assert np.isposinf(depth[int(y), int(x)]) and color[int(y), int(x)].max() > 10  # the sun is sky
    finite = depth[np.isfinite(depth)]
    assert finite.min() > 0 and 0 < np.asarray(frame.coverage).mean() < 1
    assert SAMPLE.stat().st_size < 600_000


def test_read_colonnade():
    frame = read_buffers(COLONNADE)
    assert frame.color.shape == (180, 320, 3)
    depth = np.asarray(frame.depth)
    sky = np.isposinf(depth)
    assert sky.any() and (depth[~sky] > 0).all()
    # Its A is 1 over the sky emitter too, so coverage comes from depth.
    np.testing.assert_array_equal(np.asarray(frame.coverage), (~sky).astype(np.float32))
    assert read_light(COLONNADE) is None


# ------------------------------------------------------------------------ errors


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothere.exr"):
        read_buffers(tmp_path / "nothere.exr")
    with pytest.raises(FileNotFoundError, match="nothere.exr"):
        read_light(tmp_path / "nothere.exr")


def test_text_file_renamed_exr(tmp_path):
    path = tmp_path / "x.exr"
    path.write_text("not an image\n")
    with pytest.raises(ValueError, match=r"cannot read image '.*x\.exr': "):
        read_buffers(path)


def test_no_depth_channel_lists_channels(tmp_path):
    channels = _rgb_depth("Z")
    channels["A"] = channels.pop("Z")
    _write_exr(tmp_path / "n.exr", channels)
    with pytest.raises(ValueError, match=r"n\.exr' has no depth channel \(looked for Z, depth\.Z, depth, \*\.Depth\.Z\); "
                       r"channels found: R, G, B, A"):
        read_buffers(tmp_path / "n.exr")


def test_no_rgb_lists_channels(tmp_path):
    channels = _rgb_depth("Z")
    del channels["G"], channels["B"]
    _write_exr(tmp_path / "g.exr", channels)
    with pytest.raises(ValueError, match=r"no G, B colour channel.*channels found: R, Z"):
        read_buffers(tmp_path / "g.exr")


def test_nan_colour_and_bad_depth(tmp_path):
    channels = _rgb_depth("Z")
    channels["R"][1, 1] = np.nan
    channels["G"][1, 2] = np.inf
    channels["B"][1, 2] = np.nan  # same pixel as G: counted once
    _write_exr(tmp_path / "c.exr", channels)
    with pytest.raises(ValueError, match=r"c\.exr'.*color has 2 pixels with NaN or infinite"):
        read_buffers(tmp_path / "c.exr")
    channels = _rgb_depth("Z")
    channels["Z"][2, 2] = np.nan
    channels["Z"][3, :2] = -1.0
    _write_exr(tmp_path / "d.exr", channels)
    with pytest.raises(ValueError, match=r"depth has 1 pixel with NaN; depth has 2 pixels with negative"):
        read_buffers(tmp_path / "d.exr")


def test_check_buffers_on_arrays():
    check_buffers(_frame(), name="ok")
    bad = _frame()
    cov = np.asarray(bad.coverage).copy()
    cov[2, 3] = 1.5
    with pytest.raises(ValueError, match=r"'frame 7'.*coverage has 1 pixel outside \[0, 1\]"):
        check_buffers(Buffers(color=bad.color, depth=bad.depth, coverage=cov), name="frame 7")


def test_unknown_extension_and_bad_options(tmp_path):
    image = np.zeros((2, 2, 3), np.float32)
    with pytest.raises(ValueError, match=r"unknown extension '\.bmpx'"):
        write_image(tmp_path / "a.bmpx", image)
    with pytest.raises(ValueError, match="must be 8"):
        write_image(tmp_path / "a.jpg", image, bit_depth=16)
    with pytest.raises(ValueError, match="bit_depth does not apply to EXR"):
        write_image(tmp_path / "a.exr", image, bit_depth=16)
    with pytest.raises(ValueError, match="C = 1, 3 or 4"):
        write_image(tmp_path / "a.png", np.zeros((2, 2, 2)))
    with pytest.raises(ValueError, match=r"must end in \.exr"):
        write_buffers(tmp_path / "a.png", _frame())
    assert os.listdir(tmp_path) == []


# ------------------------------------------------------------------------ atomic writes


class _FailingOutput:
    """Stands in for oiio.ImageOutput: writes part of a file, then fails."""

    @staticmethod
    def create(path):
        return _FailingOutput()

    def open(self, path, spec):
        self.path = path
        return True

    def write_image(self, pixels):
        Path(self.path).write_bytes(b"partial")
        raise RuntimeError("disk full")

    def close(self):
        return True


@pytest.mark.parametrize("target", ["img.exr", "img.png", "frame.exr"])
def test_failed_write_leaves_nothing(tmp_path, monkeypatch, target):
    (tmp_path / "keep.txt").write_text("x")
    monkeypatch.setattr(oiio, "ImageOutput", _FailingOutput)
    with pytest.raises(RuntimeError, match="disk full"):
        if target == "frame.exr":
            write_buffers(tmp_path / target, _frame())
        else:
            write_image(tmp_path / target, np.zeros((2, 2, 3), np.float32))
    assert sorted(os.listdir(tmp_path)) == ["keep.txt"]


def test_failed_write_keeps_existing_file(tmp_path, monkeypatch):
    path = tmp_path / "img.exr"
    write_image(path, np.ones((2, 2, 3), np.float32))
    before = path.read_bytes()
    monkeypatch.setattr(oiio, "ImageOutput", _FailingOutput)
    with pytest.raises(RuntimeError):
        write_image(path, np.zeros((2, 2, 3), np.float32))
    assert path.read_bytes() == before and os.listdir(tmp_path) == ["img.exr"]


def test_missing_destination_folder(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        write_image(tmp_path / "no" / "img.exr", np.zeros((2, 2, 3), np.float32))


@pytest.mark.parametrize("ext", [".png", ".tif"])
def test_premultiplied_rgba_round_trip(tmp_path, ext):
    rng = np.random.default_rng(5)
    alpha = rng.uniform(0.1, 1.0, (5, 6, 1))
    image = np.concatenate([rng.random((5, 6, 3)) * alpha, alpha], -1).astype(np.float32)
    write_image(tmp_path / f"a{ext}", image, bit_depth=16)
    np.testing.assert_allclose(np.asarray(read_image(tmp_path / f"a{ext}")), image, atol=2e-4)
