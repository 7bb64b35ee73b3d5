"""Forward-mode derivatives of few numbers, taken inside the loop that sums the copies.

Differentiated inputs with at most `FEW_NUMBERS` numbers (density, decay, the
light, an emitter's radius) are differentiated in forward mode inside the
loop: it also sums, per number, the copies' derivative in it, so a gradient
costs one such loop and one reduction per number. Inputs of many numbers get
no sums: a whole image's tangent is a sum of copies that reverse mode
transposes by gathers (`copies.copies_in_image`, `adjoint`), a weight per copy
a tangent loop (`copies`).
"""

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero

FEW_NUMBERS = 8
"""Differentiated inputs with at most this many numbers in all (counted for the image's inputs, and for the copies'
scales' and weights' together) are differentiated in forward mode inside the loop.

Their derivative images (of the copies' weights and scales, the light, or
the few numbers an image is computed from) are accumulated alongside the
copies, so reverse mode needs one reduction per number after the loop, and
no adjoint of the image. Larger inputs get no sums: a whole image goes
through `copies.copies_in_image` (its adjoint gathered, `adjoint`), a vector
of weights per copy through a tangent loop that reverse mode transposes.
"""


def _split_varying(args, tangents, budget):
    """The flattened `args` and tangents, and the differentiated leaves' indices: few (`budget` numbers in all), many."""
    leaves, tree = jax.tree.flatten(args)
    tangent_leaves = tree.flatten_up_to(tangents)
    few, many = [], []
    for index, (leaf, tangent) in enumerate(zip(leaves, tangent_leaves)):
        if type(tangent) is SymbolicZero:
            continue
        if np.size(leaf) <= budget:
            few.append(index)
            budget -= np.size(leaf)
        else:
            many.append(index)
    return leaves, tree, tangent_leaves, few, many


def _replaced(leaves, tree, indices, values):
    """The arguments rebuilt from `leaves`, with the leaves at `indices` replaced by `values`."""
    leaves = list(leaves)
    for index, value in zip(indices, values):
        leaves[index] = value
    return tree.unflatten(leaves)


def _forward_derivatives(function, leaves, tree, tangent_leaves, indices):
    """`function(*args)`, its Jacobian in the leaves at `indices` (last axis), and those leaves' tangents, flattened."""
    flat, unflatten = jax.flatten_util.ravel_pytree([leaves[i] for i in indices])
    direction, _ = jax.flatten_util.ravel_pytree([jnp.asarray(tangent_leaves[i], flat.dtype) for i in indices])

    def of_flat(flat):
        return function(*_replaced(leaves, tree, indices, unflatten(flat)))

    value, jacobian = jax.vmap(lambda basis: jax.jvp(of_flat, (flat,), (basis,)), out_axes=(None, -1))(
        jnp.eye(flat.size, dtype=flat.dtype)
    )
    return value, jacobian, direction


def differentiated(function, args, tangents, budget=FEW_NUMBERS):
    """`function(*args)`, with its forward-mode Jacobian in the few differentiated numbers of `args`.

    Returns the value, the Jacobian (numbers on the last axis; None without
    few numbers), those numbers' tangents (flattened) and the inputs of many
    numbers `(leaves, tree, tangent_leaves, indices)`: the leaves that fit in
    `budget` numbers are few (see `FEW_NUMBERS`).
    """
    leaves, tree, tangent_leaves, few, many = _split_varying(args, tangents, budget)
    if few:
        value, jacobian, direction = _forward_derivatives(function, leaves, tree, tangent_leaves, few)
    else:
        value, jacobian, direction = function(*args), None, None
    return value, jacobian, direction, (leaves, tree, tangent_leaves, many)


def tangent_of(function, part):
    """The tangent of `function` in the inputs of many numbers of `part` (from `differentiated`), or None."""
    leaves, tree, tangent_leaves, many = part
    if not many:
        return None
    _, tangent = jax.jvp(
        lambda *values: function(*_replaced(leaves, tree, many, values)),
        [leaves[i] for i in many],
        [jnp.asarray(tangent_leaves[i]) for i in many],
    )
    return tangent
