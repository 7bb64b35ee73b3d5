"""A depth map seen from the light (a shadow map) and its camera: what casts shadows outside the frame.

The frame's depth buffer knows only what the frame shows. A renderer can also
write the depth seen from the light: for the sun an orthographic view along
its direction, for a point light a perspective view from it. `LightView`
holds that map and where its camera stands relative to the frame's camera;
`kernels.light_view_shadows` reads it. Both cameras' view spaces follow the
library's convention: origin at the camera, x right, y up, z forward (the
direction it looks), scene units. docs/file_formats.md ("A depth map seen from
the light") has the file and how Blender and Mitsuba render it.
"""

from typing import Literal

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

Projection = Literal["orthographic", "perspective"]
PROJECTIONS: tuple[str, ...] = ("orthographic", "perspective")


class LightView(eqx.Module):
    """A depth map seen from the light and its camera.

    Attributes:
        depth: `(h, w)`, each pixel's distance along the light camera's forward
            axis (z) to the first surface it sees, scene units; `+inf` where it
            sees none. An orthographic map measures it from its image plane, a
            perspective one from its centre.
        from_camera: `(3, 4)`, `[R | t]`: a point `X` of the frame camera's
            view space is `R @ X + t` in the light camera's.
        scale: orthographic, pixels per scene unit; perspective, the focal
            length in pixels. The map's centre is its principal point: a point
            `(x, y, z)` of the light's view space falls on the map's pixel
            `(w / 2 + scale * x, h / 2 - scale * y)` (orthographic; perspective:
            `x / z`, `y / z`), x right, y down, pixel centres at `i + 0.5`.
        projection: `"orthographic"` (the sun) or `"perspective"` (a point
            light, one view of its surroundings), static.

    Leading batch axes are allowed (stacked frames for `jax.vmap`), the same on
    every field.
    """

    depth: Float[Array, "h w"]
    from_camera: Float[Array, "3 4"]
    scale: Float[ArrayLike, ""]
    projection: Projection = eqx.field(static=True, default="orthographic")

    def __check_init__(self):
        if self.projection not in PROJECTIONS:
            raise ValueError(f"light_view.projection must be one of {', '.join(PROJECTIONS)}, got {self.projection!r}")
        depth_shape, transform_shape = getattr(self.depth, "shape", None), getattr(self.from_camera, "shape", None)
        if depth_shape is None or transform_shape is None:
            return  # a filter spec or other non-array pytree (e.g. for eqx.partition)
        if len(depth_shape) < 2 or min(depth_shape[-2:]) < 1:
            raise ValueError(f"light_view.depth must have shape (h, w), got {tuple(depth_shape)}")
        if tuple(transform_shape[-2:]) != (3, 4) or tuple(transform_shape[:-2]) != tuple(depth_shape[:-2]):
            raise ValueError(
                f"light_view.from_camera must have shape {(*depth_shape[:-2], 3, 4)} ([R | t]), "
                f"got {tuple(transform_shape)}"
            )

    def project(
        self, points: Float[Array, "*S 3"]
    ) -> tuple[Float[Array, "*S"], Float[Array, "*S"], Float[Array, "*S"], Float[Array, "*S"]]:
        """`(x, y, z, footprint)` of points of the frame camera's view space: their position on the map (pixels,
        any real value: off the map beyond `[0, w] x [0, h]`), their depth along the light camera's axis (scene
        units; <= 0 behind a perspective map's centre) and the scene units one pixel of the map spans there."""
        height, width = self.depth.shape[-2:]
        rotation, shift = self.from_camera[:, :3], self.from_camera[:, 3]
        seen = jnp.einsum("ij,...j->...i", rotation, points) + shift
        lx, ly, lz = seen[..., 0], seen[..., 1], seen[..., 2]
        scale = jnp.asarray(self.scale, seen.dtype)
        if self.projection == "orthographic":
            return 0.5 * width + scale * lx, 0.5 * height - scale * ly, lz, jnp.broadcast_to(1.0 / scale, lz.shape)
        ahead = jnp.maximum(lz, 1e-6)  # behind the centre the position means nothing: the reader ignores it there
        return 0.5 * width + scale * lx / ahead, 0.5 * height - scale * ly / ahead, lz, ahead / scale
