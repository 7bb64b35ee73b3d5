"""Presets: one effect per source article, with that article's constants (`PRESETS`, `preset`)."""

from typing import Any

from godrays_jax.effects.base import Effect, needs_depth
from godrays_jax.effects.fog import ScatteringFog
from godrays_jax.effects.volumetric import VolumetricFog
from godrays_jax.effects.glow import Bloom, BloomBlur, LensDirt, SunOvercast, SunSpot
from godrays_jax.effects.medium import Medium
from godrays_jax.effects.shafts import FlareOuts, GodRays
from godrays_jax.kernels.lens import LENS_DIRT_ABERRATION


def _xna_crepuscular() -> GodRays:
    """The XNA crepuscular-rays article's five passes: flare `2 * pow(tex, 2)` sized `SunSize / z` (SunSize 1500),
    hardware-depth test with bias .00025, rays (128 samples, density .5 with its step clamp on clip-space z,
    decay .95, weight 1, exposure .15), bright pass, additive blend."""
    # Ours, as the article leaves them open: the flare texture (a glow with a small bright
    # core: the rays' gain of about 3 saturates only that core), the bright-pass threshold
    # (its slider) and a warm tint (the article's flare texture is coloured). The clip planes
    # are XNA_NEAR_PLANE (its author's sample camera's) and XNA_FAR_PLANE (ours): the article prints none.
    return GodRays(
        density=0.5, decay=0.95, weight=1.0, exposure=0.15, threshold=0.1, num_samples=128.0, max_samples=128,
        sun_size=1500.0, flare_sizing="clip_depth", tint=(1.0, 0.85, 0.6), depth_bias=0.00025, source="disc",
        scene_mask="depth", step_clamp=True, use_bright_pass=True, blend_mode="add",
    )  # fmt: skip


def _galaxy_vls() -> GodRays:
    """The galaxy-engine VLS article: light white and occluders black, 200 samples, density 1, decay .98, exposure .05, additive."""
    return GodRays(
        density=1.0, decay=0.98, weight=1.0, exposure=0.05, num_samples=200.0, max_samples=200,
        source="light_pass", use_bright_pass=False, blend_mode="add",
    )  # fmt: skip


def _kbengine_flares() -> FlareOuts:
    """KbEngine's article: a flare texture masked by `1 - sign(depth)`, flare-outs drawn from that full-resolution
    texture into a low-resolution target, blurred against banding, added; 20 copies scaled x1.03 each are
    kbEngine3's code, not the article's."""
    # Ours: the flare (procedural, 0.3 UV), the target at half resolution ("low-res"),
    # the intensity and the blur (sigma 1.25 % of the frame's larger side, two pixels of the
    # target at 320 wide): the target's grid stays fixed while the scene slides under it, and
    # a blur of one target pixel left detail that changed with the scene's phase on that grid
    # (benchmarks/bench_shimmer.py).
    return FlareOuts(
        scale_step=1.03, num_iters=20.0, max_iters=20, intensity=0.1, flare_size=0.3, blur_sigma=0.0125,
        blur_reach=0.0375, resolution_factor=2, scene_mask="sky",
    )  # fmt: skip


def _sun_overcast() -> SunOvercast:
    """The sun-overcasting article: orange (0.8, 0.5, 0, 0.65) glow, two Poisson-blur passes, additive."""
    # The halo size and the occluders' shrink (x1.3 / x0.8 of objects in the article) are
    # open in image space (frames without the rendered glow pass): a halo of 14 % of the
    # frame's larger side and 0.6 % of seeping read as the article's picture.
    return SunOvercast(
        blur_power=0.015, tint=(0.8, 0.5, 0.0, 0.65), num_passes=2.0, max_passes=2, source_radius=0.140625,
        occluder_shrink=0.00625,
    )  # fmt: skip


def _vbex_lens_dirt() -> LensDirt:
    """The VBex article: `pow(saturate(dot(view, L) * max(LDepth, .8)), 20) * 2` as printed, chromatic offset 0.002,
    the sun's colour, added."""
    # Ours: the dirt texture (procedural), `far_plane` (what LDepth divides by) and the tint (its SunColor).
    return LensDirt(
        power=20.0, scale=2.0, aberration=LENS_DIRT_ABERRATION, tint=(1.0, 0.8, 0.55), depth_floor=0.8,
        depth_in_power=True,
    )  # fmt: skip


def _vbex_sun_spot() -> SunSpot:
    """The VBex article: `pow(dot, SunDistance * 2000) * SunSharpness * 30` on the sky, bloomed through the glow target."""
    return SunSpot(
        sun_distance=1.0, sun_sharpness=1.0, tint=(1.0, 0.85, 0.6),
        bloom=BloomBlur(intensity=1.0, blur_sigma=0.0125, blur_reach=0.0375),
    )  # fmt: skip


def _vbex_bloom() -> Bloom:
    """The VBex article: the glow target blurred at 1/2, 1/4, 1/8, 1/16 resolution, added with equal weights."""
    # Ours: the blur (1.25 % of the frame's larger side at the finest level), the intensity,
    # and for frames without a glow target, the luminance threshold.
    return Bloom(
        threshold=1.0, weights=(1.0, 1.0, 1.0, 1.0), intensity=0.25, blur_sigma=0.0125, blur_reach=0.0375,
        method="pyramid", bloom_source="glow_target",
    )  # fmt: skip


def _gaussian_bloom() -> Bloom:
    """The single large Gaussian that the VBex article's pyramid replaces, for comparison."""
    return Bloom(
        threshold=1.0, wide_blur_sigma=0.0375, wide_blur_reach=0.1125, intensity=1.0, method="gaussian",
        bloom_source="glow_target",
    )  # fmt: skip


def _participating_media() -> ScatteringFog:
    """A light haze: no source article; physically motivated defaults, not tuned to any reference frame."""
    # Mie haze has g ~ 0.76; extinction 0.01 per unit leaves 37 % of the light after
    # 100 units; a bluish ambient (sky light) and a warm sun; the medium ends at 100 units.
    # 128 samples, the shadow's falloff of 32 samples at decay .97 (.97 per 4 samples): fewer
    # step over thin occluders, and the shafts shimmer as the camera moves.
    return ScatteringFog(
        medium=Medium(
            extinction=0.01, max_distance=100.0, anisotropy=0.76, light_color=(1.0, 0.9, 0.75),
            ambient_color=(0.05, 0.06, 0.08),
        ),
        fov_x_deg=50.0, shadow_strength=1.0, density=1.0, decay=0.97**0.25, num_samples=128.0, max_samples=128,
    )  # fmt: skip



def _volumetric_haze() -> VolumetricFog:
    """A light haze lit segment by segment: no source article; the defaults `participating_media` has, in `VolumetricFog`.

    Extinction 0.01 per unit (37 % of the light left after 100 units), Mie-like forward scattering
    (g .76), a bluish ambient and a warm sun, the medium a ball of 100 units around the camera without
    a top; half of the frame's surface light taken to be direct sunlight, dimmed on its way in; the
    depth buffer's surfaces 15 % of their depth thick.
    """
    return VolumetricFog(
        medium=Medium(
            extinction=0.01, max_distance=100.0, anisotropy=0.76, light_color=(1.0, 0.9, 0.75),
            ambient_color=(0.05, 0.06, 0.08),
        ),
        direct_fraction=0.5, thickness=0.15, edge_softness=0.05, fov_x_deg=50.0, shadows="lines", resolution_factor=1,
    )  # fmt: skip

# Presets beyond the articles: the looks people expect from a light-shaft library. The articles'
# own constants reach only a short way toward the light by design; these two reach across the frame.

BABYLON_SAMPLE_SCALE = 0.4
"""Babylon.js' volumetric-light-scattering shader scales every sample (the first included) by 0.4 before its weights."""


GPU_GEMS_SAMPLE_SPREAD = 2
"""`gpu_gems` spreads each of Babylon's 100 samples over this many (see `_gpu_gems`)."""


def _gpu_gems() -> GodRays:
    """GPU Gems 3 ch. 13's loop with the constants everyone copies: long shafts fanning across the frame.

    100 samples, density .926, decay .96815, weight .58767, exposure .3: the defaults of Babylon.js'
    `VolumetricLightScatteringPostProcess` (BabylonJS/Babylon.js,
    packages/dev/core/src/PostProcesses/volumetricLightScatteringPostProcess.ts). Its fragment shader
    (Shaders/volumetricLightScattering.fragment.fx) runs the chapter's loop and also scales every
    sample by 0.4, folded into `exposure` here (its extra x1.1 on the frame is left out). The same
    values are in the widely copied GLSL ports of the chapter's Listing 13-1, which names Density,
    Weight, Decay and Exposure but prints no values. Each pixel's samples run 92.6 % of the way to
    the light, and the last one still weighs .96815**100 = 4 % of the first.

    Ours, not Babylon's: the emitter and the sample count. Babylon draws a small sun billboard, which
    through occluders gives a halo; shafts need an emitter that occluders cut into wedges, so here the
    open sky shines, brightest at the sun and fading to nothing a frame width sideways and a frame
    height up and down (the cone flare `2 * saturate(1 - r)**2`, `flare_size` 1 UV, times the open
    sky; a uniformly bright sky would wash the frame out), in a warm tint. Babylon's 100 steps band
    visibly, and the bands crawl over the shafts as the camera moves: each of its samples is spread
    over `GPU_GEMS_SAMPLE_SPREAD` here (`num_samples` x2, `decay ** (1/2)`, `weight / 2`), the same shafts
    along the same 92.6 % of the way with half the step.
    """
    spread = GPU_GEMS_SAMPLE_SPREAD
    return GodRays(
        density=0.926, decay=0.96815 ** (1 / spread), weight=0.58767 / spread, exposure=0.3 * BABYLON_SAMPLE_SCALE,
        num_samples=100.0 * spread, max_samples=100 * spread, flare_size=1.0, flare_sizing="fixed", flare_shape="cone",
        tint=(0.3, 0.234, 0.165), source="disc", method="exact", blend_mode="add",
    )  # fmt: skip


def _physically_based() -> VolumetricFog:
    """`VolumetricFog` fitted to a path tracer's fog frame: haze lit segment by segment, in shadow behind the colonnade.

    Fitted (`benchmarks/fit_physically_based.py`: Levenberg-Marquardt on the display-space MSE from
    `volumetric_haze` alone, otherwise as `godrays-jax fit` runs, the field of view fixed at the camera's 50 degrees,
    the sun at infinity) to the Mitsuba 3 frames of a colonnade in a homogeneous medium (sigma_t .02
    per unit, albedo .95, Henyey-Greenstein g .8, a sphere of radius 40 around the camera); the
    frames live beside the checkout (`shared/data/colonnade_*`), so the constants are baked in and
    the script fits them again. The fitted extinction lands near the rendered medium's (.024 for .02);
    the medium reaches past the rendered sphere and scatters more forward, standing in for the light
    scattered more than once. Distances are in scene units; `fov_x_deg` is the colonnade camera's.
    It marches twice `volumetric_haze`'s view steps and four times its shadow samples, so that its thin slabs'
    shadows hold still on a moving camera (benchmarks/README.md, "Shimmer on a slow pan"). The constants are
    the fit of a9fff01's kernel; the script's fit on today's kernel lands on thicker slabs with sharper faces,
    a little closer to the colonnade and not as still on a pan (the same section): the preset keeps these.
    """
    return VolumetricFog(
        medium=Medium(
            extinction=0.02397, max_distance=111.34, anisotropy=0.9083, light_color=(1.7158, 1.2912, 0.7873),
            ambient_color=(0.0645, 0.0464, 0.0218),
        ),
        height_falloff=0.00047, direct_fraction=0.4998, thickness=0.0721, edge_softness=0.0552, fov_x_deg=50.0,
        num_view_steps=32, num_shadow_samples=128,
    )  # fmt: skip


PRESETS: dict[str, Any] = {
    "xna_crepuscular": _xna_crepuscular,
    "galaxy_vls": _galaxy_vls,
    "kbengine_flares": _kbengine_flares,
    "sun_overcast": _sun_overcast,
    "vbex_lens_dirt": _vbex_lens_dirt,
    "vbex_sun_spot": _vbex_sun_spot,
    "vbex_bloom": _vbex_bloom,
    "gaussian_bloom": _gaussian_bloom,
    "participating_media": _participating_media,
    "volumetric_haze": _volumetric_haze,
    "gpu_gems": _gpu_gems,
    "physically_based": _physically_based,
}
"""Preset name -> a function making that effect with the source article's constants (or, for
`gpu_gems` and `physically_based`, the constants their docstrings cite)."""


def preset(name: str) -> Effect:
    """A fresh effect with the constants of the named source article (see `PRESETS`)."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of: {', '.join(sorted(PRESETS))}")
    return PRESETS[name]()




def presets_without_depth() -> tuple[str, ...]:
    """The presets that run on a frame without depth (their effect does not measure distance: `base.needs_depth`)."""
    return tuple(sorted(name for name, make in PRESETS.items() if not needs_depth(make())))
