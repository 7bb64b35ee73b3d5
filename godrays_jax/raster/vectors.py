"""Component-first `(3, P)` vector arithmetic for the tile loop (XLA on CPU reduces a minor axis of 3 slowly)."""

from jaxtyping import Array, Float

from godrays_jax.primitives.camera import unit_vectors


def dot(a: Float[Array, "3 *P"], b: Float[Array, "3 *P"]) -> Float[Array, "*P"]:
    """Dot products of component-first vectors (inside the tile loop vectors
    are `(3, P)`: XLA on CPU reduces a minor axis of 3 slowly)."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def times(vectors: Float[Array, "3 *P"], matrix: Float[Array, "3 3"]) -> Float[Array, "3 *P"]:
    """`vectors @ matrix`, component-first."""
    column = lambda i: matrix[i].reshape((3,) + (1,) * (vectors.ndim - 1))
    return vectors[0] * column(0) + vectors[1] * column(1) + vectors[2] * column(2)


def unit_first(vectors: Float[Array, "3 *P"]) -> Float[Array, "3 *P"]:
    """Component-first vectors scaled to length 1 (`unit_vectors` along axis 0)."""
    return unit_vectors(vectors, axis=0)
