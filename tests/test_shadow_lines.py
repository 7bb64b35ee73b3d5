"""Shadows read along lines through the light (kernels/shadow_lines.py) against shadow rays traced in 3-D by NumPy.

The loop knows nothing of lines, bins or the coordinate `s`: it walks each shadow ray from points along a
segment toward the light in small steps, projects every step onto the screen and tests the texel it lands in
(its slab `[D, D * (1 + thickness)]` along that texel's camera ray, hard faces; sky, emitters and points
off screen or behind the camera block nothing, but in a frame read as closed beyond its edges a walk toward a
light in front that leaves the screen in front of the far face of the last texel it crossed is blocked there).
The kernel, fine-grained, must agree with it everywhere but at the slabs' edges, for the sun and a point light,
in front of the camera on screen, far off screen and behind the camera, open and closed.
"""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from frames import slow_where
from jax.test_util import check_grads

from godrays_jax.kernels.shadow_lines import (
    line_coordinate,
    segment_visibility_by_lines,
)

HEIGHT, WIDTH, FOV = 12, 16, 60.0
THICKNESS, MAX_DISTANCE, SEGMENTS = 2.0, 80.0, 6  # thick slabs: a small frame shows long shadows
FINE = dict(num_lines=1024, num_bins=384, cell_px=0.25)


def _focal():
    return 0.5 * WIDTH / math.tan(math.radians(FOV) / 2)


def _ray(x, y):
    f = _focal()
    return np.stack([(np.asarray(x) - 0.5 * WIDTH) / f, (0.5 * HEIGHT - np.asarray(y)) / f, np.ones_like(x)], -1)


def _depth(sky=False):
    """A wall (or sky) behind two blocks at different depths: the blocks' slabs cast the shadows."""
    depth = np.full((HEIGHT, WIDTH), np.inf if sky else 60.0)
    depth[3:7, 4:8] = 20.0
    depth[6:10, 10:13] = 12.0
    return depth


def _light(point):
    """The light's `(light_xy, light_depth, in_front)` for a camera-space point, or a direction for the sun."""
    point = np.asarray(point, float)
    f, in_front = _focal(), point[2] > 0
    z = abs(point[2])
    xy = np.asarray([0.5 * WIDTH + f * point[0] / z, 0.5 * HEIGHT - f * point[1] / z])
    return xy, float(np.linalg.norm(point)), bool(in_front)


def _segments(depth):
    x, y = np.meshgrid(np.arange(WIDTH) + 0.5, np.arange(HEIGHT) + 0.5)
    end = np.minimum(np.where(np.isfinite(depth), depth, MAX_DISTANCE), MAX_DISTANCE) * 0.98
    bounds = end[..., None] * np.linspace(0.0, 1.0, SEGMENTS + 1) ** 1.5
    return np.stack([x, y], -1), bounds[..., :-1], bounds[..., 1:]


def _loop_visibility(depth, pixel_xy, lower, upper, light_point, sun, points_per_segment=16, steps=1000, closed=False):
    """The mean over each segment of whether its points see the light, by marching each shadow ray in 3-D;
    `closed`: the frame read as closed beyond its edges."""
    f = _focal()
    light_point = np.asarray(light_point, float)
    unit = light_point / np.linalg.norm(light_point)
    emitter_limit = np.inf if sun else np.linalg.norm(light_point)
    reach = np.max(upper) + np.max(depth[np.isfinite(depth)]) * (1 + THICKNESS)
    out = np.zeros(lower.shape)
    u = (np.arange(steps) + 0.5) / steps
    for j in range(HEIGHT):
        for i in range(WIDTH):
            view = _ray(*pixel_xy[j, i])
            view = view / np.linalg.norm(view)
            # Every segment's points at once (segment, point), each walked in `steps` steps.
            fraction = (np.arange(points_per_segment) + 0.5) / points_per_segment
            t = lower[j, i, :, None] + (upper[j, i, :, None] - lower[j, i, :, None]) * fraction
            start = t[..., None] * view
            # Toward a point light up to it; toward the sun past every slab's far face (no point of the walk farther
            # from the camera than the deepest face can be in a slab).
            end = np.broadcast_to(light_point, start.shape) if not sun else start + unit * reach
            walk = start[..., None, :] * (1 - u[:, None]) + end[..., None, :] * u[:, None]
            ahead = walk[..., 2] > 1e-6
            z = np.where(ahead, walk[..., 2], 1.0)
            qx = 0.5 * WIDTH + f * walk[..., 0] / z
            qy = 0.5 * HEIGHT - f * walk[..., 1] / z
            on = ahead & (qx >= 0) & (qx < WIDTH) & (qy >= 0) & (qy < HEIGHT)
            col, row = np.clip(qx, 0, WIDTH - 1).astype(int), np.clip(qy, 0, HEIGHT - 1).astype(int)
            texel = np.where(on, depth[row, col], np.inf)
            along = np.linalg.norm(walk, axis=-1)
            blocks = np.isfinite(texel) & (texel * (1 + THICKNESS) < emitter_limit)
            blocked = np.any(blocks & (along >= texel) & (along <= texel * (1 + THICKNESS)), axis=-1)
            if closed and light_point[2] > 0:
                # Where a walk leaves the screen for good: its last step on it, and that step's texel.
                last = on.shape[-1] - 1 - np.argmax(on[..., ::-1], axis=-1)
                leaves = np.any(on, axis=-1) & ~np.take_along_axis(on, np.minimum(last + 1, on.shape[-1] - 1)[..., None],
                                                                   axis=-1)[..., 0] & (last + 1 < on.shape[-1])
                edge = np.take_along_axis(np.where(on, depth[row, col], np.inf), last[..., None], axis=-1)[..., 0]
                at = np.take_along_axis(along, last[..., None], axis=-1)[..., 0]
                edge_blocks = np.isfinite(edge) & (edge * (1 + THICKNESS) < emitter_limit)
                blocked |= leaves & edge_blocks & (at <= edge * (1 + THICKNESS))
            out[j, i] = 1.0 - np.mean(blocked, axis=-1)
    return out


LIGHTS = {
    # name: (camera-space point (a direction for the sun), sun, sky)
    "sun in front": ((0.35, 0.3, 1.0), True, True),
    "point light in front": ((6.0, 5.0, 45.0), False, False),
    "sun far off screen": ((-3.0, 0.4, 1.0), True, True),
    "sun behind the camera": ((0.5, 0.36, -1.0), True, True),
    "point light behind the camera": ((45.0, 32.4, -90.0), False, True),
}


@pytest.mark.parametrize(
    "name",
    slow_where(LIGHTS, {"point light in front", "point light behind the camera", "sun behind the camera",
                        "sun far off screen"}),
)
def test_matches_shadow_rays_traced_in_3d(name):
    point, sun, sky = LIGHTS[name]
    depth = _depth(sky)
    pixel_xy, lower, upper = _segments(depth)
    light_xy, light_depth, in_front = _light(point)
    expected = _loop_visibility(depth, pixel_xy, lower, upper, point, sun)

    def kernel(light_in_front):
        return np.asarray(segment_visibility_by_lines(
            jnp.asarray(depth), light_xy, jnp.asarray(pixel_xy), jnp.asarray(lower), jnp.asarray(upper), fov_x_deg=FOV,
            light_depth=math.inf if sun else light_depth, light_in_front=light_in_front, thickness=THICKNESS,
            edge_softness=0.01, max_distance=MAX_DISTANCE, **FINE,
        ))  # fmt: skip

    got = kernel(in_front)
    # The light's side traced (a batch's frames, each its own side: the cells scanned in the light's order) reads
    # as the side given as a Python bool.
    np.testing.assert_allclose(kernel(jnp.asarray(in_front)), got, rtol=1e-6, atol=1e-6)
    # The scene casts shadows the loop sees, and the kernel agrees but at the slabs' edges.
    assert 0.03 < np.mean(expected < 0.5) < 0.95
    assert np.mean(np.abs(got - expected)) < 0.04, np.mean(np.abs(got - expected))
    assert np.mean(np.abs(got - expected) > 0.5) < 0.02
    if not in_front:
        # The loop tells a light behind the camera from its mirror image in front.
        assert np.mean(np.abs(kernel(True) - expected)) > 0.04


CLOSED_LIGHTS = {
    "sun off the top edge": (-0.1, 1.0, 1.0),
    "sun far off the side": (-3.0, 0.4, 1.0),
}


@pytest.mark.parametrize("name", slow_where(CLOSED_LIGHTS, {"sun far off the side"}))
def test_a_closed_frame_shades_the_rays_that_leave_it_in_front_of_its_edge(name):
    """A room's frame (no sky), the light in front off screen: read closed (`enclosed=1`), a shadow ray that leaves
    the screen in front of the far face of the surface seen where it leaves is shaded, as the traced loop says; read
    open, the same frame lets it through."""
    point = CLOSED_LIGHTS[name]
    depth = _depth()
    pixel_xy, lower, upper = _segments(depth)
    light_xy, _, in_front = _light(point)
    expected = _loop_visibility(depth, pixel_xy, lower, upper, point, True, closed=True)

    def kernel(enclosed):
        return np.asarray(segment_visibility_by_lines(
            jnp.asarray(depth), light_xy, jnp.asarray(pixel_xy), jnp.asarray(lower), jnp.asarray(upper), fov_x_deg=FOV,
            light_in_front=in_front, thickness=THICKNESS, edge_softness=0.01, max_distance=MAX_DISTANCE,
            enclosed=enclosed, **FINE,
        ))  # fmt: skip

    got, open_reading = kernel(1.0), kernel(0.0)
    assert np.mean(np.abs(got - expected)) < 0.04, np.mean(np.abs(got - expected))
    assert np.mean(np.abs(got - expected) > 0.5) < 0.02
    # Closed, most of the room is shaded where open it was lit; halfway closed (the faces halfway to the eye), between.
    assert np.mean(open_reading - got) > 0.3
    half = kernel(0.5)
    assert np.all(half >= got - 1e-6) and np.all(half <= open_reading + 1e-6)
    assert np.mean(open_reading - half) > 0.05 and np.mean(half - got) > 0.05


@pytest.mark.xfail(strict=True, reason="the lines' table keeps each cell's maximum, not their union (docs/findings.md)")
def test_a_wall_of_thin_slabs_between_the_points_and_the_sun_shades_them_at_the_default_table():
    """A wall that fills the frame, receding to the right, the sun beyond it: every point in front of it is in its
    shadow, as a traced ray says. Its slabs are thin (a room's walls, as a fit of one finds them) against the default
    table's bins, so each cell's interval of `s` is narrower than a bin and the wall's cover is the union of
    consecutive cells' intervals: with the faces inside each interval the wall reads as a sawtooth, and a third of
    the segments see a twentieth of the light or more (docs/findings.md, "A room's walls read along lines let a
    sawtooth of light through")."""
    x = (np.arange(WIDTH) + 0.5) / WIDTH
    depth = np.broadcast_to(30.0 + 20.0 * x, (HEIGHT, WIDTH)).copy()
    pixel_xy, lower, upper = _segments(depth)
    lower, upper = 0.1 * depth[..., None] + 0.8 * lower, 0.1 * depth[..., None] + 0.8 * upper  # in front of it
    light_xy, _, _ = _light((0.1, 0.05, 1.0))
    got = np.asarray(segment_visibility_by_lines(
        jnp.asarray(depth), light_xy, jnp.asarray(pixel_xy), jnp.asarray(lower), jnp.asarray(upper), fov_x_deg=FOV,
        thickness=0.02, edge_softness=0.05, max_distance=MAX_DISTANCE,
    ))  # fmt: skip
    # Thick slabs, the same table: the wall shades every segment (the test's geometry is right).
    assert np.max(np.asarray(segment_visibility_by_lines(
        jnp.asarray(depth), light_xy, jnp.asarray(pixel_xy), jnp.asarray(lower), jnp.asarray(upper), fov_x_deg=FOV,
        thickness=0.2, edge_softness=0.05, max_distance=MAX_DISTANCE,
    ))) < 0.05  # fmt: skip
    assert np.mean(got) < 0.01 and np.mean(got > 0.05) < 0.01, (np.mean(got), np.mean(got > 0.05))


@pytest.mark.slow
def test_many_pixels_read_at_once_as_each_alone():
    """A frame's worth of pixels (more than the kernel reads in one chunk, and not a multiple of it) reads as the
    same pixels read a row at a time: the chunks hold each pixel's own reads, in place."""
    depth = _depth()
    light_xy, light_depth, in_front = _light((20.0, 30.0, 70.0))
    rng = np.random.default_rng(0)
    rows = 131
    pixel_xy = np.stack([rng.uniform(0, WIDTH, (rows, 129)), rng.uniform(0, HEIGHT, (rows, 129))], -1)
    lower = rng.uniform(0, 0.6 * MAX_DISTANCE, (rows, 129, 3))
    upper = lower + rng.uniform(0, 0.4 * MAX_DISTANCE, (rows, 129, 3))
    read = functools.partial(
        segment_visibility_by_lines, jnp.asarray(depth, jnp.float32), light_xy, fov_x_deg=FOV, light_depth=light_depth,
        light_in_front=in_front, thickness=THICKNESS, edge_softness=0.05, max_distance=MAX_DISTANCE,
    )  # fmt: skip
    at_once = np.asarray(read(*(jnp.asarray(a, jnp.float32) for a in (pixel_xy, lower, upper))))
    # A row a time, as a batch of rows: each row its own call of the kernel, the table (which no row changes) built
    # once for them all.
    by_row = np.asarray(jax.vmap(read)(*(jnp.asarray(a[:, None], jnp.float32) for a in (pixel_xy, lower, upper))))[:, 0]
    assert 0.05 < np.mean(at_once < 0.5) < 0.95  # the pixels see shadows and light
    np.testing.assert_allclose(at_once, by_row, atol=1e-4)  # float32 rounding of differently shaped programs


def test_line_coordinate_is_kept_along_a_shadow_ray(x64):
    """Every point of a shadow ray toward a point light (and toward the sun) has the same `s`."""
    light = np.asarray([3.0, 2.0, 20.0])
    for sun in (False, True):
        start = np.asarray([-1.0, 0.5, 7.0])
        toward = light / np.linalg.norm(light)
        ends = [start + u * ((light - start) if not sun else toward * 30.0) for u in (0.0, 0.3, 0.7)]
        values = []
        for point in ends:
            distance = np.linalg.norm(point)
            cosine = point @ toward / distance
            sine = np.linalg.norm(np.cross(point / distance, toward))
            values.append(float(line_coordinate(distance, sine, cosine, 0.0 if sun else 1.0 / np.linalg.norm(light))))
        np.testing.assert_allclose(values, values[0], rtol=1e-12)


def _small(dtype):
    depth = np.full((6, 8), 30.0)
    depth[1:4, 2:5] = 9.0
    depth[0, :] = np.inf
    x, y = np.meshgrid(np.arange(8) + 0.5, np.arange(6) + 0.5)
    bounds = np.linspace(0.5, 25.0, 6)[None, None, :] * np.linspace(0.9, 1.1, 8)[None, :, None] * np.ones((6, 1, 1))
    return (jnp.asarray(depth, dtype), jnp.asarray(np.stack([x, y], -1), dtype), jnp.asarray(bounds[..., :-1], dtype),
            jnp.asarray(bounds[..., 1:], dtype))  # fmt: skip


@pytest.mark.parametrize("light_depth", slow_where([40.0, math.inf], {40.0}))
def test_gradients_float64(x64, light_depth):
    """The derivatives in the slabs, the light and the medium's reach against central differences (bins and lines
    held where they lie: a sampling choice)."""
    depth, pixel_xy, lower, upper = _small(jnp.float64)

    def visibility(light_xy, thickness, edge_softness, inverse_depth):
        return segment_visibility_by_lines(
            depth, light_xy, pixel_xy, lower, upper, fov_x_deg=60.0,
            light_depth=1.0 / inverse_depth if math.isfinite(light_depth) else math.inf, thickness=thickness,
            edge_softness=edge_softness, max_distance=30.0, num_lines=64, num_bins=48,
        )  # fmt: skip

    # The light on no line through a pixel centre: the lines' interpolation has kinks there.
    start = (jnp.asarray([6.37, 1.71]), jnp.float64(0.4), jnp.float64(0.2), jnp.float64(1.0 / 40.0))
    check_grads(visibility, start, order=1, modes=("fwd", "rev"), eps=1e-6, atol=1e-4, rtol=1e-3)


DEGENERATE = {
    "on a pixel centre": dict(light_xy=(3.5, 2.5)),
    "on the frame's centre": dict(light_xy=(4.0, 3.0)),
    "far off screen": dict(light_xy=(1e9, -3e8)),
    "just off the edge": dict(light_xy=(8.0001, 2.0)),
    "behind the camera": dict(light_xy=(3.0, 2.0), light_in_front=False),
    "behind, far off screen": dict(light_xy=(-4e8, 1e9), light_in_front=False),
    "at the camera": dict(light_xy=(3.0, 2.0), light_depth=1e-6),
}


@pytest.mark.parametrize("name", DEGENERATE)
def test_degenerate_lights_finite_values_and_gradients(name):
    """Finite values and gradients (the light's side traced), on surfaces and on a frame all sky, where nothing
    is shaded."""
    case = DEGENERATE[name]
    depth, pixel_xy, lower, upper = _small(jnp.float32)

    @jax.jit
    @functools.partial(jax.value_and_grad, argnums=(0, 1, 2, 3, 4))
    def total(light_xy, thickness, edge_softness, light_depth, depth, light_in_front):
        return jnp.sum(segment_visibility_by_lines(
            depth, light_xy, pixel_xy, lower, upper, fov_x_deg=60.0, light_depth=light_depth,
            light_in_front=light_in_front, thickness=thickness, edge_softness=edge_softness, max_distance=30.0,
            num_lines=32, num_bins=24))  # fmt: skip

    for frame in (depth, jnp.full_like(depth, jnp.inf)):
        value, grads = total(jnp.asarray(case["light_xy"], jnp.float32), 0.3, 0.05,
                             jnp.float32(case.get("light_depth", 50.0)), frame,
                             jnp.asarray(case.get("light_in_front", True)))  # fmt: skip
        assert np.isfinite(float(value)), name
        assert all(np.all(np.isfinite(np.asarray(g))) for g in grads), name
    sky = segment_visibility_by_lines(
        jnp.full_like(depth, jnp.inf), jnp.asarray(case["light_xy"], jnp.float32), pixel_xy, lower, upper,
        fov_x_deg=60.0, light_in_front=case.get("light_in_front", True), thickness=0.3, edge_softness=0.05,
        max_distance=30.0, num_lines=32, num_bins=24,
    )  # fmt: skip
    np.testing.assert_array_equal(np.asarray(sky), 1.0)


def test_bad_options_name_the_argument():
    depth, pixel_xy, lower, upper = _small(jnp.float32)
    options = dict(fov_x_deg=60.0, thickness=0.3, edge_softness=0.05, max_distance=30.0)
    for bad, name in ((dict(num_lines=1), "num_lines"), (dict(num_bins=2.0), "num_bins"), (dict(cell_px=0), "cell_px")):
        with pytest.raises(ValueError, match=name):
            segment_visibility_by_lines(depth, (3.0, 2.0), pixel_xy, lower, upper, **options, **bad)
    with pytest.raises(ValueError, match="upper"):
        segment_visibility_by_lines(depth, (3.0, 2.0), pixel_xy, lower, upper[:2], **options)
