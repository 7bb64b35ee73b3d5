"""The camera a frame's header carries (field of view, depth kind) and depth read as renderers write it."""

import math
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import OpenImageIO as oiio
import pytest

import godrays_jax as gr
from godrays_jax.primitives.camera_metadata import FOV_X_ATTR, read_frame_camera

DATA = Path(__file__).resolve().parent / "data"
BLENDER = DATA / "blender_planar_z.exr"  # Cycles, multilayer, planar Z; tests/data/blender_planar_z.py
BLENDER_FOV = 2 * math.degrees(math.atan(18 / 30))  # 30 mm lens on Blender's 36 mm sensor


def _ray_depth_loop(planar, fov_x_deg):
    height, width = planar.shape
    focal = (width / 2) / math.tan(math.radians(fov_x_deg) / 2)
    out = np.empty(planar.shape)
    for row in range(height):
        for col in range(width):
            length = math.sqrt(1 + ((col + 0.5 - width / 2) / focal) ** 2 + ((height / 2 - row - 0.5) / focal) ** 2)
            out[row, col] = planar[row, col] * length
    return out


def _raw_z(path):
    inp = oiio.ImageInput.open(str(path))
    spec = inp.spec()
    pixels = np.asarray(inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)).reshape(spec.height, spec.width, -1)
    inp.close()
    z = pixels[..., list(spec.channelnames).index("ViewLayer.Depth.Z")].astype(np.float64)
    return np.where(z >= 1e9, np.inf, z)


def _copy_without(path, out, attribute):
    """The file with one header attribute removed (pixels and every other attribute kept)."""
    source = oiio.ImageBuf(str(path))
    source.specmod().erase_attribute(attribute)
    assert source.write(str(out))


def test_blender_header():
    camera = read_frame_camera(BLENDER)
    assert camera.depth_kind == "planar"
    assert camera.fov_x_deg == pytest.approx(BLENDER_FOV)
    assert "Lens" in camera.source


def test_blender_z_is_planar_and_read_as_ray_depth():
    raw = _raw_z(BLENDER)
    wall = raw == 6.0
    assert wall.sum() > 500  # the wall's planar depth is 6 at every pixel: Blender writes distance along the axis
    frame = gr.read_buffers(BLENDER)
    assert frame.depth_kind == "ray"
    np.testing.assert_allclose(np.asarray(frame.depth), _ray_depth_loop(raw, BLENDER_FOV), rtol=2e-6)
    assert float(np.max(np.asarray(frame.depth)[wall])) > 6.5  # the wall's corners lie farther along their rays
    np.testing.assert_allclose(np.asarray(gr.read_buffers(BLENDER, depth_kind="ray").depth), raw)
    np.testing.assert_allclose(
        np.asarray(gr.read_buffers(BLENDER, fov_x_deg=40.0).depth), _ray_depth_loop(raw, 40.0), rtol=2e-6
    )


def test_blender_without_lens_stays_planar(tmp_path):
    path = tmp_path / "no_lens.exr"
    _copy_without(BLENDER, path, "Lens")
    assert read_frame_camera(path).fov_x_deg is None and read_frame_camera(path).depth_kind == "planar"
    frame = gr.read_buffers(path)
    assert frame.depth_kind == "planar"
    np.testing.assert_allclose(np.asarray(frame.depth), _raw_z(BLENDER))
    # Effects convert it with their own field of view.
    fog = gr.preset("participating_media")
    light = jnp.asarray([40.0, 8.0])
    expected = fog(gr.read_buffers(BLENDER, fov_x_deg=float(fog.fov_x_deg)), light)
    np.testing.assert_allclose(np.asarray(fog(frame, light)), np.asarray(expected), rtol=1e-5, atol=1e-6)


def test_other_files_read_as_ray_depth(tmp_path):
    frame = gr.read_buffers(DATA / "colonnade_buffers.exr")
    assert frame.depth_kind == "ray" and read_frame_camera(DATA / "colonnade_buffers.exr").fov_x_deg is None
    planar = gr.read_buffers(DATA / "colonnade_buffers.exr", depth_kind="planar")
    assert planar.depth_kind == "planar"
    np.testing.assert_array_equal(np.asarray(planar.depth), np.asarray(frame.depth))
    with pytest.raises(ValueError, match="depth_kind"):
        gr.read_buffers(DATA / "colonnade_buffers.exr", depth_kind="z")


def test_stored_field_of_view(tmp_path):
    depth = np.full((9, 16), 5.0, np.float32)
    buffers = gr.Buffers(color=jnp.zeros((9, 16, 3)), depth=jnp.asarray(depth), coverage=jnp.ones((9, 16)))
    path = tmp_path / "frame.exr"
    gr.write_buffers(path, buffers, metadata={FOV_X_ATTR: 70.0})
    assert read_frame_camera(path).fov_x_deg == pytest.approx(70.0)
    assert read_frame_camera(path).depth_kind == "ray"
    np.testing.assert_array_equal(np.asarray(gr.read_buffers(path).depth), depth)  # ray depth: kept as stored
    converted = gr.read_buffers(path, depth_kind="planar")
    np.testing.assert_allclose(np.asarray(converted.depth), _ray_depth_loop(depth, 70.0), rtol=2e-6)


def _look_at(fov_x_deg, width, height, ndc):
    """OpenEXR's worldToCamera and worldToNDC (row vectors) of a camera at (1, 2, 3) looking down its -z."""
    world_to_camera = np.eye(4)
    world_to_camera[3, :3] = [-1.0, -2.0, -3.0]
    scale = 1 / math.tan(math.radians(fov_x_deg) / 2)
    aspect = width / height
    projection = np.zeros((4, 4))  # OpenGL's, transposed for row vectors; NDC in [-1, 1]
    projection[0, 0], projection[1, 1] = scale, scale * aspect
    projection[2, 2], projection[3, 2], projection[2, 3] = -1.0, -0.2, -1.0
    if ndc == "unit":  # RenderMan-style [0, 1]: x' = (x + w) / 2
        to_unit = np.eye(4)
        to_unit[0, 0] = to_unit[1, 1] = 0.5
        to_unit[3, 0] = to_unit[3, 1] = 0.5
        projection = projection @ to_unit
    return world_to_camera, world_to_camera @ projection


@pytest.mark.parametrize("ndc", ["signed", "unit"])
def test_standard_camera_matrices(tmp_path, ndc):
    world_to_camera, world_to_ndc = _look_at(55.0, 16, 9, ndc)
    spec = oiio.ImageSpec(16, 9, 4, oiio.FLOAT)
    spec.channelnames = ("R", "G", "B", "Z")
    spec.attribute("worldToCamera", oiio.TypeDesc("matrix44"), tuple(world_to_camera.ravel()))
    spec.attribute("worldToNDC", oiio.TypeDesc("matrix44"), tuple(world_to_ndc.ravel()))
    path = tmp_path / "camera.exr"
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), spec)
    out.write_image(np.ones((9, 16, 4), np.float32))
    out.close()
    camera = read_frame_camera(path)
    assert camera.fov_x_deg == pytest.approx(55.0, abs=1e-3) and camera.source == "worldToCamera, worldToNDC"


def test_photo_without_depth(tmp_path):
    colour = np.linspace(0.0, 1.0, 9 * 16 * 3, dtype=np.float32).reshape(9, 16, 3)
    path = tmp_path / "photo.png"
    gr.write_image(path, colour)
    with pytest.raises(ValueError, match="no depth channel"):
        gr.read_buffers(path)
    frame = gr.read_buffers(path, without_depth=True)
    assert frame.depth is None
    np.testing.assert_allclose(np.asarray(frame.color), np.asarray(gr.read_image(path)), atol=1e-6)
    np.testing.assert_array_equal(np.asarray(frame.coverage), 1.0)
    alpha = np.concatenate([colour * 0.5, np.full((9, 16, 1), 0.5, np.float32)], axis=-1)
    gr.write_image(tmp_path / "keyed.png", alpha)
    keyed = gr.read_buffers(tmp_path / "keyed.png", without_depth=True)
    np.testing.assert_allclose(np.asarray(keyed.coverage), 128 / 255, atol=1e-6)
    np.testing.assert_allclose(np.asarray(keyed.color), np.asarray(gr.read_image(tmp_path / "keyed.png"))[..., :3], atol=1e-6)
