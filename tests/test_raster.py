"""Rasterizer against analytic values (NumPy ray casting, supersampled coverage).

Compilation is slow on small CPUs, so every render here shares one scene
structure (two spheres and a one-triangle mesh), one image size and one tile
capacity: moving objects changes values, not the compiled program.
"""

import json
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from frames import slow_where

from godrays_jax.primitives.camera import Camera, project_point
from godrays_jax.raster import DirectionalLight, Material, Mesh, PointLight, Scene, Sky, Sphere
from godrays_jax.raster import load_obj, load_scene, render
from godrays_jax.raster import geometry, glow_pass, shading, tile_loop, visibility

WIDTH, HEIGHT, FOV = 32, 24, 60.0
CAPACITY = 4
FAR_AWAY = (0.0, 0.0, 500.0)  # behind the camera: not drawn
TRIANGLE = np.array([[-1.5, -1.0, -6.0], [1.0, -1.2, -6.0], [-0.2, 1.3, -6.0]], np.float32)


def _camera():
    return Camera(position=[0, 0, 0], target=[0, 0, -1], up=[0, 1, 0], fov_x_deg=FOV, width=WIDTH, height=HEIGHT)


def _scene(sun_center=(0.4, 0.2, -4.0), sun_radius=0.8, other_center=FAR_AWAY, triangle_offset=(0.0, 0.0, 500.0)):
    return Scene(
        objects=(
            Sphere(center=sun_center, radius=sun_radius, material=Material(albedo=(0, 0, 0), emission=(3.0, 2.0, 1.0))),
            Sphere(center=other_center, radius=0.5, material=Material(albedo=(0.2, 0.4, 0.9))),
            Mesh(vertices=TRIANGLE, faces=[[0, 1, 2]], translation=triangle_offset, material=Material(albedo=(1.0, 0.2, 0.1))),
        ),
        light=DirectionalLight(direction=(0.0, 0.0, 1.0)),
        sun=0,
    )


def _render(scene):
    return render(scene, _camera(), with_glow_pass=False, tile_capacity=CAPACITY)


def _pixel_rays(samples=1):
    """Unit world directions through `samples x samples` points of every pixel: (H, W, s*s, 3)."""
    focal = WIDTH / 2 / math.tan(math.radians(FOV) / 2)
    offsets = (np.arange(samples) + 0.5) / samples
    y = np.arange(HEIGHT)[:, None, None, None] + offsets[None, None, :, None]
    x = np.arange(WIDTH)[None, :, None, None] + offsets[None, None, None, :]
    y, x = np.broadcast_arrays(y, x)
    rays = np.stack([(x - WIDTH / 2) / focal, (HEIGHT / 2 - y) / focal, -np.ones_like(x)], axis=-1)
    rays = rays.reshape(HEIGHT, WIDTH, samples * samples, 3)
    return rays / np.linalg.norm(rays, axis=-1, keepdims=True)


def _sphere_hits(center, radius, rays):
    along = rays @ np.asarray(center)
    squared = radius**2 - (np.dot(center, center) - along**2)
    return np.where((squared >= 0) & (along > 0), along - np.sqrt(np.maximum(squared, 0)), np.inf)


def _triangle_hits(corners, rays):
    """Moeller-Trumbore, one ray at a time (slow and obvious)."""
    hits = np.full(rays.shape[:-1], np.inf)
    for index in np.ndindex(*rays.shape[:-1]):
        direction = rays[index]
        edge1, edge2 = corners[1] - corners[0], corners[2] - corners[0]
        p = np.cross(direction, edge2)
        det = edge1 @ p
        if abs(det) < 1e-12:
            continue
        s = -corners[0]
        u = (s @ p) / det
        q = np.cross(s, edge1)
        v = (direction @ q) / det
        t = (edge2 @ q) / det
        if u >= 0 and v >= 0 and u + v <= 1 and t > 0:
            hits[index] = t
    return hits


def _check_against_reference(buffers, hits_centre, hits_supersampled):
    depth = np.asarray(buffers.depth)
    expected_depth = hits_centre[..., 0]
    np.testing.assert_array_equal(np.isfinite(depth), np.isfinite(expected_depth))
    finite = np.isfinite(expected_depth)
    np.testing.assert_allclose(depth[finite], expected_depth[finite], rtol=1e-4)
    expected_coverage = np.isfinite(hits_supersampled).mean(axis=-1)
    coverage = np.asarray(buffers.coverage)
    assert coverage.min() >= 0 and coverage.max() <= 1
    # The supersampled reference misses slivers at corners: allow for them.
    assert coverage[expected_coverage == 1].min() > 0.95
    np.testing.assert_array_equal(coverage[expected_coverage == 0][~_near_edge(expected_coverage)], 0.0)
    # The edge term is exact along an edge and over-estimates at sharp corners.
    assert np.abs(coverage - expected_coverage).max() < 0.3
    assert abs(coverage.sum() - expected_coverage.sum()) < 0.02 * expected_coverage.sum() + 0.5


def _near_edge(coverage):
    """Pixels next to a partly covered one (the analytic edge term may reach them)."""
    partial = (coverage > 0) & (coverage < 1)
    grown = partial.copy()
    for axis in (0, 1):
        for shift in (-1, 1):
            grown |= np.roll(partial, shift, axis=axis)
    return grown[coverage == 0]


def test_sphere_depth_and_coverage_match_analytic():
    center, radius = np.array([0.4, 0.2, -4.0]), 0.8
    buffers = _render(_scene(sun_center=center, sun_radius=radius))
    _check_against_reference(buffers, _sphere_hits(center, radius, _pixel_rays()), _sphere_hits(center, radius, _pixel_rays(16)))
    ids = np.asarray(buffers.object_id)
    assert set(np.unique(ids)) == {-1, 0}
    normal = np.asarray(buffers.normal)[HEIGHT // 2, WIDTH // 2]
    np.testing.assert_allclose(np.linalg.norm(normal), 1.0, atol=1e-5)


def test_triangle_depth_and_coverage_match_analytic():
    buffers = _render(_scene(sun_center=FAR_AWAY, triangle_offset=(0.0, 0.0, 0.0)))
    _check_against_reference(buffers, _triangle_hits(TRIANGLE.astype(np.float64), _pixel_rays()), _triangle_hits(TRIANGLE.astype(np.float64), _pixel_rays(8)))
    assert set(np.unique(np.asarray(buffers.object_id))) == {-1, 2}


def test_buffers_are_the_same_under_an_outer_jit():
    scene = _scene(triangle_offset=(0.0, 0.0, 0.0))
    eager = _render(scene)
    jitted = eqx.filter_jit(_render)(scene)
    for name in ("color", "depth", "coverage", "light_pass"):
        np.testing.assert_allclose(np.asarray(getattr(jitted, name)), np.asarray(getattr(eager, name)), atol=1e-5)


def test_hidden_object_gets_no_coverage():
    # A small sphere right behind the big one: no pixel shows it, nothing changes.
    hidden = _render(_scene(other_center=(0.4, 0.2, -6.0)))
    alone = _render(_scene())
    assert not np.any(np.asarray(hidden.object_id) == 1)
    np.testing.assert_allclose(np.asarray(hidden.coverage), np.asarray(alone.coverage), atol=1e-6)
    np.testing.assert_allclose(np.asarray(hidden.color), np.asarray(alone.color), atol=1e-6)
    # Moved out from behind it, the same sphere shows.
    shown = _render(_scene(other_center=(-1.5, -0.5, -6.0)))
    assert np.any(np.asarray(shown.object_id) == 1)


def test_light_pass_centre_matches_projected_light():
    center = np.array([-0.7, 0.45, -5.0])
    buffers = _render(_scene(sun_center=center, sun_radius=0.35))
    light = np.asarray(buffers.light_pass)
    ys, xs = np.mgrid[0:HEIGHT, 0:WIDTH] + 0.5
    centroid = np.array([(light * xs).sum(), (light * ys).sum()]) / light.sum()
    xy, depth, in_front = project_point(_camera(), jnp.asarray(center))
    assert bool(in_front)
    # The projected disc's centroid differs from the projected centre only by
    # the perspective of an off-axis sphere, a small fraction of a pixel here.
    np.testing.assert_allclose(centroid, np.asarray(xy), atol=0.1)
    assert light.max() == pytest.approx(1.0)


@pytest.mark.slow
def test_gradients_with_respect_to_sphere_center_point_the_right_way():
    right_half = jnp.asarray(np.arange(WIDTH) >= WIDTH // 2, jnp.float32)[None, :]

    def summaries(center):
        buffers = _render(_scene(sun_center=center, sun_radius=0.8))
        # Moving the bright sphere right puts more of it in the right half.
        return (buffers.coverage * right_half).sum(), (buffers.color.sum(-1) * right_half).sum()

    center = jnp.asarray([-0.3, 0.1, -4.0])
    coverage_gradient = jax.grad(lambda c: summaries(c)[0])(center)
    color_gradient = jax.grad(lambda c: summaries(c)[1])(center)
    assert np.all(np.isfinite(np.asarray(coverage_gradient))) and np.all(np.isfinite(np.asarray(color_gradient)))
    assert float(coverage_gradient[0]) > 0 and float(color_gradient[0]) > 0
    # And they agree with finite differences.
    step = jnp.asarray([0.02, 0.0, 0.0])
    finite_difference = (summaries(center + step)[0] - summaries(center - step)[0]) / 0.04
    assert float(coverage_gradient[0]) == pytest.approx(float(finite_difference), rel=0.1)


def test_several_lights_each_shade_as_alone_and_add():
    """A scene's lights shade its surfaces each as it would alone, their light added: under the sun and a point
    light, the frame is the sun's frame plus the point light's own part (its frame beside a black first light, less
    that black light's frame), which is Lambert's `albedo * colour * max(N . L, 0)` on the blue sphere (a NumPy
    ray cast at the pixels it covers whole), and nothing on its side turned away."""
    import dataclasses

    base = _scene(other_center=(-1.2, -0.3, -5.0))
    sun, black = base.light, DirectionalLight(direction=(0.0, 0.0, 1.0), color=(0.0, 0.0, 0.0))
    lamp = PointLight(position=(-4.0, 0.5, -4.0), color=(0.5, 0.8, 1.0))
    colour = lambda *lights: np.asarray(_render(dataclasses.replace(  # noqa: E731
        base, light=lights[0], other_lights=lights[1:])).color, np.float64)  # fmt: skip
    lamp_alone = colour(black, lamp) - colour(black)
    np.testing.assert_allclose(colour(sun, lamp) - colour(sun), lamp_alone, atol=1e-5)

    rays = _pixel_rays()[:, :, 0]
    center, radius = np.asarray(base.objects[1].center, np.float64), 0.5
    hits = _sphere_hits(center, radius, rays)
    whole = np.isfinite(_sphere_hits(center, radius, _pixel_rays(4))).all(-1)
    points = hits[whole][:, None] * rays[whole]
    normals = (points - center) / radius
    to_lamp = np.asarray(lamp.position, np.float64) - points
    n_dot_l = np.sum(normals * to_lamp, -1) / np.linalg.norm(to_lamp, axis=-1)
    expected = np.asarray((0.2, 0.4, 0.9)) * np.asarray(lamp.color) * np.maximum(n_dot_l, 0.0)[:, None]
    assert len(points) > 10 and (n_dot_l > 0.2).any() and (n_dot_l < 0).any()
    np.testing.assert_allclose(lamp_alone[whole], expected, rtol=2e-3, atol=2e-4)


@pytest.mark.slow
def test_glow_pass_enlarges_source_and_shrinks_occluders():
    scene = _scene(sun_center=(0.0, 0.0, -8.0), sun_radius=1.0, other_center=(0.0, 0.0, -4.0))
    buffers = render(scene, _camera(), tile_capacity=CAPACITY)
    glow = np.asarray(buffers.glow_pass)
    light = np.asarray(buffers.light_pass)
    np.testing.assert_allclose(glow.max(axis=(0, 1)), [0.8, 0.5, 0.0, 0.65], atol=1e-6)
    # Enlarged x1.3 and the occluder shrunk x0.8: the glow covers more than the light does.
    assert (glow[..., 3] > 0).sum() > (light > 0).sum()
    assert glow[HEIGHT // 2, WIDTH // 2, 3] == 0.0


def test_gradients_with_respect_to_mesh_translation_match_finite_differences():
    right_half = jnp.asarray(np.arange(WIDTH) >= WIDTH // 2, jnp.float32)[None, :]

    def coverage_right(offset):
        return (_render(_scene(sun_center=FAR_AWAY, triangle_offset=offset)).coverage * right_half).sum()

    offset = jnp.asarray([0.1, 0.0, 0.0])
    gradient = jax.grad(coverage_right)(offset)
    assert np.all(np.isfinite(np.asarray(gradient))) and float(gradient[0]) > 0
    step = jnp.asarray([0.02, 0.0, 0.0])
    finite_difference = (coverage_right(offset + step) - coverage_right(offset - step)) / 0.04
    assert float(gradient[0]) == pytest.approx(float(finite_difference), rel=0.1)


def _layers(scene, camera, *, tile_mask=None, scales=None):
    """Every layer of every pixel, straight from the tile loop."""

    def finish(layers, px, py):
        if layers is None:
            return visibility.Layers(*(visibility.Layer(jnp.full(px.shape, -1, jnp.int32), jnp.zeros(px.shape), jnp.zeros((*px.shape, 3)), jnp.zeros((*px.shape, 3))),) * 3)
        # Images want the pixel axis first.
        return jax.tree_util.tree_map(lambda a: a.T if a.ndim == 2 else a, layers)

    rasterize = lambda scene, camera, mask: tile_loop.rasterize(geometry.flatten(scene, camera, scales), camera, finish, tile_size=16, capacity=CAPACITY, tile_mask=mask)
    return eqx.filter_jit(rasterize)(scene, camera, tile_mask)


def test_every_bucket_size_gives_the_same_layers(monkeypatch):
    # Tiles of 0, 1 and 2 spheres and 0 or 1 triangle, each evaluated with the
    # smallest bucket that holds it, against every tile padded to the capacity.
    scene = _scene(other_center=(-1.0, -0.3, -5.0), triangle_offset=(-1.2, 0.9, -2.0))
    bucketed = _layers(scene, _camera())
    monkeypatch.setattr(tile_loop, "_bucket_sizes", lambda limit: (0, limit))
    padded = _layers(scene, _camera())
    for got, want in zip(jax.tree_util.tree_leaves(bucketed), jax.tree_util.tree_leaves(padded)):
        if np.issubdtype(np.asarray(want).dtype, np.integer):
            np.testing.assert_array_equal(np.asarray(got), np.asarray(want))  # which object each layer holds
        else:
            # The same arithmetic in two programs: the code generator may round them apart (1e-6 here at most).
            np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-5, atol=1e-6)
    assert set(np.unique(np.asarray(bucketed.front.object_id))) == {-1, 0, 1, 2}


def _glow_scales(scene):
    return glow_pass.glow_scales(scene, glow_pass.GLOW_SOURCE_SCALE, glow_pass.GLOW_OCCLUDER_SCALE)


def _sky_light(scene, camera):
    rows, columns = np.mgrid[0:HEIGHT, 0:WIDTH] + 0.5
    rays = shading.world_rays(camera, jnp.asarray(columns.reshape(-1), jnp.float32), jnp.asarray(rows.reshape(-1), jnp.float32))
    return jnp.clip(shading.sky(scene, camera, rays)[1], 0.0, 1.0).reshape(HEIGHT, WIDTH)


def _full_glow_pass(scene, camera):
    """The glow pass rasterized in every tile (no restriction to the source's tiles)."""
    layers = _layers(scene, camera, scales=_glow_scales(scene))
    if scene.sun is not None:
        weight = visibility.object_weight(layers, scene.sun)
    else:
        weight = (1.0 - visibility.total_coverage(layers)) * _sky_light(scene, camera)
    return np.asarray(weight[..., None] * jnp.asarray(glow_pass.GLOW_COLOR))


@pytest.mark.parametrize("sun", slow_where([0, 2, None], {0, None}))
def test_glow_pass_near_the_source_equals_the_full_glow_pass(sun):
    # A small source in the top-left tile; the occluder and the triangle, and
    # the tiles they fill, elsewhere.
    objects = _scene(sun_center=(-0.9, 0.5, -4.0), sun_radius=0.3, other_center=(1.0, -0.4, -5.0), triangle_offset=(0.8, 0.0, 0.0)).objects
    # Without a sun object the sky's sun spot, beside the sphere, is the source.
    scene = Scene(objects=objects, light=DirectionalLight(direction=(-1.4, 0.7, -4.0)), sky=Sky(sun_distance=5.0, sun_sharpness=1.0), sun=sun)
    glow = np.asarray(render(scene, _camera(), tile_capacity=CAPACITY).glow_pass)
    # rtol: the sun spot, cos ** 10000, magnifies float rounding of the ray directions.
    np.testing.assert_allclose(glow, _full_glow_pass(scene, _camera()), rtol=2e-3, atol=1e-6)
    assert glow[..., 3].max() > 0.1
    if sun == 2:
        return  # the enlarged triangle (the source) reaches every visible tile
    assert glow[:16, :16, 3].sum() == pytest.approx(glow[..., 3].sum())
    # Only the top-left of the visible tiles is rasterized again.
    tiles = glow_pass.glow_tiles(scene, _camera(), geometry.flatten(scene, _camera(), _glow_scales(scene)), _sky_light(scene, _camera()), 16)
    assert np.flatnonzero(np.asarray(tiles)).tolist() == [0]

def _scene_file(tmp_path, **changes):
    table = {
        "camera": {"position": [0, 0, 0], "target": [0, 0, -1], "up": [0, 1, 0], "fov_x_deg": FOV, "width": WIDTH, "height": HEIGHT},
        "materials": {"sun": {"emission": [3, 2, 1]}},
        "objects": [{"type": "sphere", "name": "sun", "center": [0, 0, -4], "radius": 0.8, "material": "sun"}],
        "sun": "sun",
    }
    for path, value in changes.items():
        *parents, last = path.split(".")
        target = table
        for key in parents:
            target = target[int(key)] if key.isdigit() else target[key]
        target[last] = value
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(table))
    return path


def test_scene_file_loads(tmp_path):
    (tmp_path / "tri.obj").write_text("v -1 -1 -6\nv 1 -1 -6\nv 0 1 -6\nvn 0 0 1\nf 1//1 2//1 3//1\n")
    path = _scene_file(tmp_path, **{"objects": [
        {"type": "sphere", "name": "sun", "center": [0, 0, -4], "radius": 0.8, "material": "sun"},
        {"type": "mesh", "obj": "tri.obj", "translation": [0, 0, -1]},
        {"type": "uv_sphere", "segments": 8, "rings": 4, "scale": 0.5},
    ]})
    scene, camera = load_scene(path)
    assert camera.width == WIDTH and scene.sun == 0 and len(scene.objects) == 3
    assert scene.objects[1].normals is not None
    assert scene.lights == (scene.light,) and isinstance(scene.light, DirectionalLight)
    lamp = {"type": "point", "position": [1, 2, -3], "color": [1, 0.5, 0]}
    scene, _ = load_scene(_scene_file(tmp_path, lights=[{"type": "directional", "direction": [0, 1, 0]}, lamp]))
    assert isinstance(scene.light, DirectionalLight) and len(scene.other_lights) == 1
    np.testing.assert_array_equal(scene.other_lights[0].position, [1, 2, -3])


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"objects.0.radus": 1.0}, r"objects\[0\]\.radus: unknown key"),
        ({"objects.0.radius": -1.0}, r"radius must be > 0"),
        ({"camera.up": [0, 0, -1]}, r"camera: .*up is parallel"),
        ({"objects": [{"type": "mesh", "vertices": [[0, 0, 0], [1, 1, 1], [2, 2, 2]], "faces": [[0, 1, 2]]}]}, r"faces\[0\] is a degenerate"),
        ({"objects": [{"type": "mesh", "obj": "missing.obj"}]}, r"missing\.obj.*cannot read"),
        ({"sun": "moon"}, r"sun: no object named 'moon'"),
        ({"lights": []}, r"lights: must be a non-empty list"),
        ({"lights": [{"type": "point", "position": [0, 0, 0]}, {"type": "spot"}]}, r"lights\[1\]\.type: must be"),
        ({"lights": [{"type": "point", "positon": [0, 0, 0]}]}, r"lights\[0\]\.positon: unknown key"),
        ({"light": {"type": "point", "position": [0, 0, 0]}, "lights": []}, r"lights: give light or lights"),
    ],
)
def test_bad_scene_file_names_the_problem(tmp_path, changes, message):
    with pytest.raises(ValueError, match=message):
        load_scene(_scene_file(tmp_path, **changes))


def test_unparsable_obj_names_file_and_line(tmp_path):
    path = tmp_path / "broken.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv zero 1 0\nf 1 2 3\n")
    with pytest.raises(ValueError, match=r"broken\.obj.*line 3"):
        load_obj(path)


def test_bad_render_arguments():
    with pytest.raises(ValueError, match="tile_capacity"):
        render(_scene(), _camera(), tile_capacity=(4, 4))
    with pytest.raises(ValueError, match="glow_color"):
        render(_scene(), _camera(), glow_color=(1.0, 0.0, 0.0))
