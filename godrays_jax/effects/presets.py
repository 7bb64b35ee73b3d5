"""Presets: one effect per source article, with that article's constants (`PRESETS`, `preset`)."""

from typing import Any

from godrays_jax.effects.base import Effect
from godrays_jax.effects.fog import ScatteringFog
from godrays_jax.effects.glow import Bloom, LensDirt, SunOvercast, SunSpot
from godrays_jax.effects.shafts import FlareOuts, GodRays
from godrays_jax.kernels.lens import LENS_DIRT_ABERRATION


def _xna_crepuscular() -> GodRays:
    """The XNA crepuscular-rays article: 128 samples, density .5, decay .95, weight 1, exposure .15, bright pass, additive."""
    # The XNA crepuscular-rays article leaves the flare size (SunSize / z), the bright-pass threshold and
    # the colour open: with decay .95 the shafts reach only ~8 % of the way to the
    # light, so the disc must reach the occluders (120 px on a 320 px frame), and
    # a warm tint below 1 keeps the saturated core from washing the silhouettes out.
    return GodRays(
        density=0.5, decay=0.95, weight=1.0, exposure=0.15, threshold=0.25, num_samples=128.0,
        max_samples=128, light_radius=120.0, tint=(0.8, 0.7, 0.5), source="disc", use_bright_pass=True,
        blend_mode="add",
    )  # fmt: skip


def _galaxy_vls() -> GodRays:
    """The galaxy-engine VLS article: light white and occluders black, 200 samples, density 1, decay .98, exposure .05, additive."""
    return GodRays(
        density=1.0, decay=0.98, weight=1.0, exposure=0.05, num_samples=200.0, max_samples=200,
        source="light_pass", use_bright_pass=False, blend_mode="add",
    )  # fmt: skip


def _kbengine_flares() -> FlareOuts:
    """KbEngine's article: kbEngine3's 20 flare-outs scaled x1.03 each, blurred against banding, added."""
    return FlareOuts(scale_step=1.03, num_iters=20.0, max_iters=20, intensity=0.1, blur_sigma=2.0)


def _sun_overcast() -> SunOvercast:
    """The sun-overcasting article: orange (0.8, 0.5, 0, 0.65) glow, two Poisson-blur passes, additive."""
    # The halo size and the occluders' shrink (x1.3 / x0.8 of objects in the seed) are
    # open in image space: a 45 px halo and 2 px of seeping read as the article's picture.
    return SunOvercast(
        blur_power=0.015, glow_color=(0.8, 0.5, 0.0, 0.65), passes=2.0, max_passes=2, source_radius=45.0,
        occluder_shrink=2.0,
    )  # fmt: skip


def _vbex_lens_dirt() -> LensDirt:
    """The VBex article: power 20, scale 2, chromatic offset 0.002, warm sun colour, added."""
    return LensDirt(power=20.0, scale=2.0, aberration=LENS_DIRT_ABERRATION, sun_color=(1.0, 0.8, 0.55))


def _vbex_sun_spot() -> SunSpot:
    """The VBex article: `pow(dot, SunDistance * 2000) * SunSharpness * 30` on the sky, bloomed through the glow target."""
    return SunSpot(sun_distance=1.0, sun_sharpness=1.0, sun_color=(1.0, 0.85, 0.6), glow_intensity=0.5)


def _vbex_bloom() -> Bloom:
    """The VBex article: bright pass, blurs at 1/2, 1/4, 1/8, 1/16 resolution added with equal weights."""
    return Bloom(threshold=1.0, weights=(1.0, 1.0, 1.0, 1.0), intensity=0.25, method="pyramid")


def _gaussian_bloom() -> Bloom:
    """The single large Gaussian that the VBex article's pyramid replaces, for comparison."""
    return Bloom(threshold=1.0, gaussian_sigma=12.0, gaussian_radius=36, intensity=1.0, method="gaussian")


def _participating_media() -> ScatteringFog:
    """A light haze: no source article; physically motivated defaults, not tuned to any reference frame."""
    # Mie haze has g ~ 0.76; extinction 0.01 per unit leaves 37 % of the light after
    # 100 units; a bluish ambient (sky light) and a warm sun; the medium ends at 100 units.
    return ScatteringFog(
        extinction=0.01, max_distance=100.0, anisotropy=0.76, ambient=(0.05, 0.06, 0.08),
        sun_irradiance=(1.0, 0.9, 0.75), fov_x_deg=50.0, shaft_strength=1.0, density=1.0, decay=0.97,
        num_samples=32.0, max_samples=32,
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
}
"""Preset name -> a function making that effect with the source article's constants."""


def preset(name: str) -> Effect:
    """A fresh effect with the constants of the named source article (see `PRESETS`)."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of: {', '.join(sorted(PRESETS))}")
    return PRESETS[name]()


