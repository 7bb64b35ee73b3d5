"""Frame patterns as render pipelines and compositors write them (`expand_frames`), and the CLI's parsing of them."""

import os

import numpy as np
import pytest

import godrays_jax
from godrays_jax.app.cli import build_parser, main
from godrays_jax.pipeline.sequences import expand_frames, frame_number


def touch(folder, *names):
    for name in names:
        (folder / name).write_bytes(b"")
    return [str(folder / name) for name in names]


@pytest.fixture
def shot(tmp_path):
    """Frames 998-1003 and 10000 padded to 4 digits, one unpadded and one 2-digit frame, and a 1-digit series."""
    four = touch(tmp_path, *(f"shot.{n:04d}.exr" for n in (998, 999, 1000, 1001, 1002, 1003)), "shot.10000.exr")
    touch(tmp_path, "shot.12.exr", "shot.01234x.exr", "other.1001.exr")
    single = touch(tmp_path, *(f"one.{n}.exr" for n in (7, 8, 9, 10)))
    return tmp_path, four, single


@pytest.mark.parametrize("token", ["####", "#", "%04d", "$F4", "${F4}", "@@@@"])
def test_four_digit_tokens_of_every_tool(shot, token):
    folder, four, _ = shot
    assert expand_frames(str(folder / f"shot.{token}.exr")) == four  # 10000 too: past the padding, unpadded


@pytest.mark.parametrize("token", ["@", "%d", "$F"])
def test_unpadded_tokens(shot, token):
    folder, _, single = shot
    assert expand_frames(str(folder / f"one.{token}.exr")) == single  # sorted by number: 10 last


def test_hashes_count_digits_and_a_lone_hash_is_four(shot):
    folder, four, _ = shot
    # Two digits: 0998 and 0999 carry a zero that padding to two never writes.
    assert expand_frames(str(folder / "shot.##.exr")) == [str(folder / "shot.12.exr"), *four[2:]]
    with pytest.raises(ValueError, match=r"one\.<a frame number of at least 4 digits>\.exr.*lone # is 4 digits"):
        expand_frames(str(folder / "one.#.exr"))


def test_oiiotool_ranges(shot):
    folder, four, _ = shot
    assert expand_frames(str(folder / "shot.999-1002#.exr")) == four[1:5]
    assert expand_frames(str(folder / "shot.998-1003x2@@@@.exr")) == [four[0], four[2], four[4]]
    assert expand_frames(str(folder / "one.8-1000@.exr")) == [str(folder / f"one.{n}.exr") for n in (8, 9, 10)]
    with pytest.raises(ValueError, match="empty"):
        expand_frames(str(folder / "shot.1002-999#.exr"))
    with pytest.raises(ValueError, match="no frames match"):
        expand_frames(str(folder / "shot.2000-2010#.exr"))


def test_negative_frames_globs_files_and_errors(tmp_path):
    names = touch(tmp_path, "cam.-002.exr", "cam.-001.exr", "cam.0000.exr", "cam.0001.exr")
    assert expand_frames(str(tmp_path / "cam.####.exr")) == names
    assert sorted(expand_frames(str(tmp_path / "cam.*.exr"))) == sorted(names)  # a glob sorts by name
    literal = touch(tmp_path, "odd#name@.exr")
    assert expand_frames(literal[0]) == literal
    with pytest.raises(ValueError, match="more than one frame token"):
        expand_frames(str(tmp_path / "cam.####.%04d.exr"))
    with pytest.raises(ValueError, match="no frames match"):
        expand_frames(str(tmp_path / "missing.exr"))


def test_help_states_what_hash_and_at_mean(capsys):
    with pytest.raises(SystemExit):
        main(["batch", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "a lone # is 4 digits" in text and "one digit per @" in text and "$F4" in text and "%04d" in text


def test_version(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--version"])
    assert exit_info.value.code == 0
    assert capsys.readouterr().out.strip() == f"godrays-jax {godrays_jax.__version__}"


@pytest.mark.parametrize(
    "argv, light",
    [
        (["--light", "-5,10"], (-5.0, 10.0)),
        (["--light=-5,10"], (-5.0, 10.0)),
        (["--light", "-.5,-3e2"], (-0.5, -300.0)),
        (["--light", "12,-4"], (12.0, -4.0)),
    ],
)
def test_negative_light_coordinates_with_or_without_equals(argv, light):
    args = build_parser().parse_args(["apply", "frame.exr", *argv, "-o", os.devnull])
    assert args.light == [(light, True)]  # apply's lights: one here


@pytest.mark.parametrize("text, side", [("-5,10,behind", False), ("-5,10,front", True), ("-5, 10, Behind", False)])
def test_a_light_behind_the_camera_is_its_position_and_behind(text, side):
    args = build_parser().parse_args(["apply", "frame.exr", "--light", text, "-o", os.devnull])
    assert args.light == [((-5.0, 10.0), side)]
    several = build_parser().parse_args(["apply", "frame.exr", "--light", f"{text};1,2", "-o", os.devnull])
    assert several.light == [((-5.0, 10.0), side), ((1.0, 2.0), True)]


def test_a_light_option_missing_its_value_is_still_a_usage_error(capsys):
    with pytest.raises(SystemExit) as exit_info:
        build_parser().parse_args(["apply", "frame.exr", "-o", "x.png", "--light", "-q"])
    assert exit_info.value.code == 2
    assert capsys.readouterr().err.count("\n") == 1


@pytest.mark.parametrize(
    "name, number",
    [("shot.-001.exr", -1), ("shot_-12.exr", -12), ("-7.exr", -7), ("shot.0005.exr", 5), ("shot-0001.exr", 1),
     ("v2-0003.exr", 3), ("take.-2/shot.0004.exr", 4)],
)  # fmt: skip
def test_frame_numbers_keep_their_sign(name, number):
    """A minus sign belongs to the number where a separator (not a letter or digit) comes before it."""
    assert frame_number(name) == number


def test_negative_frames_throughout_a_batch(tmp_path, capsys):
    """`--frames -2-0` without `=`, the sign kept when selecting frames, and light tracks keyed by signed numbers."""
    depth = np.full((4, 6), np.inf, np.float32)
    frame = godrays_jax.Buffers(color=np.full((4, 6, 3), 0.2, np.float32), depth=depth, coverage=np.zeros((4, 6)))
    for number in (-3, -2, -1, 0, 1, 2):
        godrays_jax.write_buffers(tmp_path / f"cam.{number:04d}.exr", frame)
    (tmp_path / "track.csv").write_text("frame,x,y\n-3,1,1\n-2,2,2\n-1,3,3\n0,4,4\n1,5,5\n2,66,66\n")
    args = build_parser().parse_args(["batch", "p", "-o", "o", "--frames", "-2-0"])
    assert args.frames == "-2-0"
    assert main(["batch", str(tmp_path / "cam.####.exr"), "-o", str(tmp_path / "out"), "--frames", "-2-0",
                 "--light-track", str(tmp_path / "track.csv"), "--dry-run"]) == 0  # fmt: skip
    listed = [line for line in capsys.readouterr().out.splitlines() if line.startswith("run")]
    assert [line.split()[1].rsplit("/", 1)[1] for line in listed] == ["cam.-002.exr", "cam.-001.exr", "cam.0000.exr"]
    assert [line.split("light ")[1].split(")")[0] + ")" for line in listed] == ["(2, 2)", "(3, 3)", "(4, 4)"]
