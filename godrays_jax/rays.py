"""Radial light shafts: GPU Gems 3 radial rays (seeds 003, 004) and kbEngine flare-outs (seed 002).

All positions are pixels (x right, y down, pixel centres at `i + 0.5`). The light
may be anywhere: on screen, off screen or on a pixel centre; the kernels never
divide by the distance to it, so every case gives finite values and gradients.

Integer counts (`num_samples`, `num_iters`) accept a Python int (the exact
kernel) or a float / traced scalar with a static upper bound (the continuous
relaxation used for fitting); see each function for the relaxation.

Both kernels are sums of copies of the image scaled about the light,
`sum_k weight_k * image(light + (p - light) * scale_k)`, and share one
implementation, `scaled_copies`. Scaling about a point keeps x and y
separate, so each bilinear copy is two 1-D interpolations (whole rows, then
whole columns), several times faster on a CPU than a 2-D gather per pixel and
equal to `sampling.sample_bilinear` up to rounding. Its derivatives (forward
and reverse mode) re-run the sampling loop instead of storing every copy, so
value and gradient need memory proportional to the image, not to the number
of samples.
"""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero
from jaxtyping import Array, ArrayLike, Float

from godrays_jax._checks import check_image, check_light, check_scalar, checked_count, resolve_count
from godrays_jax.sampling import Addressing, _axis_taps


def _copy_positions(shape, light_xy, scale, dtype):
    """Sample positions `light + (p - light) * scale` of the pixel centres: xs (W,) and ys (H,)."""
    height, width = shape
    rows = jnp.arange(height, dtype=dtype) + 0.5
    cols = jnp.arange(width, dtype=dtype) + 0.5
    return light_xy[0] + (cols - light_xy[0]) * scale, light_xy[1] + (rows - light_xy[1]) * scale


def _taps_and_slopes(size: int, u, addressing: Addressing):
    """`_axis_taps` at texel coordinates `u`, plus the taps' weights' derivatives with respect to `u`."""
    taps, (_, _, low_slope, high_slope) = jax.jvp(
        lambda u: _axis_taps(size, u, addressing), (u,), (jnp.ones_like(u),)
    )
    return taps, (taps[0], taps[1], low_slope, high_slope)


def _apart(step, compute, *operands):
    """`compute(*operands)`, kept out of its consumers' fusions.

    XLA fuses a gather with the computation of its operand and then evaluates
    that operand once per gathered element, through strided transposed reads:
    30x slower on a CPU than gathering from a stored array. A conditional is
    not fused with its surroundings, and its predicate (a loop counter
    `step >= 0`, always true) cannot be folded at compile time.
    """
    return jax.lax.cond(
        step >= 0, compute, lambda *values: jax.tree.map(jnp.zeros_like, compute(*values)), *operands
    )


class _Planes:
    """An `(H, W, C)` image held as 2-D arrays for the sample loop: `(H, W*C)` by rows or `(W, H*C)` by columns.

    Both interpolations of a copy then gather whole rows (contiguous slices)
    of a stored 2-D array, the columns' from the transposed rows, and every
    reduction reverse mode makes is over a 2-D array (XLA's CPU library
    reduction is ~40x slower over three dimensions).
    """

    def __init__(self, shape):
        self.height, self.width, self.channels = shape

    def by_rows(self, image):
        return jnp.asarray(image).reshape(self.height, self.width * self.channels)

    def rows_to_columns(self, step, rows):
        def transpose(rows):
            return jnp.swapaxes(rows.reshape(self.height, self.width, self.channels), 0, 1).reshape(
                self.width, self.height * self.channels
            )

        return _apart(step, transpose, rows)

    def image_from_columns(self, columns):
        return jnp.swapaxes(columns.reshape(self.width, self.height, self.channels), 0, 1)


def _lerp_rows(values, taps):
    """Linear interpolation between whole rows of a 2-D array: `values[low] * low_weight + values[high] * high_weight`."""
    low, high, low_weight, high_weight = taps
    lower = values.at[low].get(mode="promise_in_bounds")
    upper = values.at[high].get(mode="promise_in_bounds")
    return lower * low_weight[:, None] + upper * high_weight[:, None]


def _copy_taps(planes: _Planes, light_xy, scale, addressing: Addressing, dtype):
    """Row and column taps (with the weights' slopes) of the copy sampled at `light + (p - light) * scale`."""
    xs, ys = _copy_positions((planes.height, planes.width), light_xy, scale, dtype)
    return _taps_and_slopes(planes.width, xs - 0.5, addressing), _taps_and_slopes(planes.height, ys - 0.5, addressing)


@functools.partial(jax.custom_jvp, nondiff_argnums=(4,))
def _scaled_copies(image, light_xy, scales, weights, addressing):
    planes = _Planes(image.shape)
    by_rows = planes.by_rows(image)

    def add_copy(k, total):
        (col_taps, _), (row_taps, _) = _copy_taps(planes, light_xy, scales[k], addressing, image.dtype)
        columns = planes.rows_to_columns(k, _lerp_rows(by_rows, row_taps))
        return total + weights[k] * _lerp_rows(columns, col_taps)

    total = jax.lax.fori_loop(0, scales.shape[0], add_copy, jnp.zeros((planes.width, by_rows.size // planes.width), image.dtype))
    return planes.image_from_columns(total)


@functools.partial(_scaled_copies.defjvp, symbolic_zeros=True)
def _scaled_copies_jvp(addressing, primals, tangents):
    image, light_xy, scales, weights = primals
    total = _scaled_copies(image, light_xy, scales, weights, addressing)
    varies = [type(t) is not SymbolicZero for t in tangents]
    if not any(varies):
        return total, jnp.zeros_like(image)
    image_dot, light_dot, scales_dot, weights_dot = (jnp.asarray(t) if v else None for t, v in zip(tangents, varies))
    moves = varies[1] or varies[2]
    planes = _Planes(image.shape)
    dtype = image.dtype
    by_rows = planes.by_rows(image)
    tangent_by_rows = planes.by_rows(image_dot) if varies[0] else None
    # In the column layout `(W, H*C)` a pixel's x is its row, its y its column (repeated per channel).
    col_offsets = (jnp.arange(planes.width, dtype=dtype) + 0.5 - light_xy[0])[:, None]
    row_offsets = jnp.repeat(jnp.arange(planes.height, dtype=dtype) + 0.5 - light_xy[1], planes.channels)[None, :]

    # Each scalar tangent multiplies a whole known image (the copy, its x and
    # y derivatives, its radial derivative), so reverse mode reduces the
    # cotangent against it in one pass. The body is rematerialised: reverse
    # mode recomputes each copy instead of storing one image per copy.
    @jax.checkpoint
    def add_tangent(k, total_dot):
        (col_taps, col_slopes), (row_taps, row_slopes) = _copy_taps(planes, light_xy, scales[k], addressing, dtype)
        columns = planes.rows_to_columns(k, _lerp_rows(by_rows, row_taps))
        if varies[0]:
            columns_dot = planes.rows_to_columns(k, _lerp_rows(tangent_by_rows, row_taps))
            total_dot += weights[k] * _lerp_rows(columns_dot, col_taps)
        if varies[3]:
            total_dot += weights_dot[k] * _lerp_rows(columns, col_taps)
        if moves:
            # Positions `light + (p - light) * scale`: d/d(light) = 1 - scale, d/d(scale) = p - light.
            x_derivative = _lerp_rows(columns, col_slopes)
            y_derivative = _lerp_rows(planes.rows_to_columns(k, _lerp_rows(by_rows, row_slopes)), col_taps)
            if varies[1]:
                step = weights[k] * (1.0 - scales[k])
                total_dot += (step * light_dot[0]) * x_derivative + (step * light_dot[1]) * y_derivative
            if varies[2]:
                radial_derivative = x_derivative * col_offsets + y_derivative * row_offsets
                total_dot += (weights[k] * scales_dot[k]) * radial_derivative
        return total_dot

    zeros = jnp.zeros((planes.width, by_rows.size // planes.width), dtype)
    return total, planes.image_from_columns(jax.lax.fori_loop(0, scales.shape[0], add_tangent, zeros))


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
    check_light(light_xy)
    if addressing not in ("clamp", "zero"):
        raise ValueError(f"addressing must be 'clamp' or 'zero', got {addressing!r}")
    image = jnp.asarray(image)
    dtype = image.dtype
    scales = jnp.asarray(scales, dtype)
    weights = jnp.asarray(weights, dtype)
    if scales.ndim != 1 or scales.shape != weights.shape:
        raise ValueError(f"scales and weights must be vectors of one length, got {scales.shape} and {weights.shape}")
    return _scaled_copies(image, jnp.asarray(light_xy, dtype), scales, weights, addressing)


def _powers(base, length: int, dtype):
    """`[1, base, base**2, ...]`, `length` terms; unlike `base ** k` its gradient is finite at `base = 0`."""
    factors = jnp.concatenate([jnp.ones((1,), dtype), jnp.full((length - 1,), base, dtype)])
    return jnp.cumprod(factors)


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
    """The GPU Gems 3 (ch. 13) radial-blur loop, exactly as seed 003 writes it.

    For each pixel centre `p`, with `delta = (p - light) * density / num_samples`:
    `exposure * (image(p) + sum_{i=1..n} weight * decay**(i-1) * image(p - i * delta))`,
    bilinear samples with clamp-to-edge addressing. With `density = 1` the last
    sample lands on the light; lights off screen read the clamped edge.

    Value and gradient (reverse or forward mode) need memory O(image), not
    O(samples x image). `godrays_jax.fast` has cheaper approximations.

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
            runs on that window around the light (same result, fewer pixels;
            e.g. 8x fewer at 1920x1080 with seed 003's radius 120 px and
            density 0.5). An image that breaks the promise gives wrong rays.

    Returns:
        The rays image, same shape and dtype as `image`.
    """
    check_image(image)
    check_light(light_xy)
    if source_radius is not None and not (isinstance(source_radius, (int, float)) and source_radius >= 0):
        raise ValueError(f"source_radius must be a Python number >= 0 (pixels) or None, got {source_radius!r}")
    for name, value in (("density", density), ("decay", decay), ("weight", weight), ("exposure", exposure)):
        check_scalar(value, name)
    loop_length, relaxed = resolve_count(num_samples, max_samples, "num_samples", "max_samples")
    image = jnp.asarray(image)
    dtype = image.dtype
    steps = jnp.arange(1, loop_length + 1, dtype=dtype)
    if relaxed:
        count = checked_count(num_samples, loop_length, "num_samples", "max_samples", dtype)
        # At n = 0 every weight is 0; a unit divisor keeps the (unused) positions finite.
        divisor = jnp.where(count > 0, count, 1.0)
    else:
        divisor = count = jnp.asarray(num_samples, dtype)
    scales = 1.0 - steps * (jnp.asarray(density, dtype) / divisor)
    weights = jnp.asarray(weight, dtype) * _powers(jnp.asarray(decay, dtype), loop_length, dtype)
    if relaxed:
        weights = weights * jnp.clip(count - steps + 1.0, 0.0, 1.0)
    exposure = jnp.asarray(exposure, dtype)
    window = None
    if source_radius is not None:
        window = _rays_window(image.shape, source_radius, density, num_samples, loop_length, relaxed)
    if window is None:
        return (image + scaled_copies(image, light_xy, scales, weights)) * exposure
    # Every non-zero output pixel lies in the window, and so does every sample
    # it reads (or the window's edge is the image's): the windowed loop is exact.
    light_xy = jnp.asarray(light_xy, dtype)
    height, width, channels = image.shape
    window_height, window_width, reach = window
    corner = [
        jnp.clip(jnp.floor(light_xy[axis]) - reach, 0, size - extent).astype(jnp.int32)
        for axis, size, extent in ((1, height, window_height), (0, width, window_width))
    ]
    origin = (corner[0], corner[1], jnp.int32(0))
    part = jax.lax.dynamic_slice(image, origin, (window_height, window_width, channels))
    local_light = light_xy - jnp.stack([corner[1], corner[0]]).astype(dtype)
    rays = (part + scaled_copies(part, local_light, scales, weights)) * exposure
    return jax.lax.dynamic_update_slice(jnp.zeros_like(image), rays, origin)


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
    check_light(light_xy)
    check_scalar(scale_step, "scale_step")
    check_scalar(decay, "decay")
    loop_length, relaxed = resolve_count(num_iters, max_iters, "num_iters", "max_iters")
    dtype = masked.dtype
    scales = _powers(1.0 / jnp.asarray(scale_step, dtype), loop_length, dtype)
    weights = _powers(jnp.asarray(decay, dtype), loop_length, dtype)
    if relaxed:
        count = checked_count(num_iters, loop_length, "num_iters", "max_iters", dtype)
        weights = weights * jnp.clip(count - jnp.arange(loop_length, dtype=dtype), 0.0, 1.0)
    return scaled_copies(masked, light_xy, scales, weights, addressing="zero")
