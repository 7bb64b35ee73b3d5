"""ground_layer_start: a fog layer read from a frame's depth (a ground plane below the camera); enclosed_start: a
medium bounded to the room a frame without sky shows; thin_slabs_start: where a light view casts the shadows."""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

import godrays_jax as gr
from godrays_jax.app.fit_command import fit_starts
from godrays_jax.effects.fields import field_metadata, field_value
from godrays_jax.kernels.lens import view_directions
from godrays_jax.pipeline.frame_start import (
    GROUND_PERCENTILE,
    THIN_SLABS,
    closed_room_start,
    enclosed_start,
    ground_layer_start,
    thin_slabs_room_start,
    thin_slabs_start,
)

HEIGHT, WIDTH, FOV = 18, 32, 50.0


def _frame(camera_height=1.5, far=60.0):
    """Ground `camera_height` below the camera up to `far` away along the ray, sky beyond and above the horizon."""
    up = np.asarray(view_directions(HEIGHT, WIDTH, fov_x_deg=FOV))[..., 1]
    with np.errstate(divide="ignore"):
        depth = np.where(up < 0, camera_height / -up, np.inf)
    depth = np.where(depth <= far, depth, np.inf).astype(np.float32)
    coverage = np.isfinite(depth).astype(np.float32)
    color = np.full((HEIGHT, WIDTH, 3), 0.2, np.float32)
    return gr.Buffers(color=jnp.asarray(color), depth=jnp.asarray(depth), coverage=jnp.asarray(coverage)), depth


def _values(effect):
    return [float(field_value(effect, name)) for name in ("layer_top", "medium.extinction", "medium.max_distance")]


def test_the_layer_reaches_as_high_above_the_camera_as_the_ground_lies_below():
    frame, depth = _frame()
    start = ground_layer_start(gr.preset("volumetric_haze"), frame)
    surfaces = depth[np.isfinite(depth)]
    np.testing.assert_allclose(_values(start), [1.5, 1 / np.median(surfaces), surfaces.max()], rtol=1e-4)
    # Everything else is the effect's; several frames pool their surfaces.
    assert float(start.medium.anisotropy) == pytest.approx(0.76) and start.num_view_steps == 16
    higher, higher_depth = _frame(camera_height=3.0)
    twice = ground_layer_start(gr.preset("volumetric_haze"), [frame, higher])
    # Every ground pixel lies 1.5 (first frame) or 3.0 (second) below the camera; the median depth of the pooled
    # surfaces is neither frame's own.
    pooled = np.concatenate([surfaces, higher_depth[np.isfinite(higher_depth)]])
    heights = np.concatenate([np.full(surfaces.size, -1.5), np.full(pooled.size - surfaces.size, -3.0)])
    expected = [-np.percentile(heights, GROUND_PERCENTILE), 1 / np.median(pooled), pooled.max()]
    np.testing.assert_allclose(_values(twice), expected, rtol=1e-4)


def test_values_are_clipped_into_their_bounds():
    near = _values(ground_layer_start(gr.preset("physically_based"), _frame(camera_height=0.01)[0]))
    high = _values(ground_layer_start(gr.preset("physically_based"), _frame(camera_height=500.0, far=1e6)[0]))
    assert near[0] == pytest.approx(0.01, rel=1e-3) and near[1] == 1.0  # an optical depth of 1 in 2 cm: above 1
    assert high[0] == pytest.approx(500.0, rel=1e-3) and high[2] == 1e4  # the horizon's ground 3e4 away


def test_no_layer_without_surfaces_below_the_camera_or_the_fields():
    frame, depth = _frame()
    sky = gr.Buffers(color=frame.color, depth=jnp.full_like(frame.depth, jnp.inf), coverage=jnp.zeros_like(frame.coverage))
    ceiling = gr.Buffers(color=frame.color, depth=jnp.asarray(depth[::-1].copy()), coverage=frame.coverage[::-1])
    assert ground_layer_start(gr.preset("volumetric_haze"), sky) is None
    assert ground_layer_start(gr.preset("volumetric_haze"), ceiling) is None
    assert ground_layer_start(gr.GodRays(), frame) is None


def test_the_fit_command_races_the_presets_and_a_ground_layer_on_each():
    frame, _ = _frame()
    given = dataclasses.replace(gr.preset("volumetric_haze"), fov_x_deg=np.float32(60.0))  # as the command sets it
    names, starts = fit_starts(given, [frame], 60.0)
    assert names == [
        "preset physically_based", "preset volumetric_haze",
        *[f"the ground layer estimated from the frame, on the other fields of {name}"
          for name in ("the start given", "preset physically_based", "preset volumetric_haze")],
    ]  # fmt: skip
    assert all(float(start.fov_x_deg) == 60.0 for start in starts[:2])  # the frame's, for the layers' heights
    assert float(starts[3].medium.anisotropy) == float(gr.preset("physically_based").medium.anisotropy)
    assert len({float(start.layer_top) for start in starts[2:]}) == 1  # each read with the frame's field of view
    assert not any("ground layer" in name for name in fit_starts(gr.GodRays(), [frame], None)[0])  # no layer to read


def test_a_frame_without_sky_starts_a_medium_bounded_to_its_room():
    """The farthest wall bounds the medium, the median surface sets its extinction, and nothing caps its top; a
    frame with sky, or with a surface at the eye, gives no such start, and `fit_starts` races it last."""
    frame, depth = _frame()
    room_depth = np.where(np.isfinite(depth), depth, 9.0).astype(np.float32)  # walls 9 units away where sky was
    room = gr.Buffers(color=frame.color, depth=jnp.asarray(room_depth), coverage=jnp.ones_like(frame.coverage))
    start = enclosed_start(gr.preset("volumetric_haze"), room)
    layer_top, extinction, max_distance = _values(start)
    assert max_distance == pytest.approx(float(np.max(room_depth)), rel=1e-6)
    assert extinction == pytest.approx(1.0 / float(np.median(room_depth)), rel=1e-6)
    assert layer_top == field_metadata(start)["layer_top"].bounds[1]
    assert float(start.medium.anisotropy) == float(gr.preset("volumetric_haze").medium.anisotropy)
    at_the_eye = gr.Buffers(color=frame.color, depth=jnp.zeros_like(room.depth), coverage=room.coverage)
    for other in (frame, at_the_eye):
        assert enclosed_start(gr.preset("volumetric_haze"), other) is None
    names, starts = fit_starts(gr.preset("volumetric_haze"), [room], FOV)
    index = next(k for k, name in enumerate(names) if name.startswith("the medium of the room the frames show"))
    assert _values(starts[index]) == _values(start)
    assert not any("room" in name for name in fit_starts(gr.preset("volumetric_haze"), [frame], FOV)[0])


def test_a_frame_with_a_light_view_starts_from_thin_slabs():
    """Thin slabs and every other field the start given's, for frames of which one has a light view; none without,
    or for an effect without slabs; `fit_starts` races it before the same slabs in a medium ending at the
    farthest wall."""
    frame, _ = _frame()
    view = gr.LightView(depth=jnp.full((8, 8), jnp.inf), from_camera=jnp.eye(3, 4), scale=1.0)
    seen = dataclasses.replace(frame, light_view=view)
    effect = gr.preset("volumetric_haze")
    start = thin_slabs_start(effect, [frame, seen])
    assert float(start.thickness) == pytest.approx(THIN_SLABS) and start.thickness.dtype == effect.thickness.dtype
    assert float(start.medium.extinction) == float(effect.medium.extinction)
    assert thin_slabs_start(effect, [frame]) is None and thin_slabs_start(gr.preset("xna_crepuscular"), seen) is None
    names, starts = fit_starts(effect, [seen], FOV)
    assert names[-2].startswith("thin slabs (the light view") and _values(starts[-2]) == _values(start)
    assert not any(name.startswith("thin slabs") for name in fit_starts(effect, [frame], FOV)[0])


def test_a_frame_with_a_light_view_also_starts_from_thin_slabs_in_a_medium_ending_at_its_farthest_wall():
    """`thin_slabs_room_start`: `thin_slabs_start` with `medium.max_distance` the farthest finite depth above 0 of
    the frames (clipped into its bounds); none without a light view or without such a depth; raced last."""
    frame, _ = _frame()
    view = gr.LightView(depth=jnp.full((8, 8), jnp.inf), from_camera=jnp.eye(3, 4), scale=1.0)
    seen = dataclasses.replace(frame, light_view=view)
    effect = gr.preset("volumetric_haze")
    start = thin_slabs_room_start(effect, [frame, seen])
    depth = np.concatenate([np.asarray(f.ray_depth(jnp.asarray(effect.fov_x_deg))).ravel() for f in (frame, seen)])
    farthest = np.max(depth[np.isfinite(depth) & (depth > 0)])
    assert float(start.medium.max_distance) == pytest.approx(farthest, rel=1e-6) and farthest < 100.0
    assert float(start.thickness) == pytest.approx(THIN_SLABS)
    assert float(start.medium.extinction) == float(effect.medium.extinction)
    assert thin_slabs_room_start(effect, [frame]) is None
    sky = dataclasses.replace(seen, depth=jnp.full_like(seen.depth, jnp.inf))
    assert thin_slabs_room_start(effect, [sky]) is None
    names, starts = fit_starts(effect, [seen], FOV)
    assert names[-1].startswith("thin slabs and a medium ending at the farthest wall (the light view")
    assert _values(starts[-1]) == _values(start)


def test_a_room_read_as_closed_starts_from_thin_slabs_and_its_farthest_wall():
    """A frame that the fog reads as closed beyond its edges (a room whose window shows a little sky) starts with
    thin slabs and the medium ending at its farthest surface, every other field the start given's; a frame with
    more sky, or with a light view, gives no such start; `fit_starts` races it last."""
    frame, depth = _frame()
    room_depth = np.where(np.isfinite(depth), depth, 9.0).astype(np.float32)
    room_depth[2:4, 10:13] = np.inf  # a window: 6 of the frame's 576 pixels show the sky
    room = gr.Buffers(color=frame.color, depth=jnp.asarray(room_depth), coverage=jnp.ones_like(frame.coverage))
    effect = gr.preset("volumetric_haze")
    start = closed_room_start(effect, room)
    assert float(start.thickness) == pytest.approx(THIN_SLABS)
    assert float(start.medium.max_distance) == pytest.approx(float(np.max(room_depth[np.isfinite(room_depth)])))
    assert float(start.medium.extinction) == float(effect.medium.extinction)
    view = gr.LightView(depth=jnp.full((8, 8), jnp.inf), from_camera=jnp.eye(3, 4), scale=1.0)
    at_the_eye = gr.Buffers(color=frame.color, depth=jnp.zeros_like(room.depth), coverage=room.coverage)
    # A third sky; a map says what lies beyond; surfaces at the eye are no room.
    for other in (frame, dataclasses.replace(room, light_view=view), at_the_eye):
        assert closed_room_start(effect, other) is None
    # Wholly closed (at most 5 % sky) it is the start `godrays-jax fit` takes alone; a frame 10 % sky is closed in
    # part, and only races it.
    assert closed_room_start(effect, room, wholly=True) is not None
    part = room_depth.copy()
    part.flat[: part.size // 10] = np.inf
    partly = gr.Buffers(color=frame.color, depth=jnp.asarray(part), coverage=room.coverage)
    assert closed_room_start(effect, partly) is not None and closed_room_start(effect, partly, wholly=True) is None
    names, starts = fit_starts(effect, [room], FOV)
    assert "farthest wall" in names[-1] and float(starts[-1].thickness) == pytest.approx(THIN_SLABS)
    assert not any("farthest wall" in name for name in fit_starts(effect, [frame], FOV)[0])
