"""The `godrays-jax` command line: its parser, and `main`, which runs the chosen command's module.

Every command reports an error as one line on stderr and exits non-zero; no
command leaves a partial output file (writes go through a temporary file that is
renamed into place). `COMMANDS` adds each subcommand's options; its handler
is `run(args)` in `godrays_jax.app.<command>_command`.
"""

import argparse
import atexit
import importlib
import os
import re
import sys
import threading
import traceback
import typing
import warnings
from collections.abc import Callable

import jax

import godrays_jax
from godrays_jax.app import allocator, compile_cache
from godrays_jax.app.options import (
    DEFAULT_PRESET,
    LIGHT_AUTO,
    SKY_DEPTH_HELP,
    parse_fit_light,
    parse_fov,
    parse_light_depths,
    parse_light_tints,
    parse_lights,
    parse_sky_depth,
    warn,
)
from godrays_jax.effects.presets import PRESETS
from godrays_jax.pipeline import exported
from godrays_jax.pipeline.sequences import FRAME_PATTERN_HELP, expand_frames
from godrays_jax.primitives.checks import error_line
from godrays_jax.primitives.frame_reading import SKY_DEPTH
from godrays_jax.primitives.image_files import image_size

PROGRAM = "godrays-jax"

MEMORY_HINT = "a smaller frame, or fit's --coarse-factor, needs less; docs/fitting.md says how memory grows"
"""What to do about an out-of-memory error: said after XLA's one line."""


_NEGATIVE_VALUE = re.compile(r"-\s*(?:\d|\.\d)")
"""A value that starts like a negative number (`-5,10`), which argparse would take for an option."""

_TAKES_NEGATIVE_VALUES = {"--light": _NEGATIVE_VALUE, "--frames": re.compile(r"-\d+\s*(?:[-:]\s*-?\d+)?\s*$")}
"""Options whose value may start with a minus sign: a light's position, a range of frame numbers (batch's; fit's
`--frames` takes file names)."""


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")

    def parse_known_args(self, args=None, namespace=None):
        # `--light -5,10` (a light left of or above the frame) and `--frames -2-0` (negative frame numbers):
        # argparse reads such a value as an unknown option, so it is attached (`--light=-5,10`) before parsing;
        # nothing else is rewritten.
        args = list(sys.argv[1:] if args is None else args)
        joined = []
        for arg in args:
            if joined and joined[-1] in _TAKES_NEGATIVE_VALUES and _TAKES_NEGATIVE_VALUES[joined[-1]].match(arg):
                joined[-1] = f"{joined[-1]}={arg}"
            else:
                joined.append(arg)
        return super().parse_known_args(joined, namespace)


def _add_cache_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--no-cache", action="store_true",
        help=f"neither read nor write the compilation cache (default: {compile_cache.ENVIRONMENT_VARIABLE} or "
        "~/.cache/godrays_jax; `godrays-jax cache` shows or clears it)",
    )  # fmt: skip


def _add_effect_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_mutually_exclusive_group()
    group.add_argument(
        "--preset", choices=sorted(PRESETS), help=f"a source article's effect (default {DEFAULT_PRESET})"
    )
    group.add_argument("--params", metavar="FILE", help="effect parameters as JSON (from `fit` or save_effect)")


FRAME_HELP = (
    "the frame: EXR (or any OpenImageIO format) with colour and depth channels (plain, Nuke or Blender names), or "
    "an image without depth (a photograph, a plate: the open sky comes from its alpha or its bright parts)"
)


LIGHT_VIEW_HELP = (
    "a depth map seen from the light, with its camera in its header (docs/file_formats.md; render --light-view "
    "writes one): the volumetric fog's shadows of what lies outside the frame"
)


def _add_frame_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--color-layer", metavar="LAYER",
        help="the colour layer, e.g. ViewLayer.Combined (channels LAYER.R/G/B/A); default: plain R, G, B, else the "
        "one layer with them (Blender's ViewLayer.Combined)",
    )  # fmt: skip
    parser.add_argument(
        "--depth-channel", metavar="NAME",
        help="the depth channel, e.g. ViewLayer.Depth.Z; default: Z, depth.Z (Nuke), depth, then the colour "
        "layer's view layer's Depth.Z (Blender)",
    )  # fmt: skip
    parser.add_argument("--sky-depth", type=parse_sky_depth, default=SKY_DEPTH, metavar="DEPTH", help=SKY_DEPTH_HELP)
    parser.add_argument(
        "--depth-kind", choices=("auto", "planar", "ray"), default="auto",
        help="what the depth channel measures: distance along each camera ray (ray: Mitsuba, godrays-jax render) or "
        "along the camera's axis (planar: Blender's Z, hardware depth); default auto: planar for Blender's files, "
        "ray otherwise. Effects read ray depth: planar depth is converted with the field of view",
    )  # fmt: skip
    parser.add_argument(
        "--fov-x-deg", type=parse_fov, metavar="DEG",
        help="the camera's horizontal field of view in degrees, for effects with a fov_x_deg field (fit keeps it "
        "fixed) and to convert planar depth; default: the frame's header (godrays:fov_x_deg, worldToNDC, Blender's "
        "Lens), else the effect's own",
    )  # fmt: skip


def _add_dither_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--no-dither", action="store_true",
        help="round 8-bit outputs (PNG, JPEG, TIFF) to the nearest code; by default they get triangular dither of "
        "one code, seeded by the frame number, so smooth glows do not band",
    )  # fmt: skip


def _add_apply(subparsers) -> None:
    parser = subparsers.add_parser(
        "apply",
        help="apply an effect to a frame",
        description="Apply a light-scattering effect to a frame (colour + depth) and write the result.",
    )
    parser.add_argument("buffers", help=FRAME_HELP)
    parser.add_argument("-o", "--output", required=True, help="output image (.exr, .png, .tif, .jpg)")
    parser.add_argument(
        "--light",
        type=parse_lights,
        metavar="X,Y[,behind][;X,Y...]",
        help="the light's pixel position (x right, y down; may be negative: --light -5,10), ',behind' for a light "
        "behind the camera; several lights separated by ';' (--light '160,40;300,90,behind'), their light added; "
        "default: the light `fit --light auto` found for this frame, written beside --params "
        "(PARAMS.light.json), else every light of the frame's godrays:lights metadata (a render of several), else "
        "its godrays:light_px",
    )
    _add_light_depth_and_tint(
        parser, depth_default="the frame's godrays:lights_depth or godrays:light_depth metadata, else inf",
        tint_default="the frame's godrays:lights_tint metadata when it stores several lights, else 1,1,1",
    )  # fmt: skip
    _add_effect_options(parser)
    _add_frame_options(parser)
    parser.add_argument("--light-view", metavar="EXR", help=LIGHT_VIEW_HELP)
    parser.add_argument(
        "--flare-texture", metavar="IMAGE", help="the flare texture of a GodRays or FlareOuts effect (any image)"
    )
    parser.add_argument("--layer-only", action="store_true", help="write the effect alone, not blended on the frame")
    _add_dither_option(parser)
    _add_cache_option(parser)
    parser.set_defaults(handler="godrays_jax.app.apply_command:run")


def _add_batch(subparsers) -> None:
    parser = subparsers.add_parser(
        "batch",
        help="apply an effect to a sequence of frames",
        description=(
            "Apply an effect to every frame of a sequence, reading and writing on background threads, "
            "compiling once, spreading frames over all JAX devices. Each output keeps its input's name, "
            "channels, metadata and format (only R, G, B change). Bad frames are reported and skipped; "
            "the run then exits with status 1."
        ),
    )
    parser.add_argument("pattern", help=FRAME_PATTERN_HELP.replace("%", "%%"))
    parser.add_argument("-o", "--output", required=True, metavar="OUT_DIR", help="output folder (created if missing)")
    lights = parser.add_mutually_exclusive_group()
    lights.add_argument(
        "--light", type=parse_lights, metavar="X,Y[,behind][;X,Y...]",
        help="the same light pixel position for every frame (',behind': behind the camera); several lights "
        "separated by ';', their light added",
    )  # fmt: skip
    lights.add_argument(
        "--light-from-metadata", action="store_true", help="each frame's godrays:light_px metadata (the default)"
    )
    lights.add_argument(
        "--light-track", metavar="FILE", help="per-frame lights: CSV rows 'frame,x,y[,in_front]' or JSON; frames between keys are interpolated linearly"
    )
    _add_light_depth_and_tint(
        parser, depth_default="the first frame's godrays:light_depth metadata, else inf (the same in every frame)",
        tint_default="1,1,1",
    )  # fmt: skip
    _add_effect_options(parser)
    _add_frame_options(parser)
    parser.add_argument(
        "--light-view", metavar="EXR_PATTERN",
        help=f"{LIGHT_VIEW_HELP}; one file for every frame, or a pattern (as the frames') whose file numbered N "
        "goes to frame N",
    )  # fmt: skip
    parser.add_argument("--layer-only", action="store_true", help="write the effect alone, not blended on the frame")
    parser.add_argument("--ext", help="write this format instead (e.g. png): colour only, display-encoded")
    _add_dither_option(parser)
    parser.add_argument("--resume", action="store_true", help="skip frames whose output exists")
    parser.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    parser.add_argument("--dry-run", action="store_true", help="list what would run, write nothing")
    parser.add_argument(
        "--frames", metavar="FIRST-LAST", help="only frame numbers in this inclusive range (negative too: -2-0)"
    )
    parser.add_argument("--shard", metavar="I/N", help="only the I-th (0-based) of N contiguous shares (one per host)")
    parser.add_argument(
        "--distributed", action="store_true", help="jax.distributed.initialize(); this process's share of the frames"
    )
    parser.add_argument(
        "--coordinator", metavar="HOST:PORT", help="with --distributed, where cluster auto-detection finds none"
    )
    parser.add_argument("--num-processes", type=int, metavar="N", help="with --distributed and --coordinator")
    parser.add_argument("--process-id", type=int, metavar="I", help="with --distributed and --coordinator: 0..N-1")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress line")
    _add_cache_option(parser)
    parser.set_defaults(handler="godrays_jax.app.batch_command:run")


def _add_tune(subparsers) -> None:
    parser = subparsers.add_parser(
        "tune",
        help="tune an effect live in the browser",
        description="Serve a page on 127.0.0.1 with a slider for every parameter of an effect, the light draggable "
        "on the frame, before/after and difference views, fit to a target, and save (the JSON `apply --params` reads).",
    )
    parser.add_argument("buffers", help=FRAME_HELP)
    parser.add_argument("--target", help="a reference image of the frame's size, for the difference view and fitting")
    parser.add_argument(
        "--light",
        type=parse_lights,
        metavar="X,Y[,behind][;X,Y...]",
        help="the light's starting pixel position (',behind': behind the camera); several separated by ';', each "
        "dragged, their light added; default: every light of the frame's godrays:lights metadata, else its "
        "godrays:light_px",
    )
    _add_light_depth_and_tint(
        parser, depth_default="the frame's godrays:lights_depth or godrays:light_depth metadata, else inf",
        tint_default="the frame's godrays:lights_tint metadata when it stores several lights, else 1,1,1",
    )  # fmt: skip
    _add_effect_options(parser)
    parser.add_argument("--light-view", metavar="EXR", help=LIGHT_VIEW_HELP)
    parser.add_argument("--port", type=int, default=8000, help="port on 127.0.0.1 (default 8000; 0: any free port)")
    parser.add_argument("-o", "--output", default="params.json", help="where save writes (default params.json)")
    _add_frame_options(parser)
    parser.add_argument(
        "--preview-pixels", type=int, default=40_000, help="pixels at most in drag previews (default 40000)"
    )
    parser.add_argument("--fit-steps", type=int, default=20, help="solver steps at most per fit (default 20)")
    _add_cache_option(parser)
    parser.set_defaults(handler="godrays_jax.app.tune_command:run")


def _add_light_depth_and_tint(parser, *, depth_default: str, tint_default: str) -> None:
    """`--light-depth` and `--light-tint`, one value for every light of `--light` or one per light (apply, batch,
    tune), with each command's defaults."""
    parser.add_argument(
        "--light-depth", type=parse_light_depths, metavar="D[;D...]",
        help="the light's distance from the camera in scene units, or inf (read by the fogs and the XNA preset's "
        f"depth test and step clamp), one for every light or one per light; default: {depth_default}",
    )  # fmt: skip
    parser.add_argument(
        "--light-tint", type=parse_light_tints, metavar="R,G,B[;R,G,B...]",
        help="each light's tint, the linear RGB its light is multiplied by: its colour and intensity beside the "
        f"others' (one for every light or one per light); default: {tint_default}",
    )  # fmt: skip


def _add_fit(subparsers) -> None:
    parser = subparsers.add_parser(
        "fit",
        help="fit an effect's parameters to reference frames",
        description="Fit an effect's parameters so it matches target frames (one parameter set for all frames), "
        "write them as JSON for `apply --params`. Progress goes to stderr; the fitted parameters and the loss "
        "before/after to stdout.",
    )
    parser.add_argument("buffers", help=FRAME_HELP)
    parser.add_argument("target", help="the reference image of the same size (linear; EXR recommended)")
    parser.add_argument(
        "--frames", nargs=2, action="append", metavar=("BUFFERS", "TARGET"),
        help="one more frame and its target sharing the parameters (repeatable)",
    )  # fmt: skip
    parser.add_argument(
        "--light", type=parse_fit_light, action="append", metavar="X,Y[,behind][;X,Y...]|auto",
        help="the light's pixel position, once per frame in order (',behind': behind the camera; several lights "
        "separated by ';', every one drawn and the fitted fields shared by all), or 'auto': found before the fit "
        "(once for every frame): every light in view by its own pixels (a sun's disc, a lamp's bulb, its distance "
        "with it; the others' tints fitted), else one light from the frame and its target; default: each frame's "
        "godrays:lights or godrays:light_px metadata; a light found is written beside -o (PARAMS.light.json) for "
        "apply --params",
    )  # fmt: skip
    parser.add_argument("--light-view", action="append", metavar="EXR", help=f"{LIGHT_VIEW_HELP}; once per frame, in order")
    parser.add_argument(
        "--fit-light", action="store_true",
        help="refine each given or stored light (one a frame) as --light auto finds one, from it, before the fit "
        "(the light in view nearest it, where one is)",
    )  # fmt: skip
    _add_light_depth_and_tint(
        parser, depth_default="each frame's godrays:lights_depth or godrays:light_depth metadata, else inf",
        tint_default="each frame's godrays:lights_tint metadata when it stores several lights, else 1,1,1; the "
        "fitted light_color is the first light's, the others' tints taken over the first's and fitted from there "
        "(--fixed light_tints keeps them)",
    )  # fmt: skip
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--preset", choices=sorted(PRESETS), help="start from a preset (default: volumetric_haze, VolumetricFog)")
    group.add_argument("--params", metavar="FILE", help="start from parameters saved as JSON")
    _add_frame_options(parser)
    parser.add_argument("-o", "--output", required=True, help="where to write the fitted parameters (JSON)")
    parser.add_argument("--report", metavar="PNG", help="picture: target, fitted, difference heat map, loss curve")
    parser.add_argument("--loss", choices=("mse", "l1", "charbonnier", "ssim"), default="mse", help="default mse")
    parser.add_argument("--space", choices=("display", "linear"), default="display", help="compare in x/(1+x) (default) or linear")
    parser.add_argument(
        "--solver", choices=("auto", "levenberg_marquardt", "gauss_newton", "bfgs"), default="auto",
        help="auto: Levenberg-Marquardt for mse, BFGS otherwise; gauss_newton needs a start near the solution",
    )  # fmt: skip
    parser.add_argument(
        "--fixed", metavar="A,B",
        help="comma-separated fields to keep as they are (light_tints: the tints of the lights beside the first, "
        "which a fit of several lights fits by default)",
    )  # fmt: skip
    parser.add_argument("--max-steps", type=int, default=50, help="solver steps at most, in each phase (default 50)")
    parser.add_argument(
        "--coarse-factor", type=int, metavar="N",
        help="race the starts at 1/N of the frames' resolution, then fit at full resolution from there; default: the "
        "smallest N that brings the first frame to 160x90 pixels or fewer (1: no coarse phase)",
    )  # fmt: skip
    parser.add_argument(
        "--fractional-counts", action="store_true",
        help="save counts (num_samples, ...) as fitted; by default they are rounded to integers",
    )  # fmt: skip
    _add_cache_option(parser)
    parser.set_defaults(handler="godrays_jax.app.fit_command:run")


def _add_render(subparsers) -> None:
    parser = subparsers.add_parser(
        "render",
        help="render a scene file to a frame",
        description="Render a scene (JSON or TOML) with the built-in rasterizer to an EXR frame: R, G, B, A (coverage), "
        "Z (distance along the camera ray), N.X/N.Y/N.Z, object_id, light.Y (the galaxy-engine VLS article's pass), glow.R/G/B/A (the sun-overcasting article's pass), glowtarget.R/G/B (the VBex article's glow target). "
        "The light's pixel position is stored as godrays:light_px for apply/fit, its distance as godrays:light_depth.",
    )
    parser.add_argument("scene", help="scene file (.json or .toml)")
    parser.add_argument("-o", "--output", required=True, help="output frame (.exr)")
    parser.add_argument("--light", action="store_true", help="also print the light's pixel position and distance")
    parser.add_argument("--no-glow", action="store_true", help="skip the glow pass (one rasterization instead of two)")
    parser.add_argument(
        "--light-view", metavar="EXR",
        help="also write the depth seen from the first light (a shadow map, docs/file_formats.md), which apply and "
        "fit take as --light-view: the volumetric fog's shadows of what lies outside the frame",
    )  # fmt: skip
    parser.add_argument(
        "--light-view-reach", type=float, metavar="UNITS",
        help="the radius around the camera the light view covers, scene units (the fog's max_distance); default: "
        "the volumetric_haze preset's",
    )  # fmt: skip
    _add_cache_option(parser)
    parser.set_defaults(handler="godrays_jax.app.render_command:run")


def _add_cache(subparsers) -> None:
    parser = subparsers.add_parser(
        "cache",
        help="show or clear the compilation cache",
        description="Compiled effects are kept in a cache folder so later runs start without compiling: "
        f"${compile_cache.ENVIRONMENT_VARIABLE}, else $XDG_CACHE_HOME/godrays_jax (~/.cache/godrays_jax), at most "
        f"{compile_cache.MAX_BYTES >> 20} MiB of compiled programs and {exported.MAX_BYTES >> 20} MiB of "
        f"traced ones in its {compile_cache.EXPORTED_FOLDER}/ folder (least recently used entries are dropped first).",
    )
    parser.add_argument(
        "--clear", action="store_true",
        help="remove every cached program (only the entries the library wrote: the folder's other files stay)",
    )  # fmt: skip
    parser.set_defaults(handler="godrays_jax.app.cli:run_cache", no_cache=True)


def run_cache(args) -> int:
    """`godrays-jax cache`: where the compilation cache is, how large, and `--clear`."""
    directory = compile_cache.cache_dir()
    if args.clear:
        removed, gone = compile_cache.clear(directory)
        kept = "" if gone or not os.listdir(directory) else f"; kept {directory}: it holds other files"
        print(f"cleared {removed} cached program file(s) from {directory}{kept}")
        return 0
    files, size = compile_cache.cache_size(directory)
    caps = f"{compile_cache.MAX_BYTES >> 20} MiB compiled + {exported.MAX_BYTES >> 20} MiB traced"
    print(f"{directory}: {files} file(s), {size / (1 << 20):.1f} MiB (caps {caps})")
    return 0


COMMANDS: list[Callable[[argparse._SubParsersAction], None]] = [
    _add_apply, _add_batch, _add_tune, _add_fit, _add_render, _add_cache
]
"""Functions that each add one subcommand (with `set_defaults(handler=...)`)."""


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog=PROGRAM, description="Differentiable screen-space light scattering (god rays, glow, flares).")
    parser.add_argument("--version", action="version", version=f"%(prog)s {godrays_jax.__version__}")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_Parser)
    for add_command in COMMANDS:
        add_command(subparsers)
    for command in subparsers.choices.values():
        command.add_argument("--verbose", action="store_true", help="on an error, its traceback after the one line")
    return parser


def console_main() -> int:
    """`main` as the `godrays-jax` script runs it (`script`): in a process whose allocator keeps the memory XLA frees
    where the command calls the same programs over and over (`repeats_programs`)."""
    return main(keep_freed_memory=True)


def script() -> typing.NoReturn:
    """The `godrays-jax` script and `python -m godrays_jax`: `console_main`, then the process ends without the
    interpreter's teardown.

    Tearing the interpreter down frees, one by one and through a last collection of cycles, every object JAX's
    caches hold: a large share of a short command's time (benchmarks/README.md, "Command start-up and the
    compilation cache"). Every file the command writes is closed by then, and the exit handlers still run (JAX's
    wait for its effects and its distributed shutdown among them). A thread still running that is not a daemon
    (none of the commands leaves one) gets the interpreter's own exit, which waits for it."""
    status = console_main()
    _flush_output()
    main_thread = threading.main_thread()
    if any(thread is not main_thread and not thread.daemon for thread in threading.enumerate()):
        sys.exit(status)
    atexit._run_exitfuncs()  # what the interpreter's exit runs first; `os._exit` alone would skip them
    _flush_output()
    os._exit(status)


def _flush_output() -> None:
    """Flush stdout and stderr; a reader that has gone (`godrays-jax ... | head`) is no error of the command's."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe, or a stream closed already
            pass


def fit_frame_sizes(args: argparse.Namespace) -> list[tuple[int, int]]:
    """`(width, height)` of each frame a `fit` reads (the first, then each of `--frames`), from the files' headers.

    Raises:
        OSError, ValueError: a frame that cannot be read.
    """
    return [image_size(path) for path in [args.buffers, *(pair[0] for pair in args.frames or ())]]


def repeats_programs(args: argparse.Namespace) -> bool:
    """Whether the command calls the same compiled programs many times on buffers its process may keep between
    the calls (`allocator.keep_freed_memory`): the tuner (its preview is small), and a batch or a fit of at most
    `allocator.KEPT_FIT_PIXELS` pixels (a batch's frames each, a fit's frames together). On larger frames the
    buffers kept grew beyond the commands' memory bounds for little time (`benchmarks/README.md`, "The fit as
    users run it"). A frame whose size cannot be read counts as large: the command says what is wrong with it."""
    if args.command == "tune":
        return True
    try:
        if args.command == "batch":
            sizes = [image_size(expand_frames(args.pattern)[0])]
        elif args.command == "fit":
            sizes = fit_frame_sizes(args)
        else:
            return False
    except (OSError, ValueError, IndexError):
        return False
    return sum(width * height for width, height in sizes) <= allocator.KEPT_FIT_PIXELS


_FIT_FILES = frozenset({"buffers", "target", "frames", "output", "report", "params", "light_view", "verbose", "no_cache"})
"""`fit`'s arguments that name files, or change nothing it compiles: left out of `fit_signature`."""


def fit_signature(args: argparse.Namespace) -> str | None:
    """What decides the programs a `fit` compiles, as text: its frames' sizes, its other options, whether a
    params file and light views are given, the package's source and JAX's version; None where a frame's size
    cannot be read. Two fits of frames alike (another shot of the same size) share it."""
    try:
        sizes = fit_frame_sizes(args)
    except (OSError, ValueError, IndexError):
        return None
    options = sorted((name, value) for name, value in vars(args).items() if name not in _FIT_FILES)
    given = (args.params is not None, len(args.light_view or ()))
    return repr((sizes, given, options, exported.source_digest(), jax.__version__))


def compiles_first(args: argparse.Namespace) -> bool:
    """Whether the command spends more of its time compiling its large programs than calling them: a fit that the
    compilation cache has not seen finish (`compile_cache.holds_fit` of its `fit_signature`), or any fit without the
    cache; not one that places its lights by whole fits (`--light auto`, `--fit-light`), which calls the programs of
    a dozen fits and more."""
    if args.command != "fit" or args.fit_light or LIGHT_AUTO in (args.light or ()):
        return False
    signature = None if args.no_cache else fit_signature(args)
    return signature is None or not compile_cache.holds_fit(signature)


def main(argv: list[str] | None = None, *, keep_freed_memory: bool = False) -> int:
    """Run the CLI; returns the exit status (0 success, 1 error, 2 usage, 130 interrupted). `keep_freed_memory`:
    tune the process's allocator for the commands that repeat their programs (`repeats_programs`), and hand
    what the compiler frees back to the kernel after every long compile (`allocator.hand_back_after_compiling`); the
    `godrays-jax` command does, a call from your own process by default does not."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if keep_freed_memory:
        allocator.hand_back_after_compiling()
        if repeats_programs(args):
            allocator.keep_freed_memory(arenas=allocator.COMPILING_ARENAS if compiles_first(args) else 1)
    cached = False
    try:
        with warnings.catch_warnings():
            # The library's warnings (a params file's old field name) as one line each, like every other message.
            warnings.showwarning = lambda message, *_, **__: warn(args.command, str(message))
            if not args.no_cache:
                try:
                    compile_cache.enable()
                    cached = True
                except compile_cache.CacheUnavailable as error:
                    warn(args.command, f"{error}; running without a cache")
            module, function = args.handler.split(":")
            # Only the chosen command's module is imported: `apply` never loads the rasterizer or the solver.
            status = getattr(importlib.import_module(module), function)(args)
            if status == 0 and cached and args.command == "fit" and (signature := fit_signature(args)) is not None:
                compile_cache.remember_fit(signature)
            return status
    except KeyboardInterrupt:
        print(f"{PROGRAM} {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as error:  # every failure becomes one line; its traceback only when asked for
        line = error_line(error)
        if "RESOURCE_EXHAUSTED" in line:
            line += f" (the frame needs more memory than this machine has free: {MEMORY_HINT})"
        print(f"{PROGRAM} {args.command}: error: {line}", file=sys.stderr)
        if args.verbose:
            traceback.print_exception(error, file=sys.stderr)
        return 1


