"""Each view segment's visibility of the light, read from the depth buffer at samples along the screen toward it.

The shadow ray from a point on pixel `p`'s view ray toward the light crosses the camera rays of the pixels on the
screen segment from `p` toward the light's position; at each of `num_shadow_samples` samples `q` on it, in closed
form, the depths it runs through since the previous sample meet `q`'s slab `[D_q, D_q * (1 + thickness)]` or not
(soft faces `edge_softness * D_q` wide; the test at the four texels around `q`, by bilinear weights). Where the
screen segment leaves the screen (a light in front, off screen) its last sample is where the shadow ray leaves:
in a frame read as closed beyond its edges (`enclosed`, `shadow_reading.enclosure`) the slab there reaches toward
the eye (at `enclosed = 1` to it), so that a shadow ray leaving in front of the surface seen there is shaded.
`volumetric`'s module docstring has the model; `shadow_lines` reads the same test along lines through the light.
"""

import functools
import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from godrays_jax.kernels.bounded_medium import dot, light_geometry, safe_divide
from godrays_jax.kernels.lens import rays_through
from godrays_jax.primitives.camera import focal_length_px
from godrays_jax.primitives.checks import check_light, check_scalar, is_static_int
from godrays_jax.primitives.sampling import bilinear_corners

# The sun's distance where a shadow ray reaches it, finite so that gradients stay finite.
_BEYOND_EVERY_SLAB = 1e30


def _ramp(x):
    return jnp.clip(x, 0.0, 1.0)


@functools.partial(jax.jit, static_argnums=14)
def _shadow_march(depth, pixel_xy, distances, step, reach, view_cross_light, view, toward, inverse, in_front, focal,
                  thickness, softness, enclosed, num_shadow_samples):  # fmt: skip
    """`segment_visibility`'s loop over the shadow samples, compiled once per shape and count: called eagerly, a
    loop over a function defined in the call would be traced and compiled again on every call."""
    height, width = depth.shape
    dtype = depth.dtype

    def sample(carry, k):
        visibility, previous = carry
        s = reach * jnp.minimum((k + 0.5) / num_shadow_samples, 1.0)
        q = pixel_xy + s[..., None] * step
        ray = rays_through(q[..., 0], q[..., 1], height, width, focal)
        ray_cross_light, ray_cross_view = jnp.cross(ray, toward), jnp.cross(ray, view)
        # mu' * ray = X + u (S - X), X = t * view, S = toward / inverse: crossed with (S - X), in t.
        a1 = dot(view_cross_light, ray_cross_light)[..., None]
        a2 = dot(view_cross_light, ray_cross_view)[..., None] * inverse
        b1 = dot(ray_cross_light, ray_cross_light)[..., None]
        b2 = dot(ray_cross_light, ray_cross_view)[..., None] * inverse
        b3 = dot(ray_cross_view, ray_cross_view)[..., None] * inverse * inverse
        t = distances
        numerator = t * a1 - t * t * a2
        denominator = b1 - 2 * t * b2 + t * t * b3
        # A shadow ray parallel to q's camera ray runs along it (q's ray is the point's own, toward the light):
        # from the point itself on.
        crossing = safe_divide(numerator * jnp.linalg.norm(ray, axis=-1)[..., None], denominator, t, tiny=1e-12)
        # The last sample is the light's own pixel when it is on screen: every shadow ray ends there, at the
        # light's distance (the sun's: beyond every slab).
        at_light = (k == num_shadow_samples) & in_front & (reach[..., None] >= 1.0)
        crossing = jnp.where(at_light, safe_divide(1.0, inverse, _BEYOND_EVERY_SLAB), crossing)
        # The shadow ray covers every depth between its crossings of this sample's camera ray and the previous
        # one's: near the light's screen position each step moves it far in depth, and a slab it passes
        # between two samples still blocks it. (A crossing behind the camera, or none, is taken alone.)
        both = (crossing > 0) & (previous > 0)
        nearest = jnp.where(both, jnp.minimum(crossing, previous), crossing)
        farthest = jnp.where(both, jnp.maximum(crossing, previous), crossing)
        # The slab test at the four texels around q, blended with bilinear weights: visibility moves smoothly
        # as q moves under the pixel grid (a pan, a light moved by a fraction of a pixel).
        row, col, weight = bilinear_corners(q[..., 0] - 0.5, q[..., 1] - 0.5, height, width)
        front = depth[row, col][..., None]
        # Sky, the emitter (a slab reaching the light), a surface at the eye (a slab of no depth) and the pixel's
        # own start block nothing.
        blocks = jnp.isfinite(front) & (front > 0) & (front * (1 + thickness) * inverse < 1.0) & (reach[..., None] > 0)
        front = jnp.where(blocks, front, 1.0)
        soft = softness * front
        # The last sample of a segment cut at the screen's edge, toward a light in front: where the ray leaves.
        leaves = (k == num_shadow_samples) & in_front & (reach[..., None] < 1.0)
        near_face = jnp.where(leaves, 1.0 - enclosed, 1.0) * front
        inside_slab = _ramp((farthest - near_face) / soft) * _ramp((front * (1 + thickness) - nearest) / soft)
        inside = jnp.sum(weight[..., None] * jnp.where(blocks, inside_slab, 0.0), axis=0)
        return (jnp.minimum(visibility, 1.0 - inside), crossing), None

    # At the pixel itself the shadow ray crosses the pixel's camera ray at the point's own distance.
    (visibility, _), _ = jax.lax.scan(
        jax.checkpoint(sample), (jnp.ones(distances.shape, dtype), distances),
        jnp.arange(num_shadow_samples + 1, dtype=dtype),
    )  # fmt: skip
    return visibility


def segment_visibility(
    depth: Float[Array, "H W"],
    light_xy: Float[ArrayLike, "2"],
    pixel_xy: Float[Array, "h w 2"],
    distances: Float[Array, "h w M"],
    *,
    fov_x_deg: Float[ArrayLike, ""],
    light_depth: Float[ArrayLike, ""] = math.inf,
    light_in_front: Bool[ArrayLike, ""] | bool = True,
    thickness: Float[ArrayLike, ""],
    edge_softness: Float[ArrayLike, ""],
    num_shadow_samples: int,
    enclosed: Float[ArrayLike, ""] = 0.0,
) -> Float[Array, "h w M"]:
    """How much of the light reaches the points `distances` along the view rays through `pixel_xy`, in [0, 1].

    Args:
        depth: the frame's distance along each camera ray, scene units, `+inf` on sky.
        light_xy: the light's projected position in pixels (mirrored through the
            camera plane when behind it, as `camera.project_point`), any real value.
        pixel_xy: the pixel positions whose view rays are tested (x right, y down,
            pixel centres at `i + 0.5`), on screen or near it (a ray whose screen
            segment leaves the screen at once reads nothing).
        distances: distances along those rays (scene units) of the points tested.
        fov_x_deg: horizontal field of view in degrees, in (0, 180).
        light_depth: the light's distance along its camera ray, scene units; `inf`: the sun.
        light_in_front: whether the light is in front of the camera.
        thickness: each surface's slab depth as a fraction of its own depth, >= 0.
        edge_softness: the width of the slab's soft faces, a fraction of depth, > 0.
        num_shadow_samples: depth samples along the screen segment (static int, >= 1), besides
            the one at its end.
        enclosed: how closed the frame is beyond its edges, in [0, 1] (`shadow_reading.enclosure`): 0, texels
            off screen block nothing; 1, a shadow ray toward a light in front of the camera that leaves the
            screen in front of the far face of the surface seen where it leaves is shaded. No gradient.

    The loop runs over the samples, so memory is that of `distances` whatever
    `num_shadow_samples` is.
    """
    if not is_static_int(num_shadow_samples) or num_shadow_samples < 1:
        raise ValueError(f"num_shadow_samples must be a Python int >= 1, got {num_shadow_samples!r}")
    if jnp.ndim(depth) != 2:
        raise ValueError(f"depth must have shape (H, W), got shape {jnp.shape(depth)}")
    light_xy = check_light(light_xy)
    for name, value in (("fov_x_deg", fov_x_deg), ("light_depth", light_depth), ("thickness", thickness),
                        ("edge_softness", edge_softness), ("enclosed", enclosed)):  # fmt: skip
        check_scalar(value, name)
    if jnp.ndim(pixel_xy) != 3 or jnp.shape(pixel_xy)[-1] != 2:
        raise ValueError(f"pixel_xy must have shape (h, w, 2), got shape {jnp.shape(pixel_xy)}")
    if jnp.ndim(distances) != 3 or jnp.shape(distances)[:2] != jnp.shape(pixel_xy)[:2]:
        raise ValueError(f"distances must have shape (h, w, M) matching pixel_xy, got shape {jnp.shape(distances)}")
    height, width = depth.shape
    dtype = jnp.result_type(depth, jnp.float32)
    depth = jnp.asarray(depth, dtype)
    pixel_xy = jnp.asarray(pixel_xy, dtype)
    distances = jnp.asarray(distances, dtype)
    focal = focal_length_px(width, fov_x_deg, dtype)
    toward, inverse = light_geometry(light_xy, height, width, fov_x_deg, light_depth, light_in_front, dtype)
    light_xy = jnp.asarray(light_xy, dtype)
    in_front = jnp.asarray(light_in_front)
    # Behind the camera the shadow ray runs from p away from the light's true projection (the point
    # reflection of light_xy through the image centre) until it crosses the camera plane.
    centre = jnp.asarray([0.5 * width, 0.5 * height], dtype)
    step = jnp.where(in_front, light_xy - pixel_xy, pixel_xy - (2 * centre - light_xy))
    # A step this short along an axis (a light a vanishing fraction of a pixel off a ray's row or column) counts
    # as none: its exit's derivative, -exit / step, would overflow even where the other axis's exit is taken.
    along = [jnp.abs(step[..., axis]) < 1e-12 for axis in (0, 1)]
    exits = [
        jnp.where(step[..., axis] > 0, (limit - pixel_xy[..., axis]), -pixel_xy[..., axis])
        / jnp.where(along[axis], 1.0, step[..., axis])
        for axis, limit in ((0, width), (1, height))
    ]
    exits = [jnp.where(along[axis], jnp.inf, e) for axis, e in enumerate(exits)]
    reach = jnp.minimum(exits[0], exits[1])
    reach = jnp.where(in_front, jnp.minimum(reach, 1.0), reach)
    reach = jnp.where(jnp.isfinite(reach), jnp.maximum(reach, 0.0), 0.0)
    view = rays_through(pixel_xy[..., 0], pixel_xy[..., 1], height, width, focal)
    view = view / jnp.linalg.norm(view, axis=-1, keepdims=True)
    view_cross_light = jnp.cross(view, toward)
    thickness = jnp.asarray(thickness, dtype)
    softness = jnp.maximum(jnp.asarray(edge_softness, dtype), 1e-6)
    enclosed = jax.lax.stop_gradient(jnp.asarray(enclosed, dtype))

    return _shadow_march(
        depth, pixel_xy, distances, step, reach, view_cross_light, view, toward, inverse, in_front, focal, thickness,
        softness, enclosed, num_shadow_samples,
    )  # fmt: skip
