"""A Blender reference against the same scene with light scattered once in the medium: what the second order adds.

    python benchmarks/references/render_blender.py NAME --samples 1024 --threads 2 --volume-bounces 0 --out DIR
    python benchmarks/scattering_orders.py cycles_NAME --single DIR [--fit]

The first command renders the scene with Cycles' one bounce in the medium left out (light bounced off a surface
into the medium stays). Printed, in the display space of the fit's loss (`x / (1 + |x|)`):

- both noise floors, and the share of the frame's light (linear) that the bounce in the medium adds;
- the stand-in a screen-space model could take for that bounce: the renders' light scattered once, less the clean
  frame dimmed by the scene's medium, blurred by a Gaussian of each width, times a weight plus a constant (least
  squares against the bounce itself), added to the once-scattered renders: each sum against fog A and B as a
  ratio to the reference's floor, the best that such a term reaches even on the true light scattered once;
- `--fit`: `godrays-jax fit` of the once-scattered fog A with its defaults (the reference's light and light view),
  `apply --params`, as ratios to the once-scattered renders' own floor: how far the model is from light scattered
  once alone.
"""

import argparse
import math
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
from scipy.ndimage import gaussian_filter

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / "references"))
from baseline import display_mse, light_options, read_rgb  # noqa: E402  (the references' folder joins the path first)
from scenes import BY_NAME  # noqa: E402

BLUR_PX = (3, 5, 8, 10, 14, 20)


def _distance_along_rays(path: Path, fov_x_deg: float) -> np.ndarray:
    """Blender's planar `Z` of the clean frame as the distance along each pixel's ray."""
    buffer = oiio.ImageBuf(str(path))
    names = buffer.spec().channelnames
    z = buffer.get_pixels(oiio.FLOAT)[..., names.index("ViewLayer.Depth.Z")].astype(np.float64)
    height, width = z.shape
    focal = (width / 2) / math.tan(math.radians(fov_x_deg) / 2)
    rows, cols = np.mgrid[:height, :width] + 0.5
    return z * np.sqrt(((cols - width / 2) / focal) ** 2 + ((rows - height / 2) / focal) ** 2 + 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("scene", help="a Blender reference, e.g. cycles_window_ahead")
    parser.add_argument("--single", type=Path, required=True, help="the folder of the once-scattered renders")
    parser.add_argument("--fit", action="store_true", help="also fit the once-scattered fog A with fit's defaults")
    args = parser.parse_args()
    scene = BY_NAME[args.scene]
    stem = scene.clean.name.replace("_clean.exr", "")
    fog_a, fog_b = read_rgb(scene.fog_a), read_rgb(scene.fog_b)
    single_a, single_b = (read_rgb(args.single / f"{stem}_fog_{seed}.exr") for seed in "ab")
    floor, single_floor = scene.noise_floor, display_mse(single_a, single_b) / 2
    both, single = (fog_a + fog_b) / 2, (single_a + single_b) / 2
    bounce = both - single
    print(f"{args.scene}: floor {floor:.3g}, once scattered {single_floor:.3g}; the bounce in the medium adds "
          f"{bounce.mean() / both.mean():.1%} of the light; the once-scattered renders against fog A: "
          f"{display_mse(single, fog_a) / floor:.2f} of the floor")  # fmt: skip

    sigma_t, reach = scene.medium["sigma_t"], float(scene.medium["extent"].split("radius ")[1].split()[0])
    distance = np.minimum(_distance_along_rays(scene.clean, scene.fov_x_deg), reach)
    dimmed = read_rgb(scene.clean) * np.exp(-sigma_t * distance)[..., None]
    scattered = single - dimmed
    print("| blur px | weight | constant | once scattered + blurred / floor (fog A, B) |")
    print("|---|---|---|---|")
    for px in BLUR_PX:
        blurred = gaussian_filter(scattered, (px, px, 0))
        basis = np.stack([blurred.ravel(), np.ones(blurred.size)], 1)
        (weight, constant), *_ = np.linalg.lstsq(basis, bounce.ravel(), rcond=None)
        model = single + weight * blurred + constant
        print(f"| {px} | {weight:.3f} | {constant:.2e} | {display_mse(model, fog_a) / floor:.2f}, "
              f"{display_mse(model, fog_b) / floor:.2f} |")  # fmt: skip

    if args.fit:
        light_view = scene.clean.with_name(f"{stem}_light_view.exr")
        options = light_options(scene) + (["--light-view", str(light_view)] if light_view.exists() else [])
        with tempfile.TemporaryDirectory() as folder:
            params, output = Path(folder) / "params.json", Path(folder) / "out.exr"
            target = args.single / f"{stem}_fog_a.exr"
            for command in (["fit", str(scene.clean), str(target), "-o", str(params)],
                            ["apply", str(scene.clean), "--params", str(params), "-o", str(output)]):  # fmt: skip
                subprocess.run(["godrays-jax", *command, *options], check=True, capture_output=True)
            fitted = read_rgb(output)
        print(f"fit of the once-scattered fog A: {display_mse(fitted, single_a) / single_floor:.2f}, "
              f"{display_mse(fitted, single_b) / single_floor:.2f} of its floor")  # fmt: skip


if __name__ == "__main__":
    main()
