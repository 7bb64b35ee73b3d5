"""Sums of scaled copies of an image, with derivatives in memory O(image): platform dispatch and the custom JVP.

`scaled_copies_of(image_fn, schedule, ...)` is `sum_k weight_k *
image(light + (p - light) * scale_k)` with the image, the scales and the
weights each computed from arguments by a function, so that its derivative
loop can tell the few numbers that move the copies (a radial derivative sum
each) from those that weight them (a copy sum each) and from the image's own
(derivative images sampled like it); see `forward_mode`. The image's own
tangent goes through `copies_in_image`, a primitive linear in the image whose
transpose (reverse mode) is `adjoint.copy_adjoint`, a gather like the copies.
Per-copy scales and weights (vectors of many numbers) get a rematerialised
tangent loop that reverse mode transposes.
The CPU and other platforms sum the copies in different loops (`cpu_loop`,
`gpu_loop`) with the same values.
"""

import functools

import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir

from godrays_jax.kernels.copy_sums.adjoint import copy_adjoint
from godrays_jax.kernels.copy_sums.cpu_loop import copy_sums_cpu
from godrays_jax.kernels.copy_sums.forward_mode import (
    FEW_NUMBERS,
    differentiated,
    tangent_of,
)
from godrays_jax.kernels.copy_sums.gpu_loop import copy_sums_gpu
from godrays_jax.kernels.copy_sums.planes import (
    Planes,
    copy_derivatives,
    copy_taps,
    lerp_rows,
    offsets,
)


@functools.partial(jax.jit, static_argnums=(0, 1))
def copy_sums(addressing, light_varies, image, derivative_image, light_xy, scales, weights, jacobians):
    """The copies' sum and, for forward-mode derivatives, the sums of their derivative images.

    With `image (H, W, C)` and `K` copies: the weighted copies' sum; if
    `derivative_image (H, W, C')` is given, its copies' sum; `jacobians` is the
    scales' Jacobian `(K, S)` and the weights' `(K, V)` in the few numbers each
    depends on (either may be None): per scale number the sum of every copy's
    radial derivative `(p - light) . grad` times its weight and its scale's
    derivative, per weight number the sum of every copy times its weight's
    derivative; if `light_varies`, the sums of the copies' x and y
    derivatives times `1 - scale` (their derivatives in the light). Returns
    `(total, derivative_total, scale_sums, weight_sums, light_sums)` in
    `Planes`' column layout `(W, C*H)` (numbers last); absent ones are None.
    The CPU and other platforms get different loops (same values).

    Compiled as one program, cached by its static arguments and the shapes: an
    eager call would trace the platform's loops anew (new functions each time)
    and compile them again on every call.
    """
    operands = (image, derivative_image, light_xy, scales, weights, jacobians)
    return jax.lax.platform_dependent(
        *operands,
        cpu=functools.partial(copy_sums_cpu, addressing, light_varies),
        default=functools.partial(copy_sums_gpu, addressing, light_varies),
    )


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2))
def scaled_copies_of(image_fn, schedule, addressing, image_args, light_xy, schedule_args):
    """`scaled_copies(image_fn(*image_args), light_xy, scales, weights)`, differentiable in every argument.

    `schedule = (scales_fn, weights_fn)` and `schedule_args = (scale_args,
    weight_args)`: `scales = scales_fn(*scale_args)`, `weights =
    weights_fn(*weight_args)`. Keeping them apart lets the derivative loop sum
    radial derivatives only for the numbers that move the copies and copies
    only for the numbers that weight them.
    """
    image = image_fn(*image_args)
    (scales_fn, weights_fn), (scale_args, weight_args) = schedule, schedule_args
    total, _, _, _, _ = copy_sums(
        addressing, False, image, None, light_xy, scales_fn(*scale_args), weights_fn(*weight_args), (None, None)
    )
    return Planes(image.shape).image_from_columns(total)


@functools.partial(scaled_copies_of.defjvp, symbolic_zeros=True)
def _scaled_copies_jvp(image_fn, schedule, addressing, primals, tangents):
    image_args, light_xy, (scale_args, weight_args) = primals
    image_tangents, light_dot, (scale_tangents, weight_tangents) = tangents
    scales_fn, weights_fn = schedule
    light_varies = type(light_dot) is not SymbolicZero
    image, image_jacobian, image_direction, image_part = differentiated(image_fn, image_args, image_tangents)
    scales, scale_jacobian, scale_direction, scale_part = differentiated(scales_fn, scale_args, scale_tangents)
    # The scales and weights share one budget: vectors of a weight per copy are many numbers even when the scales
    # are few (a sum per number would cost more than the tangent loop).
    weight_budget = FEW_NUMBERS - (0 if scale_direction is None else scale_direction.size)
    weights, weight_jacobian, weight_direction, weight_part = differentiated(
        weights_fn, weight_args, weight_tangents, weight_budget
    )
    dtype = image.dtype
    planes = Planes(image.shape)
    # One loop computes the copies' sum and, for every differentiated input
    # of few numbers, the image its tangent multiplies: the sum over copies of
    # the copy's derivative in that input. The copies' scales act through
    # their radial derivatives `(p - light) . grad`, the weights through the
    # copies, the light's sampling through their x and y derivatives times
    # `1 - scale`, and the image's few inputs through their derivative images
    # sampled like it.
    total, derivative_total, scale_sums, weight_sums, light_sums = copy_sums(
        addressing,
        light_varies,
        image,
        None if image_jacobian is None else image_jacobian.reshape(planes.height, planes.width, -1),
        light_xy,
        scales,
        weights,
        (scale_jacobian, weight_jacobian),
    )

    tangent = jnp.zeros_like(total)
    if image_jacobian is not None:
        by_number = derivative_total.reshape(planes.width, planes.channels, image_direction.size, planes.height)
        tangent += jnp.einsum("wcqh,q->wch", by_number, image_direction, precision="highest").reshape(total.shape)
    for number_sums, direction in ((scale_sums, scale_direction), (weight_sums, weight_direction)):
        if number_sums is not None:
            tangent += jnp.matmul(number_sums, direction, precision="highest")
    if light_varies:
        tangent += jnp.tensordot(jnp.asarray(light_dot, dtype), jnp.stack(light_sums), 1, precision="highest")

    # Per-copy weight and scale tangents (many numbers): a tangent loop,
    # rematerialised so that reverse mode recomputes each copy instead of
    # storing one image per copy; they multiply the copy and its radial
    # derivative (reverse mode reduces the cotangent against them).
    image_dot, scales_dot, weights_dot = (
        tangent_of(function, part)
        for function, part in ((image_fn, image_part), (scales_fn, scale_part), (weights_fn, weight_part))
    )
    if scales_dot is not None or weights_dot is not None:
        tangent += _tangent_of_many(planes, addressing, image, light_xy, scales, weights, scales_dot, weights_dot)
    tangent = planes.image_from_columns(tangent)
    # The image's tangent of many numbers is sampled like the image; reverse mode gathers its adjoint.
    if image_dot is not None:
        tangent += copies_in_image.bind(image_dot, light_xy, scales, weights, addressing=addressing)
    return planes.image_from_columns(total), tangent


def _copies_total(image, light_xy, scales, weights, *, addressing):
    total, _, _, _, _ = copy_sums(addressing, False, image, None, light_xy, scales, weights, (None, None))
    return Planes(image.shape).image_from_columns(total)


copies_in_image = Primitive("scaled_copies_in_image")
"""`copies_in_image.bind(image, light_xy, scales, weights, addressing=...)`: the sum of scaled copies, linear in `image`.

A primitive, so that reverse mode transposes it by `adjoint.copy_adjoint`
(gathers) instead of transposing the copies' gathers into scatters. Only the
image may be a linear (tangent) input; the light, scales and weights are
constants of the linear map. Its JVP in every input is `scaled_copies_of`'s.
"""
copies_in_image.def_impl(jax.jit(_copies_total, static_argnames="addressing"))
copies_in_image.def_abstract_eval(lambda image, *_, addressing: jax.core.ShapedArray(image.shape, image.dtype))
mlir.register_lowering(copies_in_image, mlir.lower_fun(_copies_total, multiple_results=False))


def _identity(image):
    return image


def _copies_in_image_jvp(primals, tangents, *, addressing):
    def of_all(image, light_xy, scales, weights):
        return scaled_copies_of(_identity, (_identity, _identity), addressing, (image,), light_xy, ((scales,), (weights,)))

    return jax.jvp(of_all, primals, [ad.instantiate_zeros(tangent) for tangent in tangents])


def _copies_in_image_transpose(cotangent, image, light_xy, scales, weights, *, addressing):
    if any(ad.is_undefined_primal(value) for value in (light_xy, scales, weights)):
        raise NotImplementedError("copies_in_image is linear in its image only")
    if type(cotangent) is ad.Zero:
        return ad.Zero(image.aval), None, None, None
    return copy_adjoint(addressing, cotangent, light_xy, scales, weights), None, None, None


def _copies_in_image_batch(args, dims, *, addressing):
    """A batch of images alone is summed as one image of more channels; anything else, one at a time.

    The batching protocol marks an operand without a batch axis by `None`.
    """
    image, light_xy, scales, weights = args
    if all(dim is None for dim in dims[1:]):
        moved = jnp.moveaxis(image, dims[0], -1)
        height, width, channels, count = moved.shape
        total = copies_in_image.bind(
            moved.reshape(height, width, channels * count), light_xy, scales, weights, addressing=addressing
        )
        return total.reshape(height, width, channels, count), 3
    count = next(value.shape[dim] for value, dim in zip(args, dims) if dim is not None)
    leading = [
        jnp.broadcast_to(value, (count,) + value.shape) if dim is None else jnp.moveaxis(value, dim, 0)
        for value, dim in zip(args, dims)
    ]
    return jax.lax.map(lambda values: copies_in_image.bind(*values, addressing=addressing), leading), 0


ad.primitive_jvps[copies_in_image] = _copies_in_image_jvp
ad.primitive_transposes[copies_in_image] = _copies_in_image_transpose
batching.primitive_batchers[copies_in_image] = _copies_in_image_batch


def _tangent_of_many(planes, addressing, image, light_xy, scales, weights, scales_dot, weights_dot):
    """The copies' sum's tangent in the scales' and weights' tangents (None: zero), in the column layout."""
    dtype = image.dtype
    by_rows = planes.by_rows(image)
    col_offsets, row_offsets = offsets(planes, light_xy, dtype)

    @jax.checkpoint
    def add_tangent(k, total_dot):
        (col_taps, col_slopes), (row_taps, row_slopes) = copy_taps(planes, light_xy, scales[k], addressing, dtype)
        columns = planes.rows_to_columns(k, planes.sample_rows(by_rows, row_taps))
        if weights_dot is not None:
            total_dot += weights_dot[k] * lerp_rows(columns, col_taps)
        if scales_dot is not None:
            x_derivative, y_derivative = copy_derivatives(planes, by_rows, k, columns, col_taps, col_slopes, row_slopes)
            radial_derivative = x_derivative * col_offsets + y_derivative * row_offsets
            total_dot += (weights[k] * scales_dot[k]) * radial_derivative
        return total_dot

    return jax.lax.fori_loop(0, scales.shape[0], add_tangent, planes.zeros(dtype))
