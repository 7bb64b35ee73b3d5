"""The frame buffers every effect reads: colour, depth, coverage and optional passes."""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float, Int


class Buffers(eqx.Module):
    """One rendered frame.

    Attributes:
        color: linear HDR colour, `(H, W, C)` with C = 1, 3 or 4.
        depth: linear distance along the camera ray in scene units, `(H, W)`;
            `+inf` where nothing was hit (sky).
        coverage: fraction of each pixel covered by geometry, `(H, W)` in [0, 1].
        normal: world-space unit normals `(H, W, 3)`, zero on sky, if rendered.
        object_id: index of the object seen in each pixel, `-1` on sky, if rendered.
        light_pass: seed 004's pass (the light white, everything else black),
            `(H, W)`, if rendered.
        glow_pass: seed 000's overcast pass (the source enlarged and tinted,
            occluders shrunk and transparent black), `(H, W, 4)` RGBA, if rendered.
    """

    color: Float[Array, "H W C"]
    depth: Float[Array, "H W"]
    coverage: Float[Array, "H W"]
    normal: Float[Array, "H W 3"] | None = None
    object_id: Int[Array, "H W"] | None = None
    light_pass: Float[Array, "H W"] | None = None
    glow_pass: Float[Array, "H W 4"] | None = None

    @property
    def height(self) -> int:
        return self.color.shape[-3]

    @property
    def width(self) -> int:
        return self.color.shape[-2]


def coverage_from_depth(depth: Float[Array, "H W"]) -> Float[Array, "H W"]:
    """Hard coverage for buffers that carry none: 1 where depth is finite, 0 on sky."""
    return jnp.isfinite(depth).astype(jnp.result_type(depth, jnp.float32))
