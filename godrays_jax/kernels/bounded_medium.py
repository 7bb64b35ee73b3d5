"""A bounded medium's closed forms: where a ray runs inside it, its optical depth, the light that reaches a point.

The medium fills a sphere of radius `max_distance` around the camera; its
extinction is `extinction * exp(-height_falloff * y)` (`y` the height above
the camera along its up axis, scene units: engines' height fog) below
`layer_top` (scene units above the camera, `inf`: no top). The light is the
point `S = light_depth * d_L` (`d_L` = `lens.light_direction`) or, for
`light_depth = inf`, the sun in direction `d_L`. Distances are in scene units,
points camera-space (y up). Everything is finite with finite gradients, also
on sky (`inf`), for the sun and for a light at the camera.
"""

import math
import numbers

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from godrays_jax.kernels.lens import light_direction
from godrays_jax.primitives.checks import check_scalar

# exp() arguments are clipped here: a height falloff that would make the medium e^60 times denser than at
# the camera is outside any fog, and float32 overflows near e^88.
_MAX_EXPONENT = 60.0
# A point light's irradiance is floored as if it were a ball of this fraction of its distance.
_POINT_LIGHT_RADIUS = 1e-3


class BoundedMedium(eqx.Module):
    """The medium the module's docstring describes, as `volumetric.volumetric_fog_terms` takes it.

    `extinction` per scene unit at the camera's height (>= 0); `max_distance`
    the sphere's radius (scene units); `anisotropy` the Henyey-Greenstein `g`
    of its phase function, in (-1, 1); `height_falloff` per scene unit (>= 0,
    0: homogeneous in height); `layer_top` scene units above the camera
    (negative: the camera above the layer; `inf`: no top). Scalars, each
    traceable and differentiable.
    """

    extinction: Float[ArrayLike, ""]
    max_distance: Float[ArrayLike, ""]
    anisotropy: Float[ArrayLike, ""]
    height_falloff: Float[ArrayLike, ""] = 0.0
    layer_top: Float[ArrayLike, ""] = math.inf

    def __check_init__(self):
        for name in ("extinction", "max_distance", "anisotropy", "height_falloff", "layer_top"):
            check_scalar(getattr(self, name), name)

    @property
    def density(self) -> dict:
        """The fields that give the extinction at a point: `optical_depth`'s and `light_transmittance`'s keywords."""
        return dict(extinction=self.extinction, height_falloff=self.height_falloff)

    @property
    def extent(self) -> dict:
        """The fields that bound the medium: `medium_interval`'s and `light_transmittance`'s keywords."""
        return dict(max_distance=self.max_distance, layer_top=self.layer_top)


def safe_divide(numerator, denominator, fallback, tiny=1e-20):
    ok = jnp.abs(denominator) > tiny
    return jnp.where(ok, numerator / jnp.where(ok, denominator, 1.0), fallback)


def exp_ratio(x):
    """`(1 - exp(-x)) / x`, 1 at 0, finite with finite gradients everywhere (x clipped at -`_MAX_EXPONENT`)."""
    x = jnp.maximum(x, -_MAX_EXPONENT)
    small = jnp.abs(x) < 1e-3
    safe = jnp.where(small, 1.0, x)
    return jnp.where(small, 1.0 - x / 2 + x * x / 6, -jnp.expm1(-safe) / safe)


def dot(a, b):
    return jnp.sum(a * b, axis=-1)


def medium_interval(
    origin: Float[Array, "*S 3"],
    direction: Float[Array, "*S 3"],
    length: Float[ArrayLike, "*S"],
    *,
    max_distance: Float[ArrayLike, ""],
    layer_top: Float[ArrayLike, ""] = math.inf,
) -> tuple[Float[Array, "*S"], Float[Array, "*S"]]:
    """`(start, end)` of the part of the ray `origin + u * direction`, `u` in `[0, length]`, inside the medium.

    The medium is the ball of radius `max_distance` around the camera (the
    origin) below `layer_top` (height above the camera along its up axis,
    scene units; `inf`: no top). `direction` is a unit vector; distances are in
    scene units; an empty intersection gives `start == end`.
    """
    dtype = origin.dtype
    radius = jnp.asarray(max_distance, dtype)
    top = jnp.asarray(layer_top, dtype)
    along = dot(origin, direction)
    discriminant = along * along - dot(origin, origin) + radius * radius
    inside_ball = discriminant > 0
    # The square root's derivative is infinite at 0: taken only where the ray meets the ball (else NaN gradients
    # for points outside it, a surface beyond `max_distance`).
    root = jnp.where(inside_ball, jnp.sqrt(jnp.where(inside_ball, discriminant, 1.0)), 0.0)
    start = jnp.where(inside_ball, jnp.maximum(-along - root, 0.0), 0.0)
    end = jnp.where(inside_ball, jnp.minimum(-along + root, length), 0.0)
    height, rise = origin[..., 1], direction[..., 1]
    # The height crosses layer_top at u = (top - height) / rise: below it on one side only. Without a top the
    # crossing is computed from 0 and never selected: an infinite numerator would make its gradient NaN.
    finite_top = jnp.isfinite(top)
    crossing = safe_divide(jnp.where(finite_top, top, 0.0) - height, rise, jnp.inf)
    below_now = height < top
    start = jnp.where(finite_top & (rise < 0) & ~below_now, jnp.maximum(start, crossing), start)
    end = jnp.where(finite_top & (rise > 0) & below_now, jnp.minimum(end, crossing), end)
    end = jnp.where(finite_top & (rise >= 0) & ~below_now, start, end)
    return start, jnp.maximum(end, start)


def optical_depth(
    origin: Float[Array, "*S 3"],
    direction: Float[Array, "*S 3"],
    start: Float[ArrayLike, "*S"],
    end: Float[ArrayLike, "*S"],
    *,
    extinction: Float[ArrayLike, ""],
    height_falloff: Float[ArrayLike, ""] = 0.0,
) -> Float[Array, "*S"]:
    """`integral_start^end extinction * exp(-height_falloff * y(u)) du` along `origin + u * direction`.

    `y` is the height above the camera (the origin's frame, y up), scene units;
    `extinction` per scene unit at the camera's height, `height_falloff` per
    scene unit (0: homogeneous). Closed form: `exp(-b * y(start)) * (end -
    start) * (1 - exp(-x)) / x` with `x = b * rise * (end - start)`.
    """
    dtype = origin.dtype
    falloff = jnp.asarray(height_falloff, dtype)
    start = jnp.asarray(start, dtype)
    length = jnp.asarray(end, dtype) - start
    height = origin[..., 1] + start * direction[..., 1]
    density = jnp.exp(jnp.clip(-falloff * height, -_MAX_EXPONENT, _MAX_EXPONENT))
    return jnp.asarray(extinction, dtype) * density * length * exp_ratio(falloff * direction[..., 1] * length)


def scattering_height(
    direction: Float[Array, "*S 3"],
    start: Float[ArrayLike, "*S"],
    end: Float[ArrayLike, "*S"],
    tau: Float[ArrayLike, "*S"],
) -> Float[Array, "*S"]:
    """`integral_start^end sigma * T(u) * y(u) du` along the camera ray `u * direction`, in a homogeneous medium.

    The height above the camera (`y(u) = u * direction[1]`, scene units) of
    the ray's scattering, each point weighted by its share `sigma * T(u)`,
    `T(u) = exp(-sigma * (u - start))`, for the `sigma` that gives the optical
    depth `tau` from `start` to `end` (scene units; a medium that falls off
    with height is taken as the homogeneous one of the same optical depth).
    Closed form: `direction[1] * (start * (1 - exp(-tau)) + (end - start) * (1 - exp(-tau) * (1 + tau)) / tau)`.
    """
    dtype = direction.dtype
    start = jnp.asarray(start, dtype)
    length = jnp.asarray(end, dtype) - start
    tau = jnp.maximum(jnp.asarray(tau, dtype), 0.0)
    # (1 - exp(-x) (1 + x)) / x, by its series where the difference of two near-equal terms would lose float32's digits.
    small = tau < 1e-2
    x = jnp.where(small, 1.0, tau)
    mean = jnp.where(small, tau / 2 - tau * tau / 3 + tau**3 / 8, (-jnp.expm1(-x) - x * jnp.exp(-x)) / x)
    return direction[..., 1] * (start * -jnp.expm1(-tau) + length * mean)


def is_static_sun(light_depth) -> bool:
    """Whether `light_depth` is the sun (`+inf`) known when the program is traced (a Python or NumPy number)."""
    return isinstance(light_depth, numbers.Real) and light_depth == math.inf


def light_geometry(light_xy, height, width, fov_x_deg, light_depth, light_in_front, dtype):
    """The unit direction toward the light and `1 / light_depth` (0 for the sun). A sun given as a Python number
    (`math.inf`) gives a Python 0: every point light's branch then drops out of the compiled program."""
    toward = light_direction(light_xy, height, width, fov_x_deg=fov_x_deg, light_in_front=light_in_front, dtype=dtype)
    if is_static_sun(light_depth):
        return toward, 0.0
    light_depth = jnp.asarray(light_depth, dtype)
    inverse = jnp.where(jnp.isfinite(light_depth), 1.0 / jnp.where(jnp.isfinite(light_depth), light_depth, 1.0), 0.0)
    return toward, inverse


def toward_light(points, toward, inverse_depth):
    """Unit direction from each point toward the light, and the distance to it (`inf` for the sun)."""
    finite = inverse_depth > 0
    light_point = toward * safe_divide(1.0, inverse_depth, 0.0)
    # The sun's branch never divides: a far off-screen sun's direction is tiny where float32 overflows.
    offset = jnp.where(finite, light_point - points, 1.0)
    distance = jnp.sqrt(jnp.maximum(dot(offset, offset), 1e-30))
    direction = jnp.where(finite, offset / distance[..., None], toward)
    return direction, jnp.where(finite, distance, jnp.inf)


def light_transmittance(
    points: Float[Array, "*S 3"],
    light_toward: Float[Array, "3"],
    *,
    light_depth: Float[ArrayLike, ""],
    extinction: Float[ArrayLike, ""],
    max_distance: Float[ArrayLike, ""],
    height_falloff: Float[ArrayLike, ""] = 0.0,
    layer_top: Float[ArrayLike, ""] = math.inf,
) -> Float[Array, "*S"]:
    """The fraction of the light that reaches each point (camera-space, scene units) through the medium.

    `light_toward` is the unit direction from the camera to the light, the
    light at `light_depth` along it (`inf`: the sun). A light inside the
    medium is dimmed only over its distance to the point.
    """
    dtype = points.dtype
    inverse = jnp.where(jnp.isfinite(light_depth), 1.0 / jnp.where(jnp.isfinite(light_depth), light_depth, 1.0), 0.0)
    direction, distance = toward_light(points, jnp.asarray(light_toward, dtype), jnp.asarray(inverse, dtype))
    start, end = medium_interval(points, direction, distance, max_distance=max_distance, layer_top=layer_top)
    depth = optical_depth(points, direction, start, end, extinction=extinction, height_falloff=height_falloff)
    return jnp.exp(-depth)


def light_approach(view, toward, inverse):
    """Where the ray `t * view` passes closest to a point light at `S = toward / inverse` (`along`, scene units)
    and how close (`miss`, floored by the light's own size); for the sun (`inverse` 0) the light at distance 1.
    """
    cosine = dot(view, toward)
    light_depth = safe_divide(1.0, inverse, 1.0)
    miss = jnp.sqrt(jnp.maximum(light_depth**2 * (1.0 - cosine * cosine), 0.0) + (_POINT_LIGHT_RADIUS * light_depth) ** 2)
    return light_depth * cosine, miss


def irradiance_coordinate(distance, along, miss, inverse):
    """A coordinate along a view ray in which a point light's irradiance `(light_depth / |S - t * view|)^2` is
    even (the ray's `light_approach`): `arctan((t - along) / miss)`; for the sun (`inverse` 0) `t` itself."""
    return jnp.where(inverse > 0, jnp.arctan((distance - along) / miss), distance)


def light_cosine(coordinate, miss, inverse):
    """The cosine of the angle between a view ray and the direction to a point light, from the ray's point at
    `irradiance_coordinate` `coordinate` (the ray's `light_approach` `miss`; 1 looking at the light). The angle is
    the point's own: `miss` also holds the floor on the light's size, which the angle does not take."""
    light_depth = safe_divide(1.0, inverse, 1.0)
    across = jnp.maximum(miss * miss - (_POINT_LIGHT_RADIUS * light_depth) ** 2, 0.0)  # the ray's own miss, squared
    # (t - along) / |S - t * view| with t - along = miss * tan(coordinate), times cos(coordinate) > 0 above and below.
    offset = miss * jnp.sin(coordinate)
    return -offset / jnp.sqrt(jnp.maximum(offset * offset + across * jnp.cos(coordinate) ** 2, 1e-30))


def irradiance_median(start, end, along, miss, inverse):
    """The distance along a view ray that halves the light's irradiance over `[start, end]` (the ray's
    `light_approach`): where a segment's light comes from, the geometric middle for the sun."""
    middle = 0.5 * (irradiance_coordinate(start, along, miss, inverse) + irradiance_coordinate(end, along, miss, inverse))
    return jnp.where(inverse > 0, along + miss * jnp.tan(middle), middle)


def segment_irradiance(view, start, end, toward, inverse):
    """The mean over `[start, end]` of `(light_depth / |S - t * view|)^2` (1 for the sun)."""
    light_depth = safe_divide(1.0, inverse, 1.0)
    along, miss = (value[..., None] for value in light_approach(view, toward, inverse))
    integral = (jnp.arctan((end - along) / miss) - jnp.arctan((start - along) / miss)) / miss
    middle = 0.5 * (start + end) - along
    at_middle = light_depth**2 / (middle * middle + miss * miss)
    mean = safe_divide(light_depth**2 * integral, end - start, at_middle, tiny=1e-9)
    return jnp.where(inverse > 0, mean, 1.0)
