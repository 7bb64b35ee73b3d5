"""Frames without depth: `Buffers` for a photograph or a plate, the open sky drawn from the frame's bright parts.

Blender's Sun Beams node and Nuke's GodRays blur any image toward the light;
the shaft presets here read the open sky from the frame's coverage instead.
A frame without depth gets its coverage from its alpha where it has one
(a keyed plate: transparent where the light comes through), else from its
bright parts around the light (`masks.bright_sky`), so every preset whose
effect does not measure distance (`base.needs_depth`) runs on any image.
"""

import jax.numpy as jnp
from jaxtyping import ArrayLike, Float

from godrays_jax.effects.glow import LUMINANCE
from godrays_jax.kernels.masks import bright_sky
from godrays_jax.primitives.buffers import Buffers
from godrays_jax.primitives.checks import check_light

SKY_THRESHOLD = 0.5
"""Open sky by default: brighter than the geometric mean of the dark and bright ends around the light (`masks.bright_sky`)."""


def buffers_without_depth(
    color: Float[ArrayLike, "H W C"],
    light_xy: Float[ArrayLike, "2"],
    *,
    alpha: Float[ArrayLike, "H W"] | None = None,
    sky_threshold: float = SKY_THRESHOLD,
    softness: float = 0.2,
    window: float = 0.15,
) -> Buffers:
    """A frame without depth as `Buffers` (`depth=None`) whose coverage marks what hides the light.

    Args:
        color: linear colour `(H, W, 3)` (a 4th channel is dropped: pass it as `alpha`).
        light_xy: the light's pixel position (x right, y down; anywhere, on or off screen).
        alpha: the frame's coverage in [0, 1] where it has an alpha channel;
            used as coverage unless it is 1 everywhere (an opaque photograph).
        sky_threshold, softness, window: the bright pass (`masks.bright_sky`):
            a pixel is open sky when its luminance lies above `sky_threshold`
            of the way (on a log scale) from the dark to the bright end of
            the luminance within `window` (a fraction of the frame's larger
            side) of the light, with a smooth ramp `softness` wide.

    Returns:
        `Buffers(color, depth=None, coverage)`: coverage 1 on what hides the
        light, 0 on open sky.
    """
    light_xy = jnp.asarray(check_light(light_xy), jnp.float32)  # bounded before float32 could overflow
    color = jnp.asarray(color)
    if color.ndim != 3 or color.shape[-1] not in (3, 4):
        raise ValueError(f"color must have shape (H, W, 3), got {color.shape}")
    color = color[..., :3]
    if alpha is not None:
        alpha = jnp.clip(jnp.asarray(alpha, color.dtype), 0.0, 1.0)
        if alpha.shape != color.shape[:2]:
            raise ValueError(f"alpha must have shape {color.shape[:2]}, got {alpha.shape}")
        if bool(jnp.any(alpha < 1.0)):
            return Buffers(color=color, depth=None, coverage=alpha)
    luminance = jnp.tensordot(color, jnp.asarray(LUMINANCE, color.dtype), 1, precision="highest")
    sky = bright_sky(luminance, light_xy, threshold=sky_threshold, softness=softness, window=window)
    return Buffers(color=color, depth=None, coverage=(1.0 - sky).astype(color.dtype))

