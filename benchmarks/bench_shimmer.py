"""Shimmer of the shaft presets on a slow camera pan: how much their error against a converged version changes per frame.

    python benchmarks/bench_shimmer.py [--size 320x180] [--frames 12] [--pan 0.35] [--oversample 32] [--fog-oversample 4]
        [--presets a,b] [--method fast] [--same-target] [--cache FILE] [--converged DIR] [--maps DIR]

The shipped forest (examples/scenes/forest_hero.json) is rendered by the
project's rasterizer at `--size` for `--frames` frames while the camera turns
about its vertical axis by `--pan` pixels per frame at the image centre (the
scene, the sun and its shafts slide sideways; the pixel grid stays). Every
shaft preset (every preset of `GodRays`, `FlareOuts`, `ScatteringFog` and
`VolumetricFog`) is applied at its defaults, with the light's pixel position
and distance as `render` stores them and the camera's field of view and clip
planes (as `apply` reads them from the frame), and so is its converged version:

- the same effect with every sample of its loop replaced by `--oversample`
  (K) samples spread over the sample's interval: `num_samples` (or
  `num_iters`) times K, `decay` (`copy_decay`, `scale_step`) to the power
  1/K, `weight` (`intensity`) divided by K, the exact loop
  (`method="exact"`) at full resolution (`resolution_factor=1`); the other
  fields as they are (`--same-target`: flare-outs stay in the effect's own
  low-resolution target, so only their copies are oversampled). Its weights
  are the same continuous density along the ray sampled K times as densely,
  so its only departure from the effect's own integral is the sampling;
- for `VolumetricFog`, `--fog-oversample` times its view steps and shadow
  samples, its march at full resolution (`resolution_factor=1`), its shadows
  read from samples toward the light (`shadows="samples"`): for an effect
  that reads them along lines through the light (`volumetric_haze`), the
  converged version of the same model read the other way, so that it shares
  none of the effect's own discretisation.

Both are encoded as `apply` writes a PNG (linear colour clipped to [0, 1],
sRGB-encoded, times 255), kept unrounded so that rounding does not hide or
add change. For each frame the error is `effect - converged` in these codes;
the table gives, per preset, the RMS over pixels, channels and frame pairs of
the error's change from one frame to the next, and its 99th percentile in
absolute value, plus the RMS of the error itself. The target: at most 0.3 RMS
and 1.5 codes at the 99th percentile.

`--converged DIR` keeps each converged version's codes in `DIR` (one file per
sequence and converged effect, named by a hash of both) and reads them back on
the next run: a change to an effect's kernel is then measured in seconds
(the effect's own frames), not in the minutes the converged version takes, as
long as the change leaves the converged version alone (for `VolumetricFog`:
its full-resolution march, `resolution_factor=1`). Remove `DIR` after a change
that reaches it.

`--maps DIR` writes, per preset, `DIR/NAME.png` (8-bit grey, the codes
proportional to the values): on the left the RMS over frame pairs and channels of the error's
change at each pixel, on the right the middle frame's error (grey zero,
lighter +, darker -), with their scales printed: where the shimmer lives.
"""

import argparse
import dataclasses
import hashlib
import json
import math
import os
import pickle
import time
from pathlib import Path
from unittest import mock

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import godrays_jax as gr
from godrays_jax.raster import light_distance
from godrays_jax.app.options import with_field_of_view
from godrays_jax.effects.fog import ScatteringFog
from godrays_jax.effects.volumetric import VolumetricFog
from godrays_jax.effects.presets import PRESETS
from godrays_jax.effects.serialization import effect_to_dict
from godrays_jax.effects.shafts import FlareOuts, GodRays

SCENE = Path(__file__).resolve().parent.parent / "examples" / "scenes" / "forest_hero.json"
TARGET_RMS, TARGET_P99 = 0.3, 1.5


def pan_cameras(camera: gr.Camera, *, width: int, height: int, frames: int, pan_px: float) -> list[gr.Camera]:
    """The scene's camera at `width x height`, turned about the world's up axis by `pan_px` pixels (at the centre) per frame."""
    focal = 0.5 * width / math.tan(math.radians(float(camera.fov_x_deg)) / 2)
    position = np.asarray(camera.position, np.float64)
    forward = np.asarray(camera.target, np.float64) - position
    cameras = []
    for frame in range(frames):
        angle = math.atan(pan_px / focal) * (frame - (frames - 1) / 2)
        cosine, sine = math.cos(angle), math.sin(angle)
        turned = np.array([cosine * forward[0] + sine * forward[2], forward[1], -sine * forward[0] + cosine * forward[2]])
        cameras.append(eqx.tree_at(lambda c: c.target, camera, jnp.asarray(position + turned, jnp.float32)))
    return [
        gr.Camera(position=c.position, target=c.target, up=c.up, fov_x_deg=c.fov_x_deg, width=width, height=height,
                  near=c.near, far=c.far)  # fmt: skip
        for c in cameras
    ]


def render_pan(*, width: int, height: int, frames: int, pan_px: float) -> list:
    """`(buffers, light_xy, in_front, light_depth)` of every frame of the pan."""
    scene, camera = gr.load_scene(SCENE)
    rendered = []
    for cam in pan_cameras(camera, width=width, height=height, frames=frames, pan_px=pan_px):
        xy, _, in_front = gr.light_pixel(scene, cam)
        rendered.append((gr.render(scene, cam), np.asarray(xy), bool(in_front), light_distance(scene, cam)))
    return rendered


def cached_pan(cache: str | None, key: tuple) -> list:
    """`render_pan` of `key` (width, height, frames, pan), read from the file `cache` when it holds that sequence."""
    if cache and os.path.exists(cache):
        with open(cache, "rb") as stream:
            cached_key, frames = pickle.load(stream)
        if cached_key != key:
            raise SystemExit(f"{cache} holds another sequence {cached_key}; remove it")
        return frames
    width, height, count, pan = key
    frames = render_pan(width=width, height=height, frames=count, pan_px=pan)
    if cache:
        with open(cache, "wb") as stream:
            pickle.dump((key, jax.device_get(frames)), stream)
    return frames


def shaft_presets() -> list[str]:
    """Every preset whose effect draws shafts."""
    shaft_classes = tuple(
        cls for cls in (GodRays, FlareOuts, ScatteringFog, VolumetricFog, getattr(gr, "VolumetricShafts", None))
        if cls is not None
    )
    return [name for name, make in PRESETS.items() if isinstance(make(), shaft_classes)]


def _replace(effect, **values):
    """`effect` with the named fields replaced (fields it lacks are skipped: names differ between versions); unchecked."""
    names = [name for name in values if hasattr(effect, name)]
    return eqx.tree_at(lambda e: [getattr(e, n) for n in names], effect, [values[n] for n in names])


def converged(effect, oversample: int, *, same_target: bool = False, fog_oversample: int = 4):
    """The effect with every sample of its loop spread over `oversample` samples (see the module's docstring).

    `same_target`: flare-outs stay in the effect's own (low-resolution) target. `VolumetricFog` takes
    `fog_oversample` times its view steps and shadow samples, at full resolution, its shadows from samples.
    """
    k = oversample
    if isinstance(effect, VolumetricFog):
        changed = effect
        static = dict(
            num_view_steps=effect.num_view_steps * fog_oversample,
            num_shadow_samples=effect.num_shadow_samples * fog_oversample, resolution_factor=1, shadows="samples",
        )  # fmt: skip
    elif isinstance(effect, FlareOuts):
        count = int(round(float(effect.num_iters))) * k
        changed = _replace(
            effect, num_iters=float(count), scale_step=effect.scale_step ** (1.0 / k),
            copy_decay=effect.copy_decay ** (1.0 / k), intensity=effect.intensity / k,
        )  # fmt: skip
        static = dict(max_iters=count) if same_target else dict(max_iters=count, resolution_factor=1)
    else:
        count = int(round(float(effect.num_samples))) * k
        values = dict(num_samples=float(count), decay=effect.decay ** (1.0 / k))
        if isinstance(effect, GodRays):
            values["weight"] = effect.weight / k
        changed = _replace(effect, **values)
        static = dict(max_samples=count, method="exact", resolution_factor=1)
    static = {name: value for name, value in static.items() if hasattr(changed, name)}
    # Loops longer than a user may ask for: the ranges bound what fits, the tuner and params files set.
    with (
        mock.patch("godrays_jax.effects.fields._check_static"),
        mock.patch("godrays_jax.effects.fields._check_fittable"),
    ):
        return dataclasses.replace(changed, **static)


def display_codes(image) -> np.ndarray:
    """Colour as `apply` writes it to an 8-bit PNG, before rounding: `srgb_encode(clip(x, 0, 1)) * 255`."""
    return np.asarray(gr.srgb_encode(np.asarray(image, np.float64)[..., :3])) * 255.0


def shimmer(errors: list[np.ndarray]) -> tuple[float, float, float]:
    """(RMS of the frame-to-frame change, its 99th percentile of |change|, RMS of the error)."""
    stack = np.stack(errors)
    change = np.diff(stack, axis=0)
    return (
        float(np.sqrt(np.mean(change**2))),
        float(np.percentile(np.abs(change), 99)),
        float(np.sqrt(np.mean(stack**2))),
    )


def change_map(errors: list[np.ndarray]) -> np.ndarray:
    """Per pixel, the RMS over frame pairs and channels of the error's change from one frame to the next."""
    change = np.diff(np.stack(errors), axis=0)
    return np.sqrt(np.mean(change**2, axis=(0, -1)))


def write_maps(path: Path, errors: list[np.ndarray]) -> float:
    """`change_map` beside the middle frame's error (grey zero), side by side on one scale; returns the scale (codes)."""
    change = change_map(errors)
    error = np.mean(errors[len(errors) // 2], axis=-1)
    scale = max(float(np.percentile(change, 99.9)), 1e-6)
    left = np.clip(change / scale, 0.0, 1.0)
    right = np.clip(0.5 + 0.5 * error / (4 * scale), 0.0, 1.0)
    gap = np.ones((change.shape[0], 4))
    picture = np.concatenate([left, gap, right], axis=1)
    # write_image sRGB-encodes a PNG's colour: decode first, so the file's codes are the picture's values.
    gr.write_image(path, np.asarray(gr.srgb_decode(np.repeat(picture[..., None], 3, axis=-1)), np.float32))
    return scale


def converged_codes(folder: str | None, key: tuple, reference, run_reference, frames) -> list[np.ndarray]:
    """`display_codes` of the converged version on every frame, read from `folder` when it holds them."""
    def compute():
        return [display_codes(run_reference(buffers, xy, in_front, depth)) for buffers, xy, in_front, depth in frames]

    if folder is None:
        return compute()
    described = json.dumps([list(key), effect_to_dict(reference)], sort_keys=True, default=str)
    path = Path(folder) / f"converged-{hashlib.sha256(described.encode()).hexdigest()[:16]}.npy"
    if path.exists():
        return list(np.load(path))
    codes = compute()
    path.parent.mkdir(parents=True, exist_ok=True)
    np.save(path, np.stack(codes))
    return codes


def with_camera(effect, camera: gr.Camera):
    """The effect with the camera's field of view and clip planes, as `apply` gives it those of a frame `render` wrote."""
    effect = with_field_of_view(effect, float(camera.fov_x_deg))
    if {"near_plane", "far_plane"} <= {field.name for field in dataclasses.fields(effect)}:
        effect = dataclasses.replace(effect, near_plane=float(camera.near), far_plane=float(camera.far))
    return effect


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="320x180", help="WIDTHxHEIGHT (default 320x180)")
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--pan", type=float, default=0.35, help="pixels per frame at the image centre (default 0.35)")
    parser.add_argument("--oversample", type=int, default=32, help="samples of the converged version per sample")
    parser.add_argument("--fog-oversample", type=int, default=4, help="VolumetricFog's view steps and shadow samples x this")
    parser.add_argument("--presets", default=None, help="comma-separated presets (default: every shaft preset)")
    parser.add_argument("--method", default=None, help="also measure GodRays presets with this method (e.g. fast)")
    parser.add_argument("--same-target", action="store_true", help="converged flare-outs stay in the effect's target")
    parser.add_argument("--cache", default=None, help="keep the rendered frames in this file and reuse them")
    parser.add_argument("--converged", default=None, help="keep the converged versions' codes in this folder")
    parser.add_argument("--maps", default=None, help="write per preset a picture of where the error changes to this folder")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    started = time.perf_counter()
    key = (width, height, args.frames, args.pan)
    frames = cached_pan(args.cache, key)
    rendered = time.perf_counter() - started
    print(f"{args.frames} frames of {width}x{height} in {rendered:.1f} s; "
          f"light x {float(frames[0][1][0]):.2f} .. {float(frames[-1][1][0]):.2f} px")  # fmt: skip

    camera = gr.load_scene(SCENE)[1]
    cases = []
    for name in args.presets.split(",") if args.presets else shaft_presets():
        effect = with_camera(PRESETS[name](), camera)
        cases.append((name, effect))
        if args.method and isinstance(effect, GodRays) and effect.method != args.method:
            cases.append((f"{name} (method={args.method})", dataclasses.replace(effect, method=args.method)))
    print(f"| preset | change RMS | change p99 | error RMS | within target |")
    print(f"|---|---|---|---|---|")
    for name, effect in cases:
        reference = converged(effect, args.oversample, same_target=args.same_target, fog_oversample=args.fog_oversample)
        run = jax.jit(lambda b, xy, front, depth, e=effect: e(b, xy, light_in_front=front, light_depth=depth), static_argnums=(2, 3))
        run_reference = jax.jit(lambda b, xy, front, depth, e=reference: e(b, xy, light_in_front=front, light_depth=depth), static_argnums=(2, 3))
        expected = converged_codes(args.converged, key, reference, run_reference, frames)
        errors = [display_codes(run(buffers, xy, in_front, depth)) - codes
                  for (buffers, xy, in_front, depth), codes in zip(frames, expected)]  # fmt: skip
        rms, p99, error = shimmer(errors)
        ok = "yes" if rms <= TARGET_RMS and p99 <= TARGET_P99 else "no"
        print(f"| {name} | {rms:.2f} | {p99:.2f} | {error:.2f} | {ok} |", flush=True)
        if args.maps:
            Path(args.maps).mkdir(parents=True, exist_ok=True)
            picture = Path(args.maps) / f"{name.replace(' ', '_')}.png"
            scale = write_maps(picture, errors)
            print(f"  {picture}: white {scale:.2f} codes of change RMS (left); white/black +-{4 * scale:.2f} codes of error (right)")
    print(f"total {time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
