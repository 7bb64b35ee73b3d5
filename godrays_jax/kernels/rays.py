"""Radial light shafts: the GPU Gems 3 radial blur (XNA crepuscular rays, galaxy VLS) and kbEngine's flare-outs.

All positions are pixels (x right, y down, pixel centres at `i + 0.5`). The light
may be anywhere: on screen, off screen or on a pixel centre; the kernels never
divide by the distance to it, so every case gives finite values and gradients.

Integer counts (`num_samples`, `num_iters`) accept a Python int (the exact
kernel) or a float / traced scalar with a static upper bound (the continuous
relaxation used for fitting); see each function for the relaxation.

Both kernels are sums of copies of the image scaled about the light,
`sum_k weight_k * image(light + (p - light) * scale_k)`, and share one
implementation, `scaled_copies`; the schedules below give each kernel's
scales and weights. How the copies are summed (a CPU loop of rows and
transposes, a GPU loop of 2-D gathers) and differentiated (few numbers in
forward mode inside the loop, memory O(image)) lives in `copies` and the
modules it names.
"""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from godrays_jax.kernels.copy_sums.copies import scaled_copies_of
from godrays_jax.primitives.checks import (
    check_image,
    check_light,
    check_scalar,
    checked_count,
    resolve_count,
)
from godrays_jax.primitives.sampling import Addressing, sample_separable


def scaled_copies(
    image: Float[Array, "H W C"],
    light_xy: Float[ArrayLike, "2"],
    scales: Float[ArrayLike, "K"],
    weights: Float[ArrayLike, "K"],
    *,
    addressing: Addressing = "clamp",
) -> Float[Array, "H W C"]:
    """`sum_k weights[k] * image(light + (p - light) * scales[k])` for every pixel centre `p`.

    The building block of radial rays and flare-outs: copy `k` is the image
    enlarged `1 / scales[k]` times about the light (`scales[k] = 1` is the image
    itself, `0` fills it with the value under the light), sampled bilinearly.

    Args:
        image: the texture.
        light_xy: the centre of scaling, in pixels; any real position.
        scales: `K` scale factors (any reals; negative ones mirror through the light).
        weights: `K` weights.
        addressing: off-image texels: `"clamp"` repeats the edge, `"zero"` is 0
            (see `sampling.sample_bilinear`).

    Returns:
        The weighted sum, same shape and dtype as `image`. Differentiable in
        every argument, forward and reverse mode, with memory O(image) for any `K`.
    """
    check_image(image)
    light_xy = check_light(light_xy)
    if addressing not in ("clamp", "zero"):
        raise ValueError(f"addressing must be 'clamp' or 'zero', got {addressing!r}")
    image = jnp.asarray(image)
    dtype = image.dtype
    scales = jnp.asarray(scales, dtype)
    weights = jnp.asarray(weights, dtype)
    if scales.ndim != 1 or scales.shape != weights.shape:
        raise ValueError(f"scales and weights must be vectors of one length, got {scales.shape} and {weights.shape}")
    light_xy = jnp.asarray(light_xy, dtype)
    return scaled_copies_of(_identity, (_identity, _identity), addressing, (image,), light_xy, ((scales,), (weights,)))


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
    source_radius: float | None = None,
) -> Float[Array, "H W C"]:
    """The GPU Gems 3 (ch. 13) radial-blur loop, exactly as the XNA crepuscular-rays article writes it.

    For each pixel centre `p`, with `delta = (p - light) * density / num_samples`:
    `exposure * (image(p) + sum_{i=1..n} weight * decay**(i-1) * image(p - i * delta))`,
    bilinear samples with clamp-to-edge addressing. With `density = 1` the last
    sample lands on the light; lights off screen read the clamped edge.

    Value and gradient (reverse or forward mode) need memory O(image), not
    O(samples x image). `godrays_jax.kernels.fast` has cheaper approximations.

    Args:
        image: the occlusion image (light source bright, occluders black).
        light_xy: the light's position in pixels.
        num_samples: samples per pixel. A Python int >= 1 runs the exact loop.
            A float (or traced) value `n` is the continuous relaxation: the step
            uses `n` and sample `i` (i = 1..max_samples) is weighted by
            `clip(n - i + 1, 0, 1)`, so whole samples are in or out and the last
            one fades in; at integer `n` it equals the exact loop. `n = 0` gives
            `exposure * image`.
        density: fraction of the way to the light the samples cover.
        decay: per-sample falloff, usually in (0, 1].
        weight: per-sample weight.
        exposure: overall scale.
        max_samples: static loop length for a relaxed `num_samples`.
        source_radius: optional promise, in pixels, that `image` is 0 farther
            than this from the light (a light-source disc). When the sample
            scales are known at trace time (concrete `density` and
            `num_samples`) and all lie in (0, 1], every sample of a pixel lies
            between it and the light and clamping only moves samples away from
            the light, so the rays are 0 farther than
            `(source_radius + 2) / min(scale)` from the light: the loop then
            runs on that window around the light (same result, fewer pixels).
            An image that breaks the promise gives wrong rays.

    Returns:
        The rays image, same shape and dtype as `image`.
    """
    check_image(image)
    return radial_rays_of(
        _identity,
        (jnp.asarray(image),),
        light_xy,
        num_samples=num_samples,
        density=density,
        decay=decay,
        weight=weight,
        exposure=exposure,
        max_samples=max_samples,
        source_radius=source_radius,
    )


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
    Copy 0 is `masked` itself. The sum is not normalised (kbEngine's article adds every
    copy into its target); scale it in the effect. Value and gradient need
    memory O(image), not O(iterations x image).

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
    return scale_iterated_flares_of(
        _identity, (jnp.asarray(masked),), light_xy, num_iters=num_iters, scale_step=scale_step, decay=decay,
        max_iters=max_iters,
    )  # fmt: skip


def _identity(image):
    return image


def _powers(base, length: int, dtype):
    """`[1, base, base**2, ...]`, `length` terms; unlike `base ** k` its gradient is finite at `base = 0`."""
    factors = jnp.concatenate([jnp.ones((1,), dtype), jnp.full((length - 1,), base, dtype)])
    return jnp.cumprod(factors)


def _radial_scales(loop_length: int, step):
    """The XNA crepuscular-rays article's sample scales `1 - i * step` (i = 1..loop_length), `step = density / n`."""
    return 1.0 - jnp.arange(1, loop_length + 1, dtype=step.dtype) * step


def _faded_powers(loop_length: int, relaxed: bool, decay, count):
    """Weights `decay**j` (j = 0..loop_length-1); relaxed, times the fade-in `clip(count - j, 0, 1)`."""
    weights = _powers(decay, loop_length, decay.dtype)
    if relaxed:
        weights = weights * jnp.clip(count - jnp.arange(loop_length, dtype=decay.dtype), 0.0, 1.0)
    return weights


def _flare_scales(loop_length: int, scale_step):
    """kbEngine's copy scales `scale_step**-k` (k = 0..loop_length-1)."""
    return _powers(1.0 / scale_step, loop_length, scale_step.dtype)


def _window_of(image_fn, size, origin, *image_args):
    return jax.lax.dynamic_slice(image_fn(*image_args), (origin[0], origin[1], jnp.int32(0)), size)


def radial_rays_of(image_fn, image_args, light_xy, *, num_samples, density, decay, weight, exposure, max_samples=None,
                 source_radius=None):  # fmt: skip
    """`radial_rays(image_fn(*image_args), ...)`.

    Differentiated inputs of `image_fn` with few numbers (a light-source
    disc's radius) are differentiated in forward mode inside the sample loop,
    so their reverse-mode gradient costs no adjoint of the image.
    """
    light_xy = check_light(light_xy)
    if source_radius is not None and not (isinstance(source_radius, (int, float)) and source_radius >= 0):
        raise ValueError(f"source_radius must be a Python number >= 0 (pixels) or None, got {source_radius!r}")
    for name, value in (("density", density), ("decay", decay), ("weight", weight), ("exposure", exposure)):
        check_scalar(value, name)
    loop_length, relaxed = resolve_count(num_samples, max_samples, "num_samples", "max_samples")
    shape = jax.eval_shape(image_fn, *image_args)
    dtype = shape.dtype
    if relaxed:
        count = checked_count(num_samples, loop_length, "num_samples", "max_samples", dtype)
    else:
        count = jnp.asarray(num_samples, dtype)
    schedule = (functools.partial(_radial_scales, loop_length), functools.partial(_faded_powers, loop_length, relaxed))
    # At n = 0 every weight is 0; a unit divisor keeps the (unused) positions finite.
    step = jnp.asarray(density, dtype) / (jnp.where(count > 0, count, 1.0) if relaxed else count)
    # The scales depend on density and n only through the step: one radial derivative sum in the loop for both.
    # `weight` scales every sample alike, so it multiplies their sum: one derivative image fewer in the loop.
    schedule_args = ((step,), (jnp.asarray(decay, dtype), count))
    weight = jnp.asarray(weight, dtype)
    exposure = jnp.asarray(exposure, dtype)
    light_xy = jnp.asarray(light_xy, dtype)
    window = None
    if source_radius is not None:
        window = _rays_window(shape.shape, source_radius, density, num_samples, loop_length, relaxed)
    if window is None:
        image = image_fn(*image_args)
        copies = scaled_copies_of(image_fn, schedule, "clamp", image_args, light_xy, schedule_args)
        return (image + weight * copies) * exposure
    # Every non-zero output pixel lies in the window, and so does every sample
    # it reads (or the window's edge is the image's): the windowed loop is exact.
    height, width, channels = shape.shape
    window_height, window_width, reach = window
    origin = jnp.stack(
        [
            jnp.clip(jnp.floor(light_xy[axis]) - reach, 0, size - extent).astype(jnp.int32)
            for axis, size, extent in ((1, height, window_height), (0, width, window_width))
        ]
    )
    part_fn = functools.partial(_window_of, image_fn, (window_height, window_width, channels))
    part_args = (origin, *image_args)
    local_light = light_xy - origin[::-1].astype(dtype)
    part = part_fn(*part_args)
    copies = scaled_copies_of(part_fn, schedule, "clamp", part_args, local_light, schedule_args)
    rays = (part + weight * copies) * exposure
    return jax.lax.dynamic_update_slice(jnp.zeros(shape.shape, dtype), rays, (origin[0], origin[1], jnp.int32(0)))


def _rays_window(shape, source_radius: float, density, num_samples, loop_length: int, relaxed: bool):
    """`(height, width, reach)` of the window that holds all rays of a source within `source_radius` px of the light.

    None when it cannot be known at trace time (a traced `density` or
    `num_samples`), is unbounded (a sample scale outside (0, 1]) or saves little.
    """
    if isinstance(density, jax.core.Tracer) or isinstance(num_samples, jax.core.Tracer):
        return None
    density, count = float(np.asarray(density)), float(np.asarray(num_samples))
    # Sample i (1-based) sits at scale 1 - i * density / count; the relaxation
    # weights it clip(count - i + 1, 0, 1), so the last live one is below count + 1.
    last = min(loop_length, math.ceil(count)) if relaxed else loop_length
    smallest_scale = 1.0 - last * density / count if count > 0 else 1.0
    if not (density >= 0 and smallest_scale > 0):
        return None
    # Bilinear samples reach one texel past the source; one more for rounding.
    reach = math.ceil((source_radius + 2.0) / smallest_scale)
    height, width = min(shape[0], 2 * reach + 2), min(shape[1], 2 * reach + 2)
    if height * width > shape[0] * shape[1] // 2:
        return None
    return height, width, reach


def scale_iterated_flares_of(image_fn, image_args, light_xy, *, num_iters, scale_step, decay=1.0, max_iters=None):
    """`scale_iterated_flares(image_fn(*image_args), ...)`, differentiated like `radial_rays_of`."""
    light_xy = check_light(light_xy)
    check_scalar(scale_step, "scale_step")
    check_scalar(decay, "decay")
    loop_length, relaxed = resolve_count(num_iters, max_iters, "num_iters", "max_iters")
    dtype = jax.eval_shape(image_fn, *image_args).dtype
    if relaxed:
        count = checked_count(num_iters, loop_length, "num_iters", "max_iters", dtype)
    else:
        count = jnp.asarray(num_iters, dtype)
    schedule = (functools.partial(_flare_scales, loop_length), functools.partial(_faded_powers, loop_length, relaxed))
    schedule_args = ((jnp.asarray(scale_step, dtype),), (jnp.asarray(decay, dtype), count))
    return scaled_copies_of(image_fn, schedule, "zero", image_args, jnp.asarray(light_xy, dtype), schedule_args)


def flare_outs_into(
    masked: Float[Array, "H W C"],
    light_xy: Float[ArrayLike, "2"],
    *,
    target_shape: tuple[int, int],
    num_iters: int | Float[ArrayLike, ""],
    scale_step: Float[ArrayLike, ""],
    decay: Float[ArrayLike, ""] = 1.0,
    max_iters: int | None = None,
) -> Float[Array, "h w C"]:
    """kbEngine's flare-outs drawn from the full-resolution masked texture into a smaller target, as its article does.

    `scale_iterated_flares`, but the copies are summed in a target of
    `target_shape = (h, w)` pixels covering the same frame: target pixel `i`
    (centre `(i + 0.5) / w` in UV, `(i + 0.5) * W / w` full-resolution pixels)
    adds `decay**k * masked(light + (p - light) / scale_step**k)` for each
    copy, sampled bilinearly from the full-resolution `masked` (texels outside
    it are 0), so no detail is averaged away before the copies are scaled.
    `light_xy` is in full-resolution pixels. `num_iters` and `max_iters` as in
    `scale_iterated_flares`. Differentiable in every argument (memory O(copies
    x target)).
    """
    check_image(masked, "masked")
    light_xy = check_light(light_xy)
    check_scalar(scale_step, "scale_step")
    check_scalar(decay, "decay")
    if not all(isinstance(size, int) and size >= 1 for size in target_shape):
        raise ValueError(f"target_shape must be two Python ints >= 1, got {target_shape!r}")
    loop_length, relaxed = resolve_count(num_iters, max_iters, "num_iters", "max_iters")
    dtype = masked.dtype
    count = (
        checked_count(num_iters, loop_length, "num_iters", "max_iters", dtype)
        if relaxed
        else jnp.asarray(num_iters, dtype)
    )
    scales = _flare_scales(loop_length, jnp.asarray(scale_step, dtype))
    weights = _faded_powers(loop_length, relaxed, jnp.asarray(decay, dtype), count)
    light_xy = jnp.asarray(light_xy, dtype)
    return _copies_into(masked, light_xy, scales, weights, tuple(target_shape))


@functools.partial(jax.jit, static_argnums=4)
def _copies_into(masked, light_xy, scales, weights, target_shape):
    """`flare_outs_into`'s loop over the copies, compiled once per shape: called eagerly, a loop over a function
    defined in the call would be traced and compiled again on every call."""
    (height, width), dtype = target_shape, masked.dtype
    xs = (jnp.arange(width, dtype=dtype) + 0.5) * (masked.shape[1] / width)
    ys = (jnp.arange(height, dtype=dtype) + 0.5) * (masked.shape[0] / height)

    def add_copy(k, total):
        copy_xs = light_xy[0] + (xs - light_xy[0]) * scales[k]
        copy_ys = light_xy[1] + (ys - light_xy[1]) * scales[k]
        return total + weights[k] * sample_separable(masked, copy_xs, copy_ys, addressing="zero")

    return jax.lax.fori_loop(0, scales.shape[0], add_copy, jnp.zeros((height, width, masked.shape[2]), dtype))
