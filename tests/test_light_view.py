"""A depth map seen from the light: the kernel against a NumPy loop and at its edges, its files, the fog and the
commands reading it."""

import dataclasses
import json
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import godrays_jax as gr
from godrays_jax.app.cli import main
from godrays_jax.kernels.light_view_shadows import RAMP_TEXELS, covers_view, on_light_view
from godrays_jax.primitives.light_view_files import FROM_CAMERA_ATTR

from tune_support import served_tuners

# A sun straight above: its camera looks down the frame's -y from 10 units above the frame's camera; the frame's z
# (forward) is up on the map. Slats at 4.5 along its axis (5.5 units above the frame's camera) with gaps.
FROM_ABOVE = np.asarray([[1, 0, 0, 0], [0, 0, 1, -5], [0, -1, 0, 10]], np.float64)
SLATS = np.where(np.logical_and.outer(np.arange(16) % 5 < 3, np.arange(16) % 4 < 2), 4.5, np.inf)


def _numpy_visibility(points, depth, transform, scale, projection):
    """The shadow map's test point by point: the four texels around each point's place, each lit up to its surface
    and shadowed `RAMP_TEXELS` footprints behind it, blended by bilinear weights; 1 off the map."""
    height, width = depth.shape
    out = np.ones(points.shape[:-1])
    for index in np.ndindex(*points.shape[:-1]):
        lx, ly, lz = transform[:, :3] @ points[index] + transform[:, 3]
        if projection == "perspective":
            if lz <= 0:
                continue
            x, y, footprint = width / 2 + scale * lx / lz, height / 2 - scale * ly / lz, lz / scale
        else:
            x, y, footprint = width / 2 + scale * lx, height / 2 - scale * ly, 1 / scale
        if not (0 <= x <= width and 0 <= y <= height):
            continue
        u, v = x - 0.5, y - 0.5
        col0, row0 = math.floor(u), math.floor(v)
        total = 0.0
        for dr in (0, 1):
            for dc in (0, 1):
                weight = (v - row0 if dr else 1 - (v - row0)) * (u - col0 if dc else 1 - (u - col0))
                texel = depth[min(max(row0 + dr, 0), height - 1), min(max(col0 + dc, 0), width - 1)]
                lit = 1.0 if np.isinf(texel) else min(max(1 - (lz - texel) / (RAMP_TEXELS * footprint), 0.0), 1.0)
                total += weight * lit
        out[index] = total
    return out


def _numpy_on_map(points, shape, transform, scale, projection):
    """Whether the map's test decides each point: on `[0, w] x [0, h]`, in front of a perspective map's centre."""
    height, width = shape
    out = np.zeros(points.shape[:-1], bool)
    for index in np.ndindex(*points.shape[:-1]):
        lx, ly, lz = transform[:, :3] @ points[index] + transform[:, 3]
        if projection == "perspective" and lz <= 0:
            continue
        x, y = (lx / lz, ly / lz) if projection == "perspective" else (lx, ly)
        out[index] = 0 <= width / 2 + scale * x <= width and 0 <= height / 2 - scale * y <= height
    return out


def _points(rng, count=40):
    return rng.uniform([-4.0, 0.0, 1.0], [4.0, 6.0, 9.0], size=(count, 3))


@pytest.mark.parametrize("projection", ["orthographic", "perspective"])
def test_matches_a_numpy_loop_eagerly_under_jit_and_vmap(projection, rng):
    points = _points(rng)
    scale = 2.0 if projection == "orthographic" else 6.0
    transform = FROM_ABOVE if projection == "orthographic" else FROM_ABOVE + [[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 3]]
    view = gr.LightView(depth=jnp.asarray(SLATS, jnp.float32), from_camera=jnp.asarray(transform, jnp.float32),
                        scale=jnp.float32(scale), projection=projection)  # fmt: skip
    expected = _numpy_visibility(points, SLATS, transform, scale, projection)
    assert 0.05 < np.mean(expected) < 0.95  # both lit and shadowed points
    points = jnp.asarray(points, jnp.float32)
    eager = gr.light_view_visibility(points, light_view=view)
    jitted = jax.jit(lambda p, v: gr.light_view_visibility(p, light_view=v))(points, view)
    mapped = jax.vmap(lambda p: gr.light_view_visibility(p, light_view=view))(points)
    for values in (eager, jitted, mapped):
        np.testing.assert_allclose(values, expected, atol=2e-5)
    aside = jnp.asarray([[30.0, 3.0, 4.0], [0.0, 12.0, 5.0]], jnp.float32)  # to the side; above a perspective centre
    points = jnp.concatenate([points, aside])
    on_map = _numpy_on_map(np.asarray(points), SLATS.shape, transform, scale, projection)
    assert 0 < np.mean(on_map) < 1  # points on the map and off it
    for on in (on_light_view(points, light_view=view), jax.vmap(lambda p: on_light_view(p, light_view=view))(points),
               jax.jit(lambda p, v: on_light_view(p, light_view=v))(points, view)):  # fmt: skip
        np.testing.assert_array_equal(on, on_map)


def test_off_the_map_behind_its_centre_and_where_it_sees_nothing_the_light_reaches(rng):
    beyond = jnp.asarray([[100.0, 3.0, 4.0], [0.0, 3.0, 50.0]], jnp.float32)  # far to the side, far ahead
    view = gr.LightView(depth=jnp.asarray(np.zeros((16, 16)), jnp.float32), from_camera=FROM_ABOVE, scale=2.0)
    np.testing.assert_array_equal(gr.light_view_visibility(beyond, light_view=view), 1.0)
    under_the_roof = jnp.asarray([[0.0, 3.0, 4.0]], jnp.float32)  # every texel a surface at 0: deep in its shadow
    np.testing.assert_array_equal(gr.light_view_visibility(under_the_roof, light_view=view), 0.0)
    nothing = gr.LightView(depth=jnp.full((16, 16), jnp.inf), from_camera=FROM_ABOVE, scale=2.0)
    anywhere = jnp.asarray(_points(rng), jnp.float32)
    np.testing.assert_array_equal(gr.light_view_visibility(anywhere, light_view=nothing), 1.0)
    behind = gr.LightView(depth=jnp.zeros((16, 16)), from_camera=FROM_ABOVE, scale=6.0, projection="perspective")
    above_the_light = jnp.asarray([[0.0, 12.0, 5.0]], jnp.float32)  # lz = -2: behind the map's centre
    values = gr.light_view_visibility(above_the_light, light_view=behind)
    grads = jax.grad(lambda p: gr.light_view_visibility(p, light_view=behind).sum())(above_the_light)
    assert float(values[0]) == 1.0 and np.all(np.isfinite(grads))
    assert not bool(on_light_view(above_the_light, light_view=behind)[0])  # the frame's shadows decide there
    assert not np.any(on_light_view(beyond, light_view=view)) and np.all(on_light_view(anywhere, light_view=nothing))


@pytest.mark.parametrize("projection", ["orthographic", "perspective"])
def test_a_map_covers_a_view_where_it_holds_every_point_through_the_frame_within_the_reach(projection):
    """`covers_view` against points through the frame and its margin at every depth up to the reach, the pyramid's
    corners among them (the map's region is convex: they decide): wide and narrow maps, near and far reaches."""
    height, width, focal, margin = 9, 16, 17.0, 2.0
    transform = FROM_ABOVE if projection == "orthographic" else FROM_ABOVE + [[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 3]]
    xs, ys = np.linspace(-margin, width + margin, 7), np.linspace(-margin, height + margin, 5)
    outcomes = set()
    for scale in ((0.5, 2.0, 8.0) if projection == "orthographic" else (2.0, 6.0)):
        view = gr.LightView(depth=jnp.asarray(SLATS, jnp.float32), from_camera=jnp.asarray(transform, jnp.float32),
                            scale=jnp.float32(scale), projection=projection)  # fmt: skip
        for reach in (1.0, 4.0, 12.0, 40.0):
            points = np.asarray([[z * (x - width / 2) / focal, -z * (y - height / 2) / focal, z]
                                 for x in xs for y in ys for z in np.linspace(0.0, reach, 9)])  # fmt: skip
            expected = bool(np.all(_numpy_on_map(points, SLATS.shape, transform, scale, projection)))
            covered = covers_view(view, height=height, width=width, focal=focal, reach=reach, margin=margin)
            assert covered == expected, (scale, reach)
            outcomes.add(covered)
    assert outcomes == {True, False}
    stacked = gr.LightView(depth=jnp.stack([jnp.full((16, 16), jnp.inf)] * 2), from_camera=jnp.stack([FROM_ABOVE] * 2),
                           scale=jnp.asarray([0.5, 0.5]))  # fmt: skip
    assert not covers_view(stacked, height=height, width=width, focal=focal, reach=1.0, margin=margin)


def test_gradients_float64(x64):
    """In the points and the map's camera, where a point lies within a ramp and between texel centres."""
    depth = jnp.asarray(np.where(np.arange(16)[None, :] < 8, 4.5, 3.0) * np.ones((16, 1)))
    point = jnp.asarray([[0.13, 5.21, 5.31]])  # lz = 4.79: within the ramp behind 4.5, between it and 3 beside

    def visibility(points, from_camera, scale):
        return gr.light_view_visibility(points, light_view=gr.LightView(depth, from_camera, scale))

    assert 0.0 < float(visibility(point, jnp.asarray(FROM_ABOVE), 2.0)[0]) < 1.0
    check_grads(visibility, (point, jnp.asarray(FROM_ABOVE), jnp.asarray(2.0)), order=1, modes=("fwd", "rev"),
                eps=1e-6)  # fmt: skip


def test_a_light_view_file_round_trips_and_a_bad_header_is_named(tmp_path):
    view = gr.LightView(depth=jnp.asarray(SLATS, jnp.float32), from_camera=jnp.asarray(FROM_ABOVE, jnp.float32),
                        scale=jnp.float32(2.5), projection="perspective")  # fmt: skip
    path = tmp_path / "light.exr"
    gr.write_light_view(path, view)
    back = gr.read_light_view(path)
    np.testing.assert_array_equal(back.depth, view.depth)
    np.testing.assert_array_equal(back.from_camera, view.from_camera)
    assert float(back.scale) == 2.5 and back.projection == "perspective"
    import OpenImageIO as oiio

    spec = oiio.ImageSpec(4, 3, 1, oiio.FLOAT)
    spec.channelnames = ("Z",)
    spec.attribute("godrays:light_view_projection", "orthographic")
    spec.attribute(FROM_CAMERA_ATTR, "1 0 0 0 0 1 0")  # 7 numbers
    spec.attribute("godrays:light_view_scale", "2")
    bad = tmp_path / "bad.exr"
    out = oiio.ImageOutput.create(str(bad))
    assert out.open(str(bad), spec) and out.write_image(np.full((3, 4, 1), 1e10, np.float32)) and out.close()
    with pytest.raises(ValueError, match=f"{FROM_CAMERA_ATTR} must be 12 finite numbers"):
        gr.read_light_view(bad)


def _frame(height=18, width=32):
    depth = np.full((height, width), np.inf, np.float32)
    depth[12:] = 15.0
    depth[:, 14:17] = 6.0  # a post
    return gr.Buffers(color=np.full((height, width, 3), 0.2, np.float32), depth=depth,
                      coverage=np.isfinite(depth).astype(np.float32))  # fmt: skip


def _with_view(frame, depth, height=10.0, scale=0.5):
    """`frame` with a map from a sun straight above, its camera `height` above the frame's, `scale` pixels a unit."""
    from_camera = jnp.asarray(FROM_ABOVE, jnp.float32).at[2, 3].set(height)
    view = gr.LightView(depth=jnp.asarray(depth, jnp.float32), from_camera=from_camera, scale=scale)
    return gr.Buffers(color=frame.color, depth=frame.depth, coverage=frame.coverage, light_view=view)


SUN_ABOVE = np.asarray([16.0, -400.0], np.float32)


def test_a_light_view_says_what_lies_beyond_a_closed_frame():
    """A room's frame (no sky) is read as closed beyond its edges, its light shaded wherever it leaves in front of
    the walls; given a map, the map says what lies there instead: a map that sees nothing lets more light in."""
    frame = _frame(9, 16)
    room = np.where(np.isfinite(frame.depth), frame.depth, 20.0)
    medium = gr.BoundedMedium(extinction=0.05, max_distance=30.0, anisotropy=0.7)

    def scattered(light_view):
        return np.asarray(gr.volumetric_fog_terms(jnp.asarray(room), SUN_ABOVE, fov_x_deg=50.0, medium=medium,
                                                  light_view=light_view)[1])  # fmt: skip

    closed = scattered(None)
    seeing_nothing = gr.LightView(depth=jnp.full((8, 8), jnp.inf), from_camera=jnp.asarray(FROM_ABOVE, jnp.float32),
                                  scale=0.5)  # fmt: skip
    opened = scattered(seeing_nothing)
    assert np.all(closed <= opened + 1e-7) and float(np.mean(closed)) < 0.5 * float(np.mean(opened))


def test_a_fit_shades_a_room_its_map_covers_by_the_map_alone():
    """`same_on` a room whose map covers every point its rays reach within `LIGHT_VIEW_COVER_MULTIPLE` times its
    farthest wall reads one screen sample a segment (no shadows' table) and draws the room as the effect does, values
    and gradients; a map too narrow, or a frame without one, leaves the effect itself."""
    from godrays_jax.effects.volumetric import LIGHT_VIEW_COVER_MULTIPLE

    frame = _frame(9, 16)
    room = dataclasses.replace(frame, depth=np.where(np.isfinite(frame.depth), frame.depth, 20.0))
    slats = np.where(np.arange(64) % 4 < 2, 3.0, np.inf)[None, :] * np.ones((64, 1))
    effect = dataclasses.replace(gr.preset("volumetric_haze"), num_shadow_lines=16, num_shadow_bins=16,
                                 num_view_steps=4)  # fmt: skip
    covered = _with_view(room, slats)  # 128 units of the scene each way
    cheaper = effect.same_on([covered])
    assert (cheaper.shadows, cheaper.num_shadow_samples) == ("samples", 1)
    narrow = _with_view(room, slats, scale=64 / (LIGHT_VIEW_COVER_MULTIPLE * 20.0))  # short of the reach across
    assert effect.same_on([narrow]) is effect and effect.same_on([covered, room]) is effect

    @eqx.filter_jit
    def drawn(candidate):  # the frame and the gradient of its mean, in one program
        def mean(c):
            frame = c(covered, SUN_ABOVE)
            return jnp.mean(frame), frame

        return jax.grad(mean, has_aux=True)(candidate)

    (grads, frame), (cheaper_grads, cheaper_frame) = drawn(effect), drawn(cheaper)
    arrays = [jax.tree.leaves(eqx.filter(tree, eqx.is_array)) for tree in (effect, cheaper, grads, cheaper_grads)]
    for mine, theirs in [*zip(arrays[0], arrays[1], strict=True), *zip(arrays[2], arrays[3], strict=True)]:
        np.testing.assert_allclose(np.asarray(mine), np.asarray(theirs), rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(frame, cheaper_frame, rtol=1e-6, atol=1e-7)
    assert float(grads.medium.extinction) != 0.0  # the room is fogged


@pytest.mark.slow
def test_the_fog_reads_the_light_view_on_it_and_the_frames_shadows_off_it():
    """On the map the map alone shades the fog (it holds what the frame shows too): one that sees nothing lights the
    post's shadow, one that covers none of the medium changes nothing; a roof over the whole medium leaves only the
    ambient and the surfaces; slats let some light through, differentiably, under jit and vmap over frames. (The
    fog's terms compiled: one program for the maps, one without.)"""
    effect = gr.preset("volumetric_haze")
    frame = _frame()
    medium = gr.BoundedMedium(extinction=0.05, max_distance=effect.medium.max_distance, anisotropy=0.7)

    @jax.jit
    def scattered(buffers):
        return gr.volumetric_fog_terms(buffers.depth, SUN_ABOVE, fov_x_deg=50.0, medium=medium,
                                       light_view=buffers.light_view)[1]  # fmt: skip

    unroofed = np.asarray(scattered(frame))
    unshaded = np.asarray(scattered(_with_view(frame, np.full((64, 64), np.inf))))
    assert np.all(unshaded >= unroofed - 1e-7) and float(np.max(unshaded[:, 14:17] - unroofed[:, 14:17])) > 0.0
    to_the_side = jnp.asarray(FROM_ABOVE, jnp.float32).at[0, 3].set(1e3)  # a thousand units: none of the medium on it
    aside = gr.LightView(depth=jnp.full((64, 64), jnp.inf), from_camera=to_the_side, scale=0.5)
    beside = gr.Buffers(color=frame.color, depth=frame.depth, coverage=frame.coverage, light_view=aside)
    np.testing.assert_allclose(scattered(beside), unroofed, rtol=1e-6, atol=1e-7)
    roofed = _with_view(frame, np.zeros((64, 64)), height=1e3, scale=0.01)  # a roof over all the medium, above it
    assert float(jnp.max(scattered(roofed))) == 0.0 and float(np.min(unroofed)) > 0.0
    slats = _with_view(frame, np.where(np.arange(64) % 4 < 2, 3.0, np.inf)[None, :] * np.ones((64, 1)))
    slatted = np.asarray(scattered(slats))
    assert np.all(slatted <= unroofed + 1e-7) and 0.2 < float(np.mean(slatted) / np.mean(unroofed)) < 0.85

    def loss(effect, frames):
        return jnp.mean(jax.vmap(lambda f: effect(f, SUN_ABOVE))(frames))

    frames = jax.tree.map(lambda *leaves: jnp.stack(leaves), slats, slats)
    grads = jax.jit(jax.grad(loss))(effect, frames)
    leaves = [leaf for leaf in jax.tree.leaves(grads) if isinstance(leaf, jax.Array)]
    assert leaves and all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in leaves)
    assert float(grads.medium.extinction) != 0.0


@pytest.mark.slow
def test_apply_reads_a_light_view_and_names_a_bad_one(tmp_path):
    frame, view, output = tmp_path / "frame.exr", tmp_path / "light.exr", tmp_path / "out.exr"
    slats = _with_view(_frame(), np.where(np.arange(64) % 4 < 2, 3.0, np.inf)[None, :] * np.ones((64, 1)))
    gr.write_buffers(frame, _frame(), light_xy=tuple(SUN_ABOVE))
    gr.write_light_view(view, slats.light_view)
    arguments = ["apply", str(frame), "--preset", "volumetric_haze", "--fov-x-deg", "50"]
    assert main([*arguments, "--light-view", str(view), "-o", str(output)]) == 0
    assert main([*arguments, "-o", str(tmp_path / "plain.exr")]) == 0
    shaded, plain = (np.asarray(gr.read_image(path))[..., :3] for path in (output, tmp_path / "plain.exr"))
    assert np.mean(shaded) < np.mean(plain)
    assert main([*arguments, "--light-view", str(tmp_path / "missing.exr"), "-o", str(tmp_path / "no.exr")]) == 1
    assert not (tmp_path / "no.exr").exists()


def test_batch_reads_each_frames_light_view_by_its_number(tmp_path, capsys):
    """`batch --light-view PATTERN`: each frame's map is the file of its number (a roof over all the medium in
    frame 1's, nothing in frame 2's, each with its own camera); a frame whose number has no map is the run's
    one-line error before anything is written."""
    roofed = _with_view(_frame(), np.zeros((64, 64)), height=1e3, scale=0.01).light_view
    for number, view in ((1, roofed), (2, _with_view(_frame(), np.full((64, 64), np.inf)).light_view)):
        gr.write_buffers(tmp_path / f"shot.{number:04d}.exr", _frame(), light_xy=tuple(SUN_ABOVE))
        gr.write_light_view(tmp_path / f"view.{number:04d}.exr", view)
    arguments = ["batch", str(tmp_path / "shot.####.exr"), "--preset", "volumetric_haze", "--fov-x-deg", "50",
                 "--layer-only", "-q"]  # fmt: skip
    assert main([*arguments, "-o", str(tmp_path / "out"), "--light-view", str(tmp_path / "view.####.exr")]) == 0
    shaded, open_sky = (np.asarray(gr.read_image(tmp_path / "out" / f"shot.{n:04d}.exr"))[..., :3] for n in (1, 2))
    assert np.mean(shaded) < 0.9 * np.mean(open_sky)  # the roof leaves the ambient light alone
    (tmp_path / "view.0002.exr").unlink()
    capsys.readouterr()
    assert main([*arguments, "-o", str(tmp_path / "none"), "--light-view", str(tmp_path / "view.####.exr")]) == 1
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "shot.0002.exr is frame 2, which" in error[0], error
    assert not list((tmp_path / "none").glob("*")) if (tmp_path / "none").exists() else True


def test_tune_serves_the_frame_with_its_light_view(tmp_path, monkeypatch, capsys):
    """`tune --light-view MAP`: the tuner draws the frame and its previews with the map (the previews keep it);
    a map that cannot be read is one line, and nothing is served."""
    frame, view = tmp_path / "frame.exr", tmp_path / "light.exr"
    slats = _with_view(_frame(), np.where(np.arange(64) % 4 < 2, 3.0, np.inf)[None, :] * np.ones((64, 1)))
    gr.write_buffers(frame, _frame(), light_xy=tuple(SUN_ABOVE))
    gr.write_light_view(view, slats.light_view)
    served = served_tuners(monkeypatch)
    arguments = ["tune", str(frame), "--preset", "volumetric_haze", "--fov-x-deg", "50", "-o", str(tmp_path / "p.json")]
    assert main([*arguments, "--light-view", str(view)]) == 0
    (tuner,) = served
    for buffers in (tuner.buffers, tuner.preview_buffers):
        np.testing.assert_array_equal(np.asarray(buffers.light_view.depth), np.asarray(slats.light_view.depth))
    capsys.readouterr()
    assert main([*arguments, "--light-view", str(tmp_path / "missing.exr")]) == 1
    assert capsys.readouterr().err.count("\n") == 1 and len(served) == 1


def test_maps_go_to_the_frames_of_their_number_or_one_to_every_frame(tmp_path):
    frames = [str(tmp_path / f"shot.{n:04d}.exr") for n in (7, 8)]
    maps = [tmp_path / f"lv_{n}.exr" for n in (8, 7)]
    for path in maps:
        path.write_bytes(b"")
    assert gr.maps_by_frame(frames, str(tmp_path / "lv_*.exr")) == {frames[0]: str(maps[1]), frames[1]: str(maps[0])}
    assert gr.maps_by_frame(frames, str(maps[0])) == dict.fromkeys(frames, str(maps[0]))
    with pytest.raises(ValueError, match="shot.0008.exr is frame 8, which"):
        gr.maps_by_frame(frames, str(tmp_path / "lv_7*.exr"))
    (tmp_path / "lv_008.exr").write_bytes(b"")
    with pytest.raises(ValueError, match="have the same frame number"):
        gr.maps_by_frame(frames, str(tmp_path / "lv_*.exr"))


def test_fit_takes_one_light_view_per_frame(tmp_path, capsys):
    frame, target = tmp_path / "frame.exr", tmp_path / "target.exr"
    gr.write_buffers(frame, _frame(), light_xy=tuple(SUN_ABOVE))
    gr.write_image(target, np.full((18, 32, 3), 0.3, np.float32))
    arguments = ["fit", str(frame), str(target), "-o", str(tmp_path / "p.json"), "--light-view", str(frame)]
    assert main([*arguments, "--light-view", str(frame)]) == 1
    assert "give --light-view once per frame (1 frames) or not at all, got 2" in capsys.readouterr().err
    assert not (tmp_path / "p.json").exists()


@pytest.mark.parametrize("light", [{"type": "directional", "direction": [0.3, 1.0, 0.1]},
                                   {"type": "point", "position": [1.5, 12.0, -9.0]}], ids=["sun", "lamp"])
def test_a_scenes_light_view_shades_what_lies_under_an_occluder_outside_the_frame(light):
    """`raster.light_view`: a ball above the frame (out of its view) shades the ground under it, which the frame
    shows, and not the ground beside that; the sun's view and a lamp's, through the frame's own view space."""
    scene, camera = gr.scene_from_dict({
        "camera": {"position": [0, 1.5, 0], "target": [-2, 0.5, -6], "up": [0, 1, 0], "fov_x_deg": 50, "width": 48,
                   "height": 27},
        "lights": [light],
        "objects": [{"type": "sphere", "center": [0, 5, -6], "radius": 1.5},  # above the frame's top edge
                    {"type": "sphere", "center": [0, -1000, 0], "radius": 1000}],  # the ground
    })  # fmt: skip
    ball = np.asarray([0.0, 5.0, -6.0])
    if light["type"] == "directional":
        toward = np.asarray(light["direction"]) / np.linalg.norm(light["direction"])
        shadow = ball - (ball[1] / toward[1]) * toward  # the ground under the ball, along the sunlight
    else:
        lamp = np.asarray(light["position"], np.float64)
        shadow = lamp + (ball - lamp) * lamp[1] / (lamp[1] - ball[1])
    ground = np.stack([shadow, shadow + [6.0, 0.0, 0.0]]) + [0.0, 0.02, 0.0]  # just above the ground
    points = camera.to_view(jnp.asarray(ground, jnp.float32))
    xy, _, in_front = gr.project_point(camera, jnp.asarray(ball, jnp.float32))
    assert bool(in_front) and float(xy[1]) < 0 and float(points[0, 2]) > 0  # the ball above the frame, its shadow in view
    view = gr.light_view(scene, camera, reach=40.0, size=256)
    under, beside = np.asarray(gr.light_view_visibility(points, light_view=view))
    assert under == 0.0 and beside > 0.99  # beside: the ground a ramp's share below it at a grazing angle


@pytest.mark.slow
def test_render_writes_a_light_view_that_apply_reads(tmp_path):
    scene = tmp_path / "scene.json"
    scene.write_text(json.dumps({
        "camera": {"position": [0, 1.5, 0], "target": [-2, 0.5, -6], "up": [0, 1, 0], "fov_x_deg": 50, "width": 48,
                   "height": 27},
        "lights": [{"type": "directional", "direction": [0.3, 1.0, 0.1]}],
        "objects": [{"type": "sphere", "center": [0, 5, -6], "radius": 1.5},
                    {"type": "sphere", "center": [0, -1000, 0], "radius": 1000}],
    }))  # fmt: skip
    frame, view = tmp_path / "frame.exr", tmp_path / "light.exr"
    assert main(["render", str(scene), "-o", str(frame), "--light-view", str(view), "--light-view-reach", "30"]) == 0
    seen = gr.read_light_view(view)
    assert seen.projection == "perspective" and seen.depth.shape == (1024, 1024) and np.isfinite(seen.depth).any()
    assert main(["apply", str(frame), "--preset", "volumetric_haze", "--light-view", str(view),
                 "-o", str(tmp_path / "out.exr")]) == 0  # fmt: skip
    assert main(["render", str(scene), "-o", str(tmp_path / "f2.exr"), "--light-view", str(tmp_path / "f2.exr")]) == 1
    assert not (tmp_path / "f2.exr").exists()
