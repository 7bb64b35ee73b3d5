"""`godrays-jax fit ... --report` and `apply` timed as users run them: fresh processes, an empty compilation cache
and then a warm one, peak memory.

    python benchmarks/bench_fit_cli.py [--sizes 320x180 960x540 1920x1080] [--scenes SCENE ...]
        [--fit-options "--light auto"] [--apply] [--tests] [--json FILE]

Each case runs the command line in a child process (`_child.py` below: the command's own `script`, with a
`jax.monitoring` listener that sums the time JAX spends compiling or loading compiled programs, and timers around
`fit` and what follows it), twice: first with `GODRAYS_JAX_CACHE_DIR` an empty folder (cold), then again on the
folder the first run filled (warm). Recorded: wall seconds, seconds compiling (XLA's compilation or a load from
the cache), seconds in `fit`, seconds of the checks after it (metrics, `determination`, the report and the files),
the fit's steps, the child's peak RSS (`resource.getrusage(RUSAGE_CHILDREN)`, a fresh process per run), and how
many of XLA's slow-compile banners its stderr held (summed in a line after the table).

Frames: the `hidden_sun` reference at its own 320x180, and pairs made from it at other sizes (each pixel repeated, the
light's position scaled, its field of view kept in the header). `--scenes`: other references
(`benchmarks/references/SCENE_clean.exr`, `SCENE_fog_a.exr`) made the first size's in the same way (every light of the
header scaled, their distances and tints kept), fitted with their depth map seen from the light (`SCENE_light_view.exr`,
`--light-view`) where they ship one. `--fit-options`: options every fit takes besides (`--light auto`: the light's
search and the fits around it, the headers' lights unused). `--apply`: `godrays-jax apply` of the default fog
(`volumetric_haze`) at 1920x1080, cold and warm, and its forward pass in-process (the median of 7 after one that
compiles, and the page faults a call): the effect jitted inside `values_only()` (its fields constants), `apply`'s
program (`frames_function` on a group of one frame), a fit's render (`render_compiled`: the fields and the light's
distance its arguments), and the effect jitted as a caller who differentiates it traces it; in a fresh process with
glibc's defaults, then in one with the tunables docs/fitting.md gives a user's own process (`USERS_TUNABLES`), the two
alternated twice. `--tests`: the README's test command's wall time. `uptime` first: the machine may be shared.
"""

import argparse
import json
import os
import shlex
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REFERENCE = HERE / "references" / "hidden_sun"

FORWARD_RUNS = 7
"""Calls of each forward pass timed in-process, after the one that compiles it."""

USERS_TUNABLES = ("glibc.malloc.hugetlb=1:glibc.malloc.arena_max=1:glibc.malloc.mmap_threshold=33554432"
                  ":glibc.malloc.trim_threshold=2147483647")  # fmt: skip
"""glibc's tunables docs/fitting.md gives a user's own process that calls the same programs many times: XLA allocates
a program's temporaries afresh on every call, and with glibc's defaults their pages are faulted in again 4 KiB at a
time."""

CHILD = textwrap.dedent(
    """
    import os, sys
    import godrays_jax_script
    # Started again with glibc's huge pages where the `godrays-jax` script is (before anything else is imported).
    environ = godrays_jax_script.restart_with_huge_pages([sys.argv[0], *sys.argv[2:]], dict(os.environ))
    if environ is not None:
        os.execve(sys.executable, sys.orig_argv, environ)
    import atexit, json, time
    import jax
    compiling = [0.0]
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, seconds, **_: compiling.__setitem__(0, compiling[0] + seconds)
        if event == "/jax/core/compile/backend_compile_duration" else None
    )
    from godrays_jax.app import cli, fit_command
    times = {}
    fit = fit_command.fit
    def timed_fit(*args, **kwargs):
        start = time.perf_counter()
        try:
            return fit(*args, **kwargs)
        finally:
            times["fit"] = time.perf_counter() - start
            times["fit_end"] = time.perf_counter()
    fit_command.fit = timed_fit
    record_path = sys.argv.pop(1)
    console_main, status = cli.console_main, []
    def recorded_console_main():
        status.append(console_main())
        return status[-1]
    cli.console_main = recorded_console_main
    def write_record():  # `cli.script` ends the process after the exit handlers, so the record is written by one
        end = time.perf_counter()
        record = {"status": status[0] if status else None, "compiling": compiling[0], "fit": times.get("fit"),
                  "after_fit": end - times["fit_end"] if "fit_end" in times else None}
        with open(record_path, "w") as stream:
            json.dump(record, stream)
    atexit.register(write_record)
    cli.script()  # as the `godrays-jax` script runs it, once started
    """
)


def frame_pair(folder: Path, height: int, width: int, reference: Path = REFERENCE) -> tuple[Path, Path]:
    """The reference's clean frame and fog render at `height x width` (pixels repeated), its header kept: every
    light (positions scaled), their distances and tints, the field of view."""
    import godrays_jax as gr
    from godrays_jax.app.options import read_target
    from godrays_jax.primitives.image_files import read_header
    from godrays_jax.primitives.light_metadata import lights_metadata, read_light, read_lights

    clean, fog = Path(f"{reference}_clean.exr"), Path(f"{reference}_fog_a.exr")
    frame = gr.read_buffers(clean)
    if (frame.height, frame.width) == (height, width):
        return clean, fog
    rows = np.arange(height) * frame.height // height
    cols = np.arange(width) * frame.width // width
    pick = lambda image: np.asarray(image)[rows][:, cols]  # noqa: E731
    scaled_xy = lambda xy: (xy[0] * width / frame.width, xy[1] * height / frame.height)  # noqa: E731
    (x, y), in_front = read_light(clean)
    spec = read_header(clean)
    # The camera and the lights' distances as the reference's header has them (the field of view, `inf` for the sun).
    header = {name: spec.getattribute(name) for name in ("godrays:fov_x_deg", "godrays:light_depth")}
    header = {name: value for name, value in header.items() if value is not None}
    lights = read_lights(clean)
    if lights is not None:
        header.update(lights_metadata([light._replace(xy=scaled_xy(light.xy)) for light in lights]))
    scaled = gr.Buffers(color=pick(frame.color), depth=pick(frame.depth), coverage=pick(frame.coverage))
    frame_path, target_path = folder / f"clean_{width}x{height}.exr", folder / f"fog_{width}x{height}.exr"
    gr.write_buffers(frame_path, scaled, light_xy=scaled_xy((x, y)), light_in_front=in_front, metadata=header)
    gr.write_image(target_path, pick(read_target(str(fog))))
    return frame_path, target_path


def measured(arguments: list[str], folder: Path) -> list[dict]:
    """The command cold (an empty cache) then warm (the cache the first run filled)."""
    cache = folder / "cache"
    return [run_peak(arguments, cache, folder) for _ in ("cold", "warm")]


def run_peak(arguments: list[str], cache: Path, folder: Path) -> dict:
    """`run_command` in a grandchild whose own peak RSS is read (RUSAGE_CHILDREN of this process keeps a maximum)."""
    script = folder / "peak.py"
    script.write_text(
        "import json, resource, subprocess, sys\n"
        "done = subprocess.run(sys.argv[2:], env=None)\n"
        "json.dump({'rc': done.returncode, 'peak': resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss},"
        " open(sys.argv[1], 'w'))\n"
    )
    peak_path = folder / "peak.json"
    record_path = folder / "record.json"
    record_path.unlink(missing_ok=True)
    (folder / "child.py").write_text(CHILD)
    start = time.perf_counter()
    done = subprocess.run(
        [sys.executable, str(script), str(peak_path), sys.executable, str(folder / "child.py"), str(record_path),
         *arguments],
        capture_output=True, text=True, env={**os.environ, "GODRAYS_JAX_CACHE_DIR": str(cache)},
    )  # fmt: skip
    wall = time.perf_counter() - start
    peak = json.loads(peak_path.read_text())
    if peak["rc"] != 0:
        raise RuntimeError(f"{' '.join(arguments)} failed:\n{done.stderr[-2000:]}")
    record = json.loads(record_path.read_text())
    # XLA's banner for a compile it finds slow ("Very slow compile? If you want to file a bug ...") on stderr.
    banners = sum("slow compile" in line.lower() for line in done.stderr.splitlines())
    record.update(wall=wall, stdout=done.stdout, peak_rss_mib=peak["peak"] / 1024, slow_compile_banners=banners)
    return record


def steps_of(stdout: str) -> str:
    line = next((line for line in stdout.splitlines() if line.startswith("fitted ")), "")
    return line[line.find("(") + 1 : line.rfind(")")]


def fit_rows(
    sizes: list[str], folder: Path, scenes: tuple[str, ...] = (), options: tuple[str, ...] = ()
) -> list[dict]:
    """The README's fit at each size, then each of `scenes` (reference names) at the first size, each with the
    command's `options` besides."""
    rows = []
    cases = [(size, REFERENCE) for size in sizes] + [(sizes[0], REFERENCE.with_name(scene)) for scene in scenes]
    for size, reference in cases:
        width, height = (int(n) for n in size.split("x"))
        name = "" if reference == REFERENCE else f" {reference.name}"
        case = folder / f"fit_{size}{name.replace(' ', '_')}"
        case.mkdir()
        frame, target = frame_pair(case, height, width, reference)
        # A scene whose shadows are cast from outside the frame ships the depth map seen from its light.
        light_view = reference.with_name(f"{reference.name}_light_view.exr")
        light_view = ["--light-view", str(light_view)] if light_view.exists() else []
        arguments = ["fit", str(frame), str(target), "-o", str(case / "params.json"), "--report", str(case / "report.png"),
                     *light_view, *options]  # fmt: skip
        for label, record in zip(("cold", "warm"), measured(arguments, case)):
            loss = next((line for line in record["stdout"].splitlines() if line.startswith("loss before")), "")
            rows.append(dict(case=f"fit{name} {size} + report", cache=label, wall=record["wall"], compiling=record["compiling"],
                             fit=record["fit"], after_fit=record["after_fit"], steps=steps_of(record["stdout"]),
                             peak_rss_mib=record["peak_rss_mib"], loss=loss,
                             slow_compile_banners=record["slow_compile_banners"]))  # fmt: skip
            print(_row(rows[-1]), flush=True)
    return rows


def apply_rows(folder: Path) -> list[dict]:
    case = folder / "apply_1920x1080"
    case.mkdir()
    frame, _ = frame_pair(case, 1080, 1920)
    arguments = ["apply", str(frame), "-o", str(case / "out.exr"), "--preset", "volumetric_haze"]
    rows = []
    for label, record in zip(("cold", "warm"), measured(arguments, case)):
        rows.append(dict(case="apply volumetric_haze 1920x1080", cache=label, wall=record["wall"],
                         compiling=record["compiling"], fit=None, after_fit=None, steps="",
                         peak_rss_mib=record["peak_rss_mib"], loss="",
                         slow_compile_banners=record["slow_compile_banners"]))  # fmt: skip
        print(_row(rows[-1]), flush=True)
    # Alternated, each twice: the machine's speed moves between minutes.
    for label, tunables in 2 * (("glibc's defaults", None), ("docs/fitting.md's tunables", USERS_TUNABLES)):
        environ = {key: value for key, value in os.environ.items() if key != "GLIBC_TUNABLES"}
        environ.update({"JAX_COMPILATION_CACHE_DIR": str(case / "forward_cache")},
                       **({"GLIBC_TUNABLES": tunables} if tunables else {}))  # fmt: skip
        record = case / "forward.json"
        done = subprocess.run([sys.executable, __file__, "--forward", str(frame), "--json", str(record)],
                              env=environ, capture_output=True, text=True)  # fmt: skip
        if done.returncode != 0:
            raise RuntimeError(f"the forward in-process failed:\n{done.stderr[-2000:]}")
        for name, seconds, faults in json.loads(record.read_text()):
            print(f"forward in-process, volumetric_haze 1920x1080, {name}, {label}: median {seconds:.3f} s of "
                  f"{FORWARD_RUNS}, {faults} page faults a call", flush=True)  # fmt: skip
            rows.append(dict(case=f"forward volumetric_haze 1920x1080 (in-process, {name}, {label})", cache="",
                             wall=seconds, compiling=None, fit=None, after_fit=None, steps="", peak_rss_mib=None,
                             loss="", page_faults=faults))  # fmt: skip
    return rows


def forward_medians(frame: Path) -> list[tuple[str, float, int]]:
    """The default fog's forward pass over `frame` in this process, four ways, each after one call that compiles:
    its name, the median seconds of `FORWARD_RUNS` calls and the median page faults a call (the pages of its
    temporaries faulted in again: `USERS_TUNABLES`)."""
    import resource

    import jax

    import godrays_jax as gr
    from godrays_jax.pipeline.batch import frames_function
    from godrays_jax.pipeline.compiled import render_compiled
    from godrays_jax.primitives.light_metadata import read_light

    buffers = gr.read_buffers(frame)
    (x, y), in_front = read_light(frame)
    effect = gr.preset("volumetric_haze")
    light = jax.numpy.asarray([x, y], jax.numpy.float32)
    # The effect jitted for a render (`values_only`, its fields constants), what `apply` runs (`frames_function`: a
    # group of one frame, the light's side an argument), a fit's render (`render_compiled`: the fields and the light's
    # distance arguments of one program for any values), and the effect as a caller who differentiates it traces it.

    def render(frame):
        with gr.values_only():
            return effect(frame, light, light_in_front=in_front)

    apply = frames_function(effect)
    programs = {
        "jitted, values_only": jax.jit(render),
        "apply's program": lambda frame: apply(
            jax.tree.map(lambda plane: plane[None], frame), light[None], jax.numpy.asarray([in_front])
        ),
        "a fit's render": lambda frame: render_compiled(effect, frame, light, in_front),
        "jitted, differentiable": jax.jit(lambda frame: effect(frame, light, light_in_front=in_front)),
    }
    medians = []
    for name, forward in programs.items():
        jax.block_until_ready(forward(buffers))
        seconds, faults = [], []
        for _ in range(FORWARD_RUNS):
            before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
            start = time.perf_counter()
            jax.block_until_ready(forward(buffers))
            seconds.append(time.perf_counter() - start)
            faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
        medians.append((name, float(np.median(seconds)), int(np.median(faults))))
    return medians


def test_row() -> dict:
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-n", "auto", "-m", "not slow"], cwd=HERE.parent,
                          capture_output=True, text=True)  # fmt: skip
    wall = time.perf_counter() - start
    summary = done.stdout.strip().splitlines()[-1] if done.stdout.strip() else ""
    print(f"test suite: {wall:.0f} s ({summary})", flush=True)
    return dict(case='python -m pytest -q -n auto -m "not slow"', cache="", wall=wall, compiling=None, fit=None, after_fit=None,
                steps=summary, peak_rss_mib=None, loss="")  # fmt: skip


def _number(value, digits=1):
    return "" if value is None else f"{value:.{digits}f}"


def _row(row: dict) -> str:
    return (
        f"| {row['case']} | {row['cache']} | {_number(row['wall'])} | {_number(row['compiling'])} | "
        f"{_number(row['fit'])} | {_number(row['after_fit'])} | {row['steps']} | {_number(row['peak_rss_mib'], 0)} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="*", default=["320x180", "960x540", "1920x1080"])
    parser.add_argument(
        "--scenes", nargs="*", default=[],
        help="also fit these references (benchmarks/references/SCENE_*.exr, with its light view) at the first size",
    )  # fmt: skip
    parser.add_argument("--fit-options", default="", help="options every fit also takes, as a shell would split them: "
                        "'--light auto' times the light's search and the fits that place it")  # fmt: skip
    parser.add_argument("--apply", action="store_true", help="also time apply of volumetric_haze at 1920x1080")
    parser.add_argument("--tests", action="store_true", help="also time the README's test command")
    parser.add_argument("--json", type=Path, help="write the rows here as JSON")
    parser.add_argument("--forward", type=Path, help=argparse.SUPPRESS)  # apply's child: the forward in-process
    args = parser.parse_args()
    if args.forward:
        args.json.write_text(json.dumps(forward_medians(args.forward)) + "\n")
        return
    print(subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip())
    print("| case | cache | wall s | compiling s | fit s | after the fit s | steps | peak RSS MiB |")
    print("|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as folder:
        rows = fit_rows(args.sizes, Path(folder), tuple(args.scenes), tuple(shlex.split(args.fit_options)))
        if args.apply:
            rows += apply_rows(Path(folder))
    banners = sum(row.get("slow_compile_banners", 0) for row in rows)
    print(f"XLA's slow-compile banners on the commands' stderr: {banners} in {len(rows)} runs", flush=True)
    if args.tests:
        rows.append(test_row())
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
