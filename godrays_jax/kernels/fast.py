"""Fast approximations of `radial_rays` and `scale_iterated_flares`, for real-time budgets and many-evaluation fits.

Three independent tricks, each a pure function; `fast_radial_rays` combines
them into the project's default fast path (used by `GodRays(method="fast")`):

- `radial_rays_multipass`: the engines' multi-pass radial blur (CryEngine 2:
  3 passes x 8 taps, "virtually 512"; Unreal 3 x 12). Each pass samples the
  previous pass's output with a step `num_taps` times longer, so `num_taps**num_passes`
  effective samples cost `num_passes * num_taps` image reads.
- `at_reduced_resolution`: run any kernel on a `resolution_factor`-times smaller box-averaged
  image and read it back bilinearly (rays are smooth, so 1/2 resolution costs
  a quarter of the reads for little error; errors in `benchmarks/README.md`).
- `radial_rays_jittered`: per-pixel interleaved-gradient-noise offsets of the
  sample positions, trading the banding of low sample counts for fine noise.

Errors against the exact 128-sample loop (PSNR) are measured by
`benchmarks/run.py` and listed in `benchmarks/README.md`. Every function is
differentiable in its image, light and scalars (fittable like the exact
kernels), and like them needs O(image) memory for value and gradient.
"""

from collections.abc import Callable

import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike
from jaxtyping import Array, ArrayLike, Float

from godrays_jax.kernels.rays import scaled_copies
from godrays_jax.primitives.checks import (
    check_image,
    check_light,
    check_scalar,
    checked_count,
    is_static_int,
    resolve_count,
)
from godrays_jax.primitives.resample import downsample_box, upsample_bilinear
from godrays_jax.primitives.sampling import pixel_centres, sample_bilinear


def _check_ray_options(image, light_xy, density, decay, weight, exposure):
    """Trace-time checks; returns the image as a JAX array and the light as `check_light` bounds it."""
    check_image(image)
    light_xy = check_light(light_xy)
    for name, value in (("density", density), ("decay", decay), ("weight", weight), ("exposure", exposure)):
        check_scalar(value, name)
    return jnp.asarray(image), light_xy


def _check_positive_int(value, name: str, minimum: int = 1) -> None:
    if not is_static_int(value) or value < minimum:
        raise ValueError(f"{name} must be a Python int >= {minimum}, got {value!r}")


def _count(num_samples, max_samples, dtype):
    loop_length, relaxed = resolve_count(num_samples, max_samples, "num_samples", "max_samples")
    if relaxed:
        return loop_length, checked_count(num_samples, loop_length, "num_samples", "max_samples", dtype)
    return loop_length, jnp.asarray(num_samples, dtype)


def radial_rays_multipass(
    image: Float[Array, "H W C"],
    light_xy: Float[ArrayLike, "2"],
    *,
    num_samples: int | Float[ArrayLike, ""],
    density: Float[ArrayLike, ""],
    decay: Float[ArrayLike, ""],
    weight: Float[ArrayLike, ""],
    exposure: Float[ArrayLike, ""],
    num_passes: int = 3,
    num_taps: int = 8,
) -> Float[Array, "H W C"]:
    """Multi-pass approximation of `radial_rays` with the same parameters: `num_passes * num_taps` reads,
    `num_taps**num_passes` samples.

    Scaling about the light composes multiplicatively, so in `u = -log(scale)`
    every pass is a comb: pass `k` reads the previous output at scales
    `exp(-(j * num_taps**k + offset) * h)`, j = 0..num_taps-1, with weights
    `w_k[j]`. Their composition is exactly the comb of `M = num_taps**num_passes`
    samples at `u = (m + 1/2) * h` weighted
    `A * prod_k w_k[digit_k(m)]` (`digit_k(m)` the k-th base-`num_taps` digit of
    `m`). The exact loop's samples (`scale_i = 1 - i * density / n`, weight
    `weight * decay**(i-1)`, i = 1..n, each the right end of its cell
    `(i - 1, i]` of the sample index) are a density in `u`; the comb spans
    the same range of `u` (scales 1 to `1 - density`) and `log w_k` are the
    weighted least-squares fit of the log of that density's mass per comb
    cell (weights: the mass), a sum of one term per digit; `A` makes the total weight exactly
    `weight * sum_i decay**(i-1)`.
    The pixel's own term `image(p)` is added exactly. A relaxed (float or
    traced) `num_samples` needs no upper bound here: it only moves the comb.

    Accuracy: the rays match the exact loop closely for the usual
    `0 < density <= 1` and `decay` near 1 (see `benchmarks/README.md` for
    PSNR); they are smoother (no banding). Samples stop at the light: a
    `density` above 1 (which mirrors through the light in the exact loop) is
    treated as reaching the light. Off-screen lights read the clamped edge at
    every pass, which differs slightly from one clamped read.

    Args:
        image, light_xy, num_samples, density, decay, weight, exposure: as
            `radial_rays` (pixels, clamp-to-edge addressing).
        num_passes: static number of num_passes (>= 1).
        num_taps: static num_taps per pass (>= 1).

    Returns:
        The rays image, same shape and dtype as `image`.
    """
    image, light_xy = _check_ray_options(image, light_xy, density, decay, weight, exposure)
    _check_positive_int(num_passes, "num_passes")
    _check_positive_int(num_taps, "num_taps")
    dtype = image.dtype
    if is_static_int(num_samples):
        _count(num_samples, None, dtype)
    else:
        check_scalar(num_samples, "num_samples")
    count = jnp.maximum(jnp.asarray(num_samples, dtype), 0.0)
    comb_length = num_taps**num_passes
    # The exact samples i = 1..n are the right ends of the sample index's cells (i - 1, i]: the comb
    # spreads them over t in [0, n], as the loop with ever more samples does (scales 1 - t * density / n,
    # mapped to u = -log(scale)).
    step = jnp.clip(jnp.asarray(density, dtype), 0.0, 1.0) / jnp.maximum(count, 1e-6)
    smallest_scale = 1.0 / (4.0 * max(image.shape[0], image.shape[1]))  # within a pixel of the light
    u_end = -jnp.log(jnp.maximum(1.0 - count * step, smallest_scale))
    cell = u_end / comb_length
    edges = cell * jnp.arange(comb_length + 1, dtype=dtype)
    # Sample index t at each cell edge; the linear limit keeps density -> 0 finite.
    safe_step = jnp.where(step > 1e-12, step, 1.0)
    linear_index = count * jnp.arange(comb_length + 1, dtype=dtype) / comb_length
    index = jnp.where(step > 1e-12, -jnp.expm1(-edges) / safe_step, linear_index)
    log_decay = jnp.log(jnp.clip(jnp.asarray(decay, dtype), 1e-6, None))
    width = jnp.diff(index)
    flat_decay = jnp.abs(log_decay) < 1e-6
    safe_log_decay = jnp.where(flat_decay, 1.0, log_decay)
    cell_mass = jnp.exp((index[:-1] - 1.0) * log_decay) * jnp.where(
        flat_decay, width, jnp.expm1(width * log_decay) / safe_log_decay
    )
    # sum_{i=1..n} decay**(i-1), exact at integer n and smooth in between.
    total_mass = jnp.asarray(weight, dtype) * jnp.where(
        flat_decay, count, jnp.expm1(count * log_decay) / jnp.expm1(safe_log_decay)
    )
    # The comb's weights are products of one weight per pass and digit, so log(weight) is a sum of one
    # term per digit: fitted to log(mass) by weighted least squares (weights = mass), it follows the
    # exact loop's profile along the ray closely (a single exponential in m could not: mass per cell
    # falls as exp(-u) * decay**t(u)). A profile that departs from the loop's draws every shaft's edge
    # into the error, which a moving camera turns into shimmer.
    # Guarded divisions (not maximum(x, eps)) so that an empty comb (n = 0) keeps finite gradients.
    mass_sum = jnp.sum(cell_mass)
    fit_weights = jnp.where(mass_sum > 0, cell_mass, 1.0) / jnp.where(mass_sum > 0, mass_sum, comb_length)
    log_mass = jnp.log(jnp.maximum(cell_mass, 1e-30))
    design = jnp.asarray(_digit_design(num_passes, num_taps), dtype)
    normal = design.T @ (fit_weights[:, None] * design)
    # A small ridge picks one of the equivalent solutions (a constant moves freely between passes).
    ridge = 1e-6 * jnp.eye(num_passes * num_taps, dtype=dtype)
    centred = log_mass - jnp.sum(fit_weights * log_mass)
    log_weights = jnp.linalg.solve(normal + ridge, design.T @ (fit_weights * centred))
    log_weights = jnp.clip(log_weights.reshape(num_passes, num_taps), -30.0, 30.0)
    log_weights = log_weights - jnp.max(log_weights, axis=1, keepdims=True)

    light_xy = jnp.asarray(light_xy, dtype)
    rays = image
    digits = jnp.arange(num_taps, dtype=dtype)
    # Coarse pass first: the sharp image is resampled once at scales far apart, and the fine passes
    # (scales near 1, whose bilinear blur follows the light's sub-pixel position) read smooth images.
    for level in reversed(range(num_passes)):
        stride = num_taps**level
        scales = jnp.exp(-cell * digits * stride)
        if level == 0:
            scales = scales * jnp.exp(-0.5 * cell)
        rays = scaled_copies(rays, light_xy, scales, jnp.exp(log_weights[level]))
    comb_mass = jnp.prod(jnp.sum(jnp.exp(log_weights), axis=1))
    return (image + rays * (total_mass / comb_mass)) * jnp.asarray(exposure, dtype)


def _digit_design(num_passes: int, num_taps: int) -> np.ndarray:
    """`(num_taps**num_passes, num_passes * num_taps)` indicators: row `m` marks each pass's digit of `m` (base `num_taps`)."""
    m = np.arange(num_taps**num_passes)
    design = np.zeros((num_taps**num_passes, num_passes * num_taps))
    for level in range(num_passes):
        design[m, level * num_taps + (m // num_taps**level) % num_taps] = 1.0
    return design


def at_reduced_resolution(
    image: Float[Array, "H W C"],
    light_xy: Float[ArrayLike, "2"],
    *,
    kernel: Callable[..., Float[Array, "h w C"]],
    resolution_factor: int,
    **options,
) -> Float[Array, "H W C"]:
    """`kernel(image, light_xy, **options)` computed at `1/resolution_factor` resolution and upsampled.

    The image is box-averaged over square blocks of `resolution_factor` pixels a side (`downsample_box`),
    the light moved to `light_xy / resolution_factor` (pixels of the small image), the
    kernel run there, and the result read back bilinearly (`upsample_bilinear`).
    Kernel options in pixels would need rescaling; those of `radial_rays`,
    `radial_rays_multipass` and `scale_iterated_flares` are all unitless.
    `resolution_factor = 1` calls the kernel unchanged.
    """
    check_image(image)
    light_xy = check_light(light_xy)
    _check_positive_int(resolution_factor, "resolution_factor")
    image = jnp.asarray(image)
    if resolution_factor == 1:
        return kernel(image, light_xy, **options)
    height, width, _ = image.shape
    light_small = jnp.asarray(light_xy, image.dtype) / resolution_factor
    small = kernel(downsample_box(image, resolution_factor), light_small, **options)
    return upsample_bilinear(small, resolution_factor, height, width)


def interleaved_gradient_noise(height: int, width: int, *, seed: int = 0, dtype: DTypeLike = jnp.float32) -> Float[Array, "H W"]:
    """Jimenez's interleaved gradient noise in [0, 1): `fract(52.98 * fract(0.0671 x + 0.00584 y))`.

    `x, y` are integer pixel indices shifted by `seed` (a static int that picks
    another, equally blue, pattern). Computed in float64 on the host so the
    pattern is the same on every device.
    """
    x = np.arange(width, dtype=np.float64)[None, :] + 5.588238 * seed
    y = np.arange(height, dtype=np.float64)[:, None] + 1.617 * seed
    noise = np.mod(52.9829189 * np.mod(0.06711056 * x + 0.00583715 * y, 1.0), 1.0)
    return jnp.asarray(noise, dtype)


def radial_rays_jittered(
    image: Float[Array, "H W C"],
    light_xy: Float[ArrayLike, "2"],
    *,
    num_samples: int | Float[ArrayLike, ""],
    density: Float[ArrayLike, ""],
    decay: Float[ArrayLike, ""],
    weight: Float[ArrayLike, ""],
    exposure: Float[ArrayLike, ""],
    max_samples: int | None = None,
    seed: int = 0,
) -> Float[Array, "H W C"]:
    """`radial_rays` with every pixel's samples shifted by a fraction of a step (interleaved gradient noise).

    Sample `i` of pixel `p` sits at `p - (i - 1/2 + noise(p)) * delta`
    (`delta` as in `radial_rays`, `noise` in [0, 1) from
    `interleaved_gradient_noise(seed=seed)`), so neighbouring pixels sample
    between each other's positions: at low sample counts the bands of the
    exact loop turn into fine noise that averages out. Deterministic for a
    given `seed`. Each sample is a 2-D gather (`sample_bilinear`), slower per
    sample than the exact kernel's separable reads: use it with few samples.
    Relaxed counts and gradients work as in `radial_rays`; memory grows with
    the number of samples in reverse mode (plain `fori_loop`).
    """
    image, light_xy = _check_ray_options(image, light_xy, density, decay, weight, exposure)
    height, width, _ = image.shape
    dtype = image.dtype
    loop_length, count = _count(num_samples, max_samples, dtype)
    relaxed = not is_static_int(num_samples)
    light_xy = jnp.asarray(light_xy, dtype)
    x, y = pixel_centres(height, width, dtype)
    divisor = jnp.where(count > 0, count, 1.0)
    offset = interleaved_gradient_noise(height, width, seed=seed, dtype=dtype) - 0.5
    step_x = (x - light_xy[0]) * (jnp.asarray(density, dtype) / divisor)
    step_y = (y - light_xy[1]) * (jnp.asarray(density, dtype) / divisor)
    total = image
    illumination = jnp.ones((), dtype)
    for i in range(1, loop_length + 1):
        sample = sample_bilinear(image, x - (i + offset) * step_x, y - (i + offset) * step_y)
        sample_weight = illumination * jnp.asarray(weight, dtype)
        if relaxed:
            sample_weight = sample_weight * jnp.clip(count - i + 1, 0.0, 1.0)
        total = total + sample_weight * sample
        illumination = illumination * jnp.asarray(decay, dtype)
    return total * jnp.asarray(exposure, dtype)


def fast_radial_rays(
    image: Float[Array, "H W C"],
    light_xy: Float[ArrayLike, "2"],
    *,
    num_samples: int | Float[ArrayLike, ""],
    density: Float[ArrayLike, ""],
    decay: Float[ArrayLike, ""],
    weight: Float[ArrayLike, ""],
    exposure: Float[ArrayLike, ""],
    resolution_factor: int = 2,
    num_passes: int = 3,
    num_taps: int = 8,
) -> Float[Array, "H W C"]:
    """The default fast path: `radial_rays_multipass` at `1/resolution_factor` resolution, plus the exact pixel term.

    `exposure * (image(p) + upsampled multi-pass sum)`: the pixel's own term
    (the sharp emitter) stays exact at full resolution and only the smooth
    shafts are computed small. With the defaults (1/2 resolution, 3 x 8) it
    reads 24 quarter-size images instead of 128 full ones. Same parameters
    and units as `radial_rays`; see `radial_rays_multipass` for accuracy.
    """
    image, light_xy = _check_ray_options(image, light_xy, density, decay, weight, exposure)
    _check_positive_int(resolution_factor, "resolution_factor")

    def shafts(small, small_light):
        return radial_rays_multipass(
            small, small_light, num_samples=num_samples, density=density, decay=decay, weight=weight,
            exposure=1.0, num_passes=num_passes, num_taps=num_taps,
        ) - small  # fmt: skip
    reduced = at_reduced_resolution(image, light_xy, kernel=shafts, resolution_factor=resolution_factor)
    return (image + reduced) * jnp.asarray(exposure, image.dtype)
