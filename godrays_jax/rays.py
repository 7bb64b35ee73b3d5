"""Radial light shafts: GPU Gems 3 radial rays (seeds 003, 004) and kbEngine flare-outs (seed 002).

All positions are pixels (x right, y down, pixel centres at `i + 0.5`). The light
may be anywhere: on screen, off screen or on a pixel centre; the kernels never
divide by the distance to it, so every case gives finite values and gradients.

Integer counts (`num_samples`, `num_iters`) accept a Python int (the exact
kernel) or a float / traced scalar with a static upper bound (the continuous
relaxation used for fitting); see each function for the relaxation.
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, ArrayLike

from godrays_jax._checks import checked_count, check_image, check_light, check_scalar, resolve_count
from godrays_jax.sampling import pixel_centres, sample_bilinear


def radial_rays(
    image: Float[Array, "H W C"],
    light_xy: Float[ArrayLike, "2"],
    *,
    num_samples: int | Float[ArrayLike, ""],
    density: Float[ArrayLike, ""],
    decay: Float[ArrayLike, ""],
    weight: Float[ArrayLike, ""],
    exposure: Float[ArrayLike, ""],
    max_samples: int | None = None,
) -> Float[Array, "H W C"]:
    """The GPU Gems 3 (ch. 13) radial-blur loop, exactly as seed 003 writes it.

    For each pixel centre `p`, with `delta = (p - light) * density / num_samples`:
    `exposure * (image(p) + sum_{i=1..n} weight * decay**(i-1) * image(p - i * delta))`,
    bilinear samples with clamp-to-edge addressing. With `density = 1` the last
    sample lands on the light; lights off screen read the clamped edge.

    Args:
        image: the occlusion image (light source bright, occluders black).
        light_xy: the light's position in pixels.
        num_samples: samples per pixel. A Python int >= 1 runs the exact loop.
            A float (or traced) value `n` is the continuous relaxation: the step
            uses `n` and sample `i` (i = 1..max_samples) is weighted by
            `clip(n - i + 1, 0, 1)`, so whole samples are in or out and the last
            one fades in; at integer `n` it equals the exact loop.
        density: fraction of the way to the light the samples cover.
        decay: per-sample falloff, usually in (0, 1].
        weight: per-sample weight.
        exposure: overall scale.
        max_samples: static loop length for a relaxed `num_samples`.

    Returns:
        The rays image, same shape and dtype as `image`.
    """
    check_image(image)
    check_light(light_xy)
    for name, value in (("density", density), ("decay", decay), ("weight", weight), ("exposure", exposure)):
        check_scalar(value, name)
    loop_length, relaxed = resolve_count(num_samples, max_samples, "num_samples", "max_samples")
    height, width, _ = image.shape
    dtype = image.dtype
    light_xy = jnp.asarray(light_xy, dtype)
    count = checked_count(num_samples, loop_length, "num_samples", "max_samples", dtype) if relaxed else jnp.asarray(num_samples, dtype)
    x, y = pixel_centres(height, width, dtype)
    step_x = (x - light_xy[0]) * (density / count)
    step_y = (y - light_xy[1]) * (density / count)

    def add_sample(i, carry):
        total, illumination = carry
        sample = sample_bilinear(image, x - i * step_x, y - i * step_y)
        sample_weight = illumination * weight
        if relaxed:
            sample_weight = sample_weight * jnp.clip(count - i + 1, 0.0, 1.0)
        return total + sample_weight * sample, illumination * decay

    total, _ = jax.lax.fori_loop(1, loop_length + 1, add_sample, (image, jnp.ones((), dtype)))
    return total * exposure


def scale_iterated_flares(
    masked: Float[Array, "H W C"],
    light_xy: Float[ArrayLike, "2"],
    *,
    num_iters: int | Float[ArrayLike, ""],
    scale_step: Float[ArrayLike, ""],
    decay: Float[ArrayLike, ""] = 1.0,
    max_iters: int | None = None,
) -> Float[Array, "H W C"]:
    """kbEngine's "flare-outs": the masked flare texture repeatedly scaled about the light.

    `sum_{k=0..n-1} decay**k * masked(light + (p - light) / scale_step**k)`: copy `k`
    is the texture enlarged `scale_step**k` times about the light, sampled
    bilinearly; texels outside the image are 0 (a copy never smears the border).
    Copy 0 is `masked` itself. The sum is not normalised (seed 002 adds every
    copy into its target); scale it in the effect.

    Args:
        masked: the masked flare texture (flare times sky mask).
        light_xy: the centre of scaling, in pixels; may be off screen.
        num_iters: copies. A Python int >= 1 is exact; a float `n` is the
            relaxation: copy `k` (k = 0..max_iters-1) weighted `clip(n - k, 0, 1)`,
            equal to the exact sum at integer `n`.
        scale_step: scale between successive copies (kbEngine3: 1.03). Values
            below 1 shrink the copies toward the light.
        decay: per-copy intensity factor.
        max_iters: static loop length for a relaxed `num_iters`.
    """
    check_image(masked, "masked")
    check_light(light_xy)
    check_scalar(scale_step, "scale_step")
    check_scalar(decay, "decay")
    loop_length, relaxed = resolve_count(num_iters, max_iters, "num_iters", "max_iters")
    height, width, _ = masked.shape
    dtype = masked.dtype
    light_xy = jnp.asarray(light_xy, dtype)
    count = checked_count(num_iters, loop_length, "num_iters", "max_iters", dtype) if relaxed else jnp.asarray(num_iters, dtype)
    x, y = pixel_centres(height, width, dtype)
    offset_x = x - light_xy[0]
    offset_y = y - light_xy[1]
    inverse_step = 1.0 / jnp.asarray(scale_step, dtype)

    def add_copy(k, carry):
        total, shrink, intensity = carry
        copy = sample_bilinear(
            masked, light_xy[0] + offset_x * shrink, light_xy[1] + offset_y * shrink, addressing="zero"
        )
        copy_weight = intensity
        if relaxed:
            copy_weight = copy_weight * jnp.clip(count - k, 0.0, 1.0)
        return total + copy_weight * copy, shrink * inverse_step, intensity * decay

    start = (jnp.zeros_like(masked), jnp.ones((), dtype), jnp.ones((), dtype))
    total, _, _ = jax.lax.fori_loop(0, loop_length, add_copy, start)
    return total
