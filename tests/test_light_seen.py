"""Lights read from their own pixels (`seen_lights`) and `godrays-jax fit --light auto` / `--fit-light` placing a
light in view without a search: discs drawn anti-aliased at known sub-pixel centres, whole, hidden in part by
something nearer, cut by the frame's edge; and what is not a light (a lit patch, an LDR plate, a bar)."""

import json
import math

import jax.numpy as jnp
import numpy as np
import pytest

import godrays_jax as gr
from godrays_jax.app.cli import main

HEIGHT, WIDTH = 96, 160  # a sun's disc of radius 5 under 1 % of it: the 99th percentile the sky's
SKY, SUN = 0.3, 3000.0
SUPERSAMPLING = 8


def _coverage(centre, radius, shape=(HEIGHT, WIDTH)) -> np.ndarray:
    """Each pixel's share inside the disc, from `SUPERSAMPLING**2` samples a pixel: an anti-aliased edge."""
    offsets = (np.arange(SUPERSAMPLING) + 0.5) / SUPERSAMPLING
    rows = (np.arange(shape[0])[:, None] + offsets[None, :]).reshape(-1)
    columns = (np.arange(shape[1])[:, None] + offsets[None, :]).reshape(-1)
    inside = (columns[None, :] - centre[0]) ** 2 + (rows[:, None] - centre[1]) ** 2 <= radius**2
    return inside.reshape(shape[0], SUPERSAMPLING, shape[1], SUPERSAMPLING).mean(axis=(1, 3))


def _frame(color: np.ndarray, depth: np.ndarray | None, **options) -> gr.Buffers:
    coverage = None if depth is None else jnp.asarray(np.isfinite(depth).astype(np.float32))
    return gr.Buffers(
        color=jnp.asarray(np.repeat(color[..., None], 3, axis=-1).astype(np.float32)),
        depth=None if depth is None else jnp.asarray(depth.astype(np.float32)),
        coverage=coverage,
        **options,
    )


def _sky_with_sun(centre, radius=5.0) -> tuple[np.ndarray, np.ndarray]:
    """A sky at `SKY` with a ground below row 60 (depth 20), and a sun's disc at `centre` in the sky."""
    depth = np.full((HEIGHT, WIDTH), np.inf)
    depth[60:] = 20.0
    color = np.where(np.isfinite(depth), 0.05, SKY)
    share = _coverage(centre, radius)
    return color * (1.0 - share) + SUN * share, depth


@pytest.mark.parametrize("centre", [(40.5, 15.5), (23.37, 12.81), (61.9, 19.26)])
def test_a_whole_disc_is_placed_at_its_centre_to_a_few_hundredths_of_a_pixel(centre):
    color, depth = _sky_with_sun(centre)
    (light,) = gr.seen_lights(_frame(color, depth))
    assert np.linalg.norm(light.light_xy - centre) < 0.03, (light.light_xy, centre)
    assert not light.hidden and math.isinf(light.depth)
    assert abs(light.radius - 5.0) < 0.2 and np.all(light.standard_error < 0.1), light
    assert light.pixels > 60


def test_a_disc_hidden_in_part_by_something_nearer_is_placed_by_the_rest_of_its_edge():
    centre = (40.3, 15.7)
    color, depth = _sky_with_sun(centre, radius=6.0)
    depth[:13] = 5.0  # a slat above its centre, nearer than the sky, hides its top
    color[:13] = 0.05
    (light,) = gr.seen_lights(_frame(color, depth))
    assert light.hidden
    assert np.linalg.norm(light.light_xy - centre) < 0.3, (light.light_xy, centre)
    # Its pixels' centroid lies below the centre: what the circle through its edge corrects.
    rows = np.indices(color.shape)[0] + 0.5
    bright = color > 100.0
    assert np.mean(rows[bright]) - centre[1] > 1.0


def test_a_disc_cut_by_the_frames_edge_is_placed_where_the_rest_of_it_says():
    centre = (3.4, 20.2)  # most of it on screen, its left part beyond the edge
    color, depth = _sky_with_sun(centre, radius=6.0)
    (light,) = gr.seen_lights(_frame(color, depth))
    assert light.hidden and np.linalg.norm(light.light_xy - centre) < 0.3, (light.light_xy, centre)


def test_a_disc_hidden_beyond_half_its_edge_is_not_placed():
    color, depth = _sky_with_sun((40.0, 15.0), radius=6.0)
    depth[:17] = 5.0  # hides all of it above a chord below its centre
    color[:17] = 0.05
    assert gr.seen_lights(_frame(color, depth)) == []


def test_lamps_are_placed_at_their_distance_brightest_first_and_planar_depth_needs_the_field_of_view():
    shape = (HEIGHT, WIDTH)
    color, depth = np.full(shape, 0.02), np.full(shape, 30.0)
    lamps = [((40.6, 28.2), 2.5, 8.0, 800.0), ((116.3, 61.7), 3.5, 12.0, 1500.0)]
    for centre, radius, distance, radiance in lamps:
        share = _coverage(centre, radius, shape)
        color = color * (1.0 - share) + radiance * share
        depth = np.where(share > 0.0, distance, depth)
    lights = gr.seen_lights(_frame(color, depth))
    assert [round(light.depth) for light in lights] == [12, 8]  # the larger, brighter lamp first
    for light, (centre, *_) in zip(lights, lamps[::-1]):
        assert np.linalg.norm(light.light_xy - centre) < 0.05, (light.light_xy, centre)
    planar = _frame(color, depth, depth_kind="planar")
    with pytest.raises(ValueError, match="fov_x_deg"):
        gr.seen_lights(planar)
    along_rays = gr.seen_lights(planar, fov_x_deg=60.0)
    assert along_rays[0].depth > 12.0 and along_rays[1].depth > 8.0  # off the axis: farther along its ray


@pytest.mark.parametrize(
    "case", ["a sunlit patch in a dark room", "an 8-bit plate", "a bright bar", "no depth, a glint of one pixel"]
)
def test_what_is_not_a_light_in_view_is_not_read_as_one(case):
    color, depth = np.full((HEIGHT, WIDTH), 0.01), np.full((HEIGHT, WIDTH), 4.0)
    if case == "a sunlit patch in a dark room":  # a surface lit by a light: far less than 100 times the rest
        color[30:44, 10:40] = 5.0
    elif case == "an 8-bit plate":
        color, depth = np.clip(_sky_with_sun((40.0, 15.0))[0], 0.0, 1.0), _sky_with_sun((40.0, 15.0))[1]
    elif case == "a bright bar":  # long and thin: not round, not a sun or a bulb
        depth[:] = np.inf
        color[20, 20:50] = 2000.0  # under 1 % of the frame
    lights = gr.seen_lights(_frame(color, None if case.startswith("no depth") else depth))
    assert lights == []
    if case.startswith("no depth"):  # a point a pixel across is a light: too few edge points for a circle
        color[10, 30] = 2000.0
        (light,) = gr.seen_lights(_frame(color, None))
        np.testing.assert_allclose(light.light_xy, (30.5, 10.5), atol=1e-6)
        assert np.all(np.isnan(light.standard_error)) and math.isinf(light.depth)


def _files(tmp_path, centre):
    color, depth = _sky_with_sun(centre)
    frame, target = tmp_path / "frame.exr", tmp_path / "target.exr"
    buffers = _frame(color, depth)
    gr.write_buffers(frame, buffers)  # no godrays:light_px: the light is not known
    effect = gr.replace_fields(gr.preset("xna_crepuscular"), {"tint": (0.9, 0.7, 0.45)})
    gr.write_image(target, np.asarray(effect(buffers, jnp.asarray(centre, jnp.float32))))
    return frame, target


FIT = ["--preset", "xna_crepuscular", "--max-steps", "1", "--coarse-factor", "1", "--fixed",
       "flare_size,offscreen_fade,fov_x_deg,density,decay,weight,exposure,sun_size,threshold,num_samples"]  # fmt: skip


def test_fit_light_auto_places_a_light_in_view_by_its_pixels_without_a_search(tmp_path, capsys):
    centre = (41.27, 14.63)
    frame, target = _files(tmp_path, centre)
    params = tmp_path / "params.json"
    assert main(["fit", str(frame), str(target), "-o", str(params), "--light", "auto", *FIT]) == 0
    out = capsys.readouterr().out
    (line,) = [line for line in out.splitlines() if line.startswith("light of")]
    assert "in view (a disc of radius" in line and "in the sky" in line, out
    assert "a fit with the light at" not in out and "placed at" not in out  # no fits around it
    (entry,) = json.loads((tmp_path / "params.light.json").read_text())["lights"]
    assert np.linalg.norm(np.asarray(entry["light_px"]) - centre) < 0.05, entry
    assert all(0 < error < 0.1 for error in entry["standard_error_px"]), entry

    assert main(["fit", str(frame), str(target), "-o", str(params), "--light", "45,20", "--fit-light", *FIT]) == 0
    (line,) = [line for line in capsys.readouterr().out.splitlines() if line.startswith("light of")]
    assert "in view" in line and "px from 45,20" in line, line
    (entry,) = json.loads((tmp_path / "params.light.json").read_text())["lights"]
    assert np.linalg.norm(np.asarray(entry["light_px"]) - centre) < 0.05, entry


def test_fit_light_auto_draws_a_lamp_in_view_at_its_distance_and_apply_params_takes_it(tmp_path, capsys):
    centre, distance = (70.4, 30.3), 8.0
    share = _coverage(centre, 2.5)
    depth = np.where(share > 0.0, distance, 30.0)
    buffers = _frame(0.05 * (1.0 - share) + 900.0 * share, depth)
    frame, target = tmp_path / "frame.exr", tmp_path / "target.exr"
    gr.write_buffers(frame, buffers)  # no light and no distance in its header
    effect = gr.replace_fields(gr.preset("xna_crepuscular"), {"tint": (0.9, 0.7, 0.45)})
    gr.write_image(target, np.asarray(effect(buffers, jnp.asarray(centre, jnp.float32), light_depth=distance)))
    params = tmp_path / "params.json"
    assert main(["fit", str(frame), str(target), "-o", str(params), "--light", "auto", *FIT]) == 0
    (line,) = [line for line in capsys.readouterr().out.splitlines() if line.startswith("light of")]
    assert "its pixels at a distance of" in line and "drawn at" not in line, line
    (entry,) = json.loads((tmp_path / "params.light.json").read_text())["lights"]
    assert abs(entry["light_depth"] - distance) < 0.1 and np.linalg.norm(np.subtract(entry["light_px"], centre)) < 0.05

    output = tmp_path / "applied.exr"
    assert main(["apply", str(frame), "--params", str(params), "-o", str(output)]) == 0
    assert f"at a distance of {entry['light_depth']:.6g} from" in capsys.readouterr().out
    drawn = gr.load_effect(params)(
        gr.read_buffers(frame), jnp.asarray(entry["light_px"], jnp.float32), light_depth=entry["light_depth"]
    )
    np.testing.assert_allclose(np.asarray(gr.read_image(output))[..., :3], np.asarray(drawn)[..., :3], atol=2e-3)
    elsewhere = gr.load_effect(params)(gr.read_buffers(frame), jnp.asarray(entry["light_px"], jnp.float32))
    assert np.max(np.abs(np.asarray(elsewhere) - np.asarray(drawn))) > 0.01  # the distance matters to this frame


@pytest.mark.slow
def test_fit_light_auto_draws_every_lamp_in_view_and_apply_params_draws_them_all(tmp_path, capsys):
    lamps = [((40.6, 28.2), 3.0, 8.0, 1500.0), ((116.3, 61.7), 2.0, 14.0, 800.0)]
    color, depth = np.full((HEIGHT, WIDTH), 0.05), np.full((HEIGHT, WIDTH), 30.0)
    for centre, radius, distance, radiance in lamps:
        share = _coverage(centre, radius)
        color, depth = color * (1.0 - share) + radiance * share, np.where(share > 0.0, distance, depth)
    buffers = _frame(color, depth)
    frame, target = tmp_path / "frame.exr", tmp_path / "target.exr"
    gr.write_buffers(frame, buffers)
    effect = gr.replace_fields(gr.preset("xna_crepuscular"), {"tint": (0.9, 0.7, 0.45)})
    drawn = [gr.Light(jnp.asarray(c, jnp.float32), depth=d, tint=(t, t, t)) for (c, _, d, _), t in zip(lamps, (1, 0.5))]
    gr.write_image(target, np.asarray(gr.lit_by(effect, buffers, drawn)))
    params = tmp_path / "params.json"
    assert main(["fit", str(frame), str(target), "-o", str(params), "--light", "auto", *FIT]) == 0
    out = capsys.readouterr().out
    assert "1 more in view, drawn beside it (their tints fitted): 116.29" in out, out
    stored = json.loads((tmp_path / "params.light.json").read_text())
    (entry,), (tint,) = stored["lights"], stored["light_tints"]
    (other,) = entry["beside"]
    assert abs(entry["light_depth"] - 8.0) < 0.1 and abs(other["light_depth"] - 14.0) < 0.1, entry
    assert np.linalg.norm(np.subtract(other["light_px"], lamps[1][0])) < 0.05, other

    output = tmp_path / "applied.exr"
    assert main(["apply", str(frame), "--params", str(params), "-o", str(output)]) == 0
    assert "lights 40.6" in capsys.readouterr().out
    lights = [
        gr.Light(jnp.asarray(entry["light_px"], jnp.float32), depth=entry["light_depth"]),
        gr.Light(jnp.asarray(other["light_px"], jnp.float32), depth=other["light_depth"], tint=tint),
    ]
    expected = gr.lit_by(gr.load_effect(params), gr.read_buffers(frame), lights)
    np.testing.assert_allclose(np.asarray(gr.read_image(output))[..., :3], np.asarray(expected)[..., :3], atol=2e-3)


def test_fit_light_auto_lists_a_glint_far_fainter_than_the_light_without_drawing_it(tmp_path, capsys):
    color, depth = _sky_with_sun((60.3, 20.6))
    color[70, 100] = 2.0 * SUN  # a glint on the ground: one pixel, a small share of the sun's pixels
    buffers = _frame(color, depth)
    frame, target = tmp_path / "frame.exr", tmp_path / "target.exr"
    gr.write_buffers(frame, buffers)
    effect = gr.replace_fields(gr.preset("xna_crepuscular"), {"tint": (0.9, 0.7, 0.45)})
    gr.write_image(target, np.asarray(effect(buffers, jnp.asarray((60.3, 20.6), jnp.float32))))
    params = tmp_path / "params.json"
    assert len(gr.seen_lights(buffers)) == 2
    assert main(["fit", str(frame), str(target), "-o", str(params), "--light", "auto", *FIT]) == 0
    out = capsys.readouterr().out
    assert "1 fainter more in view; to draw them all: --light '60.29" in out and "drawn beside it" not in out, out
    (entry,) = json.loads((tmp_path / "params.light.json").read_text())["lights"]
    assert "beside" not in entry and "light_tints" not in json.loads((tmp_path / "params.light.json").read_text())


def test_of_many_glints_the_brightest_groups_are_read_the_sun_first():
    shape = (2 * HEIGHT, 2 * WIDTH)  # the sun and the glints under 1 % of it
    depth = np.where(np.arange(shape[0])[:, None] >= 120, 20.0, np.inf) * np.ones(shape)
    share = _coverage((60.3, 20.6), 5.0, shape)
    color = np.where(np.isfinite(depth), 0.05, SKY) * (1.0 - share) + SUN * share
    rows = np.random.default_rng(0).integers(124, shape[0], 200)
    columns = np.random.default_rng(1).integers(0, shape[1], 200)
    color[rows, columns] = 0.5 * SUN  # sunlit water: a glint a pixel, each a light of its own
    lights = gr.seen_lights(_frame(color, depth))
    assert len(lights) == gr.pipeline.light_seen.MOST_GROUPS
    assert np.linalg.norm(lights[0].light_xy - (60.3, 20.6)) < 0.03 and lights[0].pixels > 60
