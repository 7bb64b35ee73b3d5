"""Pinhole camera and the projection of world points to pixel coordinates.

Conventions (shared by the rasterizer and every effect): right-handed world,
pixel x to the right, y down, pixel centres at `i + 0.5`, square pixels; the
horizontal field of view fixes the focal length `f = (width / 2) / tan(fov_x / 2)`
in pixels.

Depth kinds (`DEPTH_KINDS`): renderers write a pixel's depth either as the
distance along its camera ray (`"ray"`: Mitsuba, `render`) or as the distance
along the camera's axis (`"planar"`, view-space z: Blender's Cycles `Z` pass,
hardware depth buffers). The two differ by the length of the pixel's
direction `((x - W/2) / f, (H/2 - y) / f, 1)`: 1 at the centre, growing toward
the corners (`ray_depth_scale`).
"""

from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike
from jaxtyping import Array, ArrayLike, Bool, Float

from godrays_jax.primitives.sampling import pixel_centres

# Points this close to the camera plane (in scene units) are projected as if
# they were this far, so that projection stays finite.
_MIN_PROJECTION_DEPTH = 1e-6


def focal_length_px(width: int, fov_x_deg: Float[ArrayLike, ""], dtype: DTypeLike = jnp.float32) -> Float[Array, ""]:
    """The pinhole focal length in pixels of a frame `width` pixels wide: `(W / 2) / tan(fov_x / 2)`."""
    return 0.5 * width / jnp.tan(jnp.deg2rad(jnp.asarray(fov_x_deg, dtype)) / 2)


DepthKind = Literal["ray", "planar"]
DEPTH_KINDS: tuple[str, ...] = ("ray", "planar")
"""How a depth buffer measures distance: along each pixel's camera ray, or along the camera's axis (view-space z)."""


def ray_depth_scale(
    height: int, width: int, *, fov_x_deg: Float[ArrayLike, ""], dtype: DTypeLike = jnp.float32
) -> Float[Array, "H W"]:
    """Distance along each pixel-centre ray per unit of distance along the camera's axis, `(H, W)`, >= 1.

    `sqrt(1 + ((x - W/2) / f)^2 + ((H/2 - y) / f)^2)` with `f` the focal
    length in pixels of the horizontal field of view `fov_x_deg` (degrees, in
    (0, 180)). Differentiable in `fov_x_deg`.
    """
    focal = focal_length_px(width, fov_x_deg, dtype)
    x, y = pixel_centres(height, width, dtype)
    return jnp.sqrt(1.0 + ((x - 0.5 * width) / focal) ** 2 + ((0.5 * height - y) / focal) ** 2)


def planar_to_ray_depth(depth: Float[ArrayLike, "H W"], *, fov_x_deg: Float[ArrayLike, ""]) -> Float[Array, "H W"]:
    """Planar depth (along the camera's axis, scene units) as distance along each pixel's ray.

    `depth * ray_depth_scale(...)`; `+inf` (sky) stays `+inf`. Differentiable
    in `depth` and `fov_x_deg` (finite gradients on sky too).
    """
    depth = jnp.asarray(depth)
    if depth.ndim != 2:
        raise ValueError(f"depth must have shape (H, W), got {depth.shape}")
    dtype = jnp.result_type(depth, jnp.float32)
    scale = ray_depth_scale(depth.shape[0], depth.shape[1], fov_x_deg=fov_x_deg, dtype=dtype)
    sky = jnp.isposinf(depth)
    return jnp.where(sky, jnp.inf, jnp.where(sky, 0.0, depth) * scale)


def unit_vectors(vectors: Float[Array, "*S"], *, axis: int = -1) -> Float[Array, "*S"]:
    """`vectors` scaled to length 1 along `axis` (a zero vector stays finite: its length is floored)."""
    squared = jnp.sum(vectors * vectors, axis=axis, keepdims=True)
    return vectors * jax.lax.rsqrt(jnp.maximum(squared, 1e-24))


def _as_float_array(value: ArrayLike) -> Array:
    return jnp.asarray(value, dtype=jnp.float32)


def _is_concrete(*values) -> bool:
    return not any(isinstance(v, jax.core.Tracer) for v in values)


class Camera(eqx.Module):
    """A pinhole camera looking from `position` at `target`.

    Attributes:
        position: camera centre in world units, shape (3,).
        target: a point the optical axis passes through, shape (3,).
        up: approximate up direction, shape (3,); must not be parallel to the
            viewing direction.
        fov_x_deg: horizontal field of view in degrees, in (0, 180); fittable.
        width, height: image size in pixels (static Python ints).
        near, far: clipping distances along the optical axis, `0 < near < far`;
            geometry outside [near, far] is not drawn.
    """

    position: Float[Array, "3"] = eqx.field(converter=_as_float_array)
    target: Float[Array, "3"] = eqx.field(converter=_as_float_array)
    up: Float[Array, "3"] = eqx.field(converter=_as_float_array)
    fov_x_deg: Float[Array, ""] = eqx.field(converter=_as_float_array)
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)
    near: Float[Array, ""] = eqx.field(converter=_as_float_array, default=0.01)
    far: Float[Array, ""] = eqx.field(converter=_as_float_array, default=1e4)

    def __check_init__(self):
        for name in ("position", "target", "up"):
            if getattr(self, name).shape != (3,):
                raise ValueError(f"Camera.{name} must have shape (3,), got {getattr(self, name).shape}")
        for name in ("fov_x_deg", "near", "far"):
            if getattr(self, name).shape != ():
                raise ValueError(f"Camera.{name} must be a scalar, got shape {getattr(self, name).shape}")
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"Camera.{name} must be a positive int, got {value!r}")
        if not _is_concrete(self.position, self.target, self.up, self.fov_x_deg, self.near, self.far):
            return
        forward = np.asarray(self.target, np.float64) - np.asarray(self.position, np.float64)
        up = np.asarray(self.up, np.float64)
        if np.linalg.norm(forward) == 0:
            raise ValueError("Camera.target must differ from Camera.position")
        if np.linalg.norm(up) == 0:
            raise ValueError("Camera.up must be non-zero")
        sine = np.linalg.norm(np.cross(forward, up)) / (np.linalg.norm(forward) * np.linalg.norm(up))
        if sine < 1e-6:
            raise ValueError("Camera.up is parallel to the viewing direction (target - position)")
        if not 0 < float(self.fov_x_deg) < 180:
            raise ValueError(f"Camera.fov_x_deg must be in (0, 180), got {float(self.fov_x_deg)}")
        if not 0 < float(self.near) < float(self.far):
            raise ValueError(f"Camera.near and Camera.far must satisfy 0 < near < far, got {float(self.near)}, {float(self.far)}")

    @property
    def focal_px(self) -> Float[Array, ""]:
        """Focal length in pixels."""
        return focal_length_px(self.width, self.fov_x_deg)

    def basis(self) -> tuple[Float[Array, "3"], Float[Array, "3"], Float[Array, "3"]]:
        """Orthonormal (right, up, forward) world vectors of the view."""
        forward = self.target - self.position
        forward = forward / jnp.linalg.norm(forward)
        right = jnp.cross(forward, self.up)
        right = right / jnp.linalg.norm(right)
        return right, jnp.cross(right, forward), forward

    def to_view(self, points: Float[Array, "*N 3"]) -> Float[Array, "*N 3"]:
        """World points to view coordinates (x right, y up, z forward), scene units."""
        right, up, forward = self.basis()
        return jnp.matmul(points - self.position, jnp.stack([right, up, forward], axis=1), precision="highest")

    def ray_directions(self) -> Float[Array, "H W 3"]:
        """View-space directions through every pixel centre, scaled so the
        forward component is 1 (a point at `t * d` has view depth `t`)."""
        x = (jnp.arange(self.width, dtype=jnp.float32) + 0.5 - 0.5 * self.width) / self.focal_px
        y = (0.5 * self.height - jnp.arange(self.height, dtype=jnp.float32) - 0.5) / self.focal_px
        xx, yy = jnp.meshgrid(x, y)
        return jnp.stack([xx, yy, jnp.ones_like(xx)], axis=-1)


def project_point(
    camera: Camera, point: Float[Array, "3"]
) -> tuple[Float[Array, "2"], Float[Array, ""], Bool[Array, ""]]:
    """Project a world point to pixel coordinates.

    Returns:
        xy: pixel coordinates (x right, y down, pixel centres at `i + 0.5`);
            any real value, on screen or off it.
        view_depth: distance along the optical axis in scene units; negative
            behind the camera.
        in_front: whether `view_depth > 0`.

    A point behind the camera (or on its plane) is projected through its
    mirror image in the camera plane, i.e. where the point's direction would
    appear if it were in front; the result is always finite and `in_front` is
    False. Accepts leading batch dimensions on `point` (`(..., 3)`).
    """
    point = jnp.asarray(point, dtype=jnp.float32)
    if point.shape[-1:] != (3,):
        raise ValueError(f"project_point: point must have shape (..., 3), got {point.shape}")
    view = camera.to_view(point)
    view_depth = view[..., 2]
    safe_depth = jnp.maximum(jnp.abs(view_depth), _MIN_PROJECTION_DEPTH)
    scale = camera.focal_px / safe_depth
    xy = jnp.stack(
        [0.5 * camera.width + view[..., 0] * scale, 0.5 * camera.height - view[..., 1] * scale],
        axis=-1,
    )
    return xy, view_depth, view_depth > 0
