"""The fit's compiled forward-mode Jacobian against reverse mode, on every path-traced reference.

    python benchmarks/fit_jacobians.py [SCENE ...] [--tolerance 1e-4]

`fit` linearises its loss by a vmapped forward-mode Jacobian (`fit_programs.forward_mode`
in `godrays_jax/pipeline/fit.py`), compiled. XLA has compiled such Jacobians
of `VolumetricFog` with one lane's values in another's, on some machines and
not on others (benchmarks/README.md, "The fit's Jacobian and XLA": XLA's
YNNPACK fusions; `tests/test_volumetric.py` compiles its case without them),
and on a frame of the size the fits use a wrong lane only shows as a fit that
stalls. Per scene (`benchmarks/references/scenes.py`)
this builds the problem `fit` starts from by default (`volumetric_haze`'s
stand-in, `Effect.fit_stand_in`, at the frame's field of view, the scene's light, the display-space MSE against fog
A, every field in its bounds fitted, the field of view too) and compares the
gradient of the loss through `fit_programs.forward_mode` (by the effect's stages, as `fit`
takes it), compiled, with reverse mode,
compiled: the largest difference over the unknowns whose columns `fit` takes
by derivatives, relative to the largest gradient. The columns it takes by
central differences (`Effect.DIFFERENCED_STAGES`: the field of view's) are
compared apart, each relative to its exact entry: a difference's error, not
a mixed lane. Run it after a change to a kernel the fit reaches or to the JAX
stack; about half an hour for the sixteen scenes on two cores, each compiling
both gradients. Exits 1 when a scene's derivatives are beyond `--tolerance`.
"""

import argparse
import math
import sys
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import godrays_jax as gr
from godrays_jax.pipeline.fit_programs import objective_function as _objective_function
from godrays_jax.pipeline.problem import FitProblem, as_frames, fitted_bounds, start_point

sys.path.insert(0, str(Path(__file__).resolve().parent / "references"))
from baseline import read_rgb  # noqa: E402  (the references' folder joins the path first)
from scenes import BY_NAME, SCENES  # noqa: E402


def relative_difference(scene) -> tuple[int, float, float]:
    """How many unknowns the default start fits; the largest |forward - reverse| over those `fit` differentiates /
    max |reverse|; and over those it differences, the largest |forward - reverse| / |reverse| (NaN where none)."""
    frame = gr.read_buffers(scene.clean)
    start = eqx.tree_at(lambda effect: effect.fov_x_deg, gr.preset("volumetric_haze"), jnp.float32(scene.fov_x_deg))
    start = start.fit_stand_in()  # what `fit` differentiates (`Effect.fit_stand_in`)
    target = jnp.asarray(read_rgb(scene.fog_a), jnp.float32)
    light = jnp.asarray(scene.light_px, jnp.float32)
    frame_data = as_frames(frame, light, target, scene.light_in_front, scene.light_depth)
    problem = FitProblem.of(start, fitted_bounds(start), frame_data[0], loss="mse", space="display")
    y = start_point(problem, jnp.float32)

    def objective(flat, frame_data):
        return problem.objective(problem.effect_at(flat), frame_data)

    def through_forward_mode(flat, frame_data):
        return _objective_function(flat, (problem, frame_data))[0]  # as `fit` takes it: by the effect's stages

    reverse = np.asarray(eqx.filter_jit(jax.grad(objective))(y, frame_data))
    forward = np.asarray(eqx.filter_jit(jax.grad(through_forward_mode))(y, frame_data))
    differenced = np.zeros(len(y), bool)
    differenced[list(problem.stage_unknowns(type(start).DIFFERENCED_STAGES))] = True
    derived = np.abs(forward - reverse)[~differenced].max() / np.abs(reverse).max()
    errors = np.abs(forward - reverse)[differenced] / np.maximum(np.abs(reverse[differenced]), 1e-30)
    return len(y), float(derived), float(errors.max()) if errors.size else math.nan


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("scenes", nargs="*", help=f"default: all of {', '.join(BY_NAME)}")
    parser.add_argument("--tolerance", type=float, default=1e-4, help="the relative difference allowed: %(default)s")
    args = parser.parse_args()
    scenes = [BY_NAME[name] for name in args.scenes] if args.scenes else list(SCENES)
    print("| scene | unknowns | derivatives: max abs(forward - reverse) / max abs(reverse) | differenced columns: max "
          "abs(forward - reverse) / abs(reverse) |")  # fmt: skip
    print("|---|---|---|---|")
    beyond = []
    for scene in scenes:
        count, difference, differenced = relative_difference(scene)
        print(f"| {scene.name} | {count} | {difference:.1e} | {differenced:.1e} |", flush=True)
        # Each scene's programs are compiled for it alone: dropped, so that the process's code maps stay within
        # Linux's limit (`vm.max_map_count`; LLVM cannot allocate its next program past it).
        jax.clear_caches()
        if difference > args.tolerance:
            beyond.append(scene.name)
    if beyond:
        print(f"beyond {args.tolerance:g}: {', '.join(beyond)}", file=sys.stderr)
        raise SystemExit(1)


if __name__ == "__main__":
    main()
