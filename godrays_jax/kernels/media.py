"""Participating media in screen space: extinction and single in-scattering of a homogeneous fog.

Along a camera ray through a homogeneous medium (extinction coefficient
`sigma_t` per scene unit), the radiance reaching the camera from a surface at
distance `d` is

    L = L_surface * T + (1 - T) * (ambient_color + light_color * p(cos theta) * lit),
    T = exp(-sigma_t * min(d, max_distance)),

the closed form of the single-scattering integral when the medium is lit
uniformly: `ambient_color` is the isotropic in-scattered radiance (albedo times the
sky's radiance), `light_color` the albedo times the sun's irradiance,
`p` the Henyey-Greenstein phase function (per steradian) of the angle `theta`
between the view ray and the direction to the sun, and `lit` in [0, 1] the
fraction of the ray the sun reaches (1 without shadows; screen-space light
shafts estimate it, see `effects.ScatteringFog`). Sky pixels (depth `+inf`)
see `max_distance` of medium: the medium's extent (a fog bank or a sphere
around the camera). Depth is the distance along the camera ray, in scene units.

Directions come from the horizontal field of view (`lens.view_directions`,
`lens.light_direction`): a light behind the camera gives its (weak, for
forward scattering) backward lobe, never a crash. Everything is finite and
differentiable in every parameter, including on sky and for any light position.
"""

import math

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from godrays_jax.kernels.lens import light_direction, view_directions
from godrays_jax.primitives.checks import check_image, check_plane, check_scalar


def henyey_greenstein(cosine: Float[ArrayLike, "*S"], *, anisotropy: Float[ArrayLike, ""]) -> Float[Array, "*S"]:
    """The Henyey-Greenstein phase function `(1 - g^2) / (4 pi (1 + g^2 - 2 g cos)^1.5)`, per steradian.

    `cosine` is the cosine of the angle between the view ray and the direction
    to the light (1 looking straight at it); `anisotropy` `g` in (-1, 1): 0 is
    isotropic (`1 / 4 pi`), positive scatters forward (haze about 0.7, fog
    0.8 and more), negative backward. It integrates to 1 over the sphere.
    """
    check_scalar(anisotropy, "anisotropy")
    cosine = jnp.asarray(cosine)
    g = jnp.asarray(anisotropy, cosine.dtype)
    # For |g| < 1 the base is at least (1 - |g|)^2 > 0: no division by zero.
    return (1.0 - g * g) / (4.0 * math.pi * (1.0 + g * g - 2.0 * g * cosine) ** 1.5)


def transmittance(
    depth: Float[Array, "H W"], *, extinction: Float[ArrayLike, ""], max_distance: Float[ArrayLike, ""]
) -> Float[Array, "H W"]:
    """`exp(-extinction * min(depth, max_distance))`: the fraction of a surface's light that reaches the camera.

    `depth` is the distance along the camera ray in scene units (`+inf` on sky,
    which sees `max_distance` of medium); `extinction` is per scene unit.
    """
    if jnp.ndim(depth) != 2:
        raise ValueError(f"depth must have shape (H, W), got shape {jnp.shape(depth)}")
    check_scalar(extinction, "extinction")
    check_scalar(max_distance, "max_distance")
    dtype = jnp.result_type(depth, jnp.float32)
    depth = jnp.asarray(depth, dtype)
    max_distance = jnp.asarray(max_distance, dtype)
    finite = jnp.isfinite(depth)
    distance = jnp.where(finite, jnp.minimum(jnp.where(finite, depth, 0.0), max_distance), max_distance)
    return jnp.exp(-jnp.asarray(extinction, dtype) * jnp.maximum(distance, 0.0))


def in_scattering(
    depth: Float[Array, "H W"],
    light_xy: Float[ArrayLike, "2"],
    *,
    fov_x_deg: Float[ArrayLike, ""],
    extinction: Float[ArrayLike, ""],
    max_distance: Float[ArrayLike, ""],
    ambient_color: Float[ArrayLike, "3"],
    light_color: Float[ArrayLike, "3"],
    anisotropy: Float[ArrayLike, ""],
    lit: Float[ArrayLike, "H W"] | float = 1.0,
    light_in_front: Bool[ArrayLike, ""] | bool = True,
) -> Float[Array, "H W 3"]:
    """The light the medium scatters toward the camera: `(1 - T) * (ambient_color + light_color * p * lit)`.

    Args:
        depth: distance along each camera ray in scene units, `+inf` on sky.
        light_xy: the sun's projected position in pixels, anywhere on or off screen.
        fov_x_deg: horizontal field of view in degrees, in (0, 180).
        extinction: `sigma_t` per scene unit, >= 0.
        max_distance: the medium's extent along a ray, scene units (what sky pixels see).
        ambient_color: isotropic in-scattered radiance, RGB (albedo x sky radiance).
        light_color: RGB albedo x sun irradiance; times the phase function (per sr).
        anisotropy: Henyey-Greenstein `g`, in (-1, 1).
        lit: fraction of each ray the sun reaches, `(H, W)` or a scalar, in [0, 1].
        light_in_front: whether the sun is in front of the camera; behind it the
            lobe points away from the screen (`lens.light_direction`).
    """
    if jnp.ndim(depth) != 2:
        raise ValueError(f"depth must have shape (H, W), got shape {jnp.shape(depth)}")
    for name, value in (("ambient_color", ambient_color), ("light_color", light_color)):
        if np.shape(value) != (3,):
            raise ValueError(f"{name} must be an RGB triple, shape (3,), got shape {np.shape(value)}")
    height, width = depth.shape
    if jnp.ndim(lit) != 0:
        check_plane(lit, "lit", height, width)
    dtype = jnp.result_type(depth, jnp.float32)
    toward_sun = light_direction(light_xy, height, width, fov_x_deg=fov_x_deg, light_in_front=light_in_front, dtype=dtype)
    cosine = jnp.matmul(view_directions(height, width, fov_x_deg=fov_x_deg, dtype=dtype), toward_sun, precision="highest")
    sun = henyey_greenstein(cosine, anisotropy=anisotropy) * jnp.asarray(lit, dtype)
    scattered = jnp.asarray(ambient_color, dtype) + sun[..., None] * jnp.asarray(light_color, dtype)
    opacity = 1.0 - transmittance(depth, extinction=extinction, max_distance=max_distance)
    return opacity[..., None] * scattered


def apply_fog(
    image: Float[Array, "H W C"],
    depth: Float[Array, "H W"],
    light_xy: Float[ArrayLike, "2"],
    *,
    fov_x_deg: Float[ArrayLike, ""],
    extinction: Float[ArrayLike, ""],
    max_distance: Float[ArrayLike, ""],
    ambient_color: Float[ArrayLike, "3"],
    light_color: Float[ArrayLike, "3"],
    anisotropy: Float[ArrayLike, ""],
    lit: Float[ArrayLike, "H W"] | float = 1.0,
    light_in_front: Bool[ArrayLike, ""] | bool = True,
) -> Float[Array, "H W C"]:
    """`image * T + in_scattering(...)` on the colour channels; an alpha channel passes through.

    `image` is the clean linear frame; the other arguments are `in_scattering`'s (the light's
    position in pixels, depth in scene units).
    A 1-channel image receives the mean of the RGB in-scattering.
    """
    check_image(image)
    check_plane(depth, "depth", image.shape[0], image.shape[1])
    dtype = image.dtype
    extinguished = transmittance(depth, extinction=extinction, max_distance=max_distance).astype(dtype)[..., None]
    scattered = in_scattering(
        depth, light_xy, fov_x_deg=fov_x_deg, extinction=extinction, max_distance=max_distance,
        ambient_color=ambient_color, light_color=light_color, anisotropy=anisotropy, lit=lit,
        light_in_front=light_in_front,
    ).astype(dtype)  # fmt: skip
    channels = min(image.shape[-1], 3)
    if channels == 1:
        scattered = jnp.mean(scattered, axis=-1, keepdims=True)
    colour = image[..., :channels] * extinguished + scattered[..., :channels]
    return jnp.concatenate([colour, image[..., channels:]], axis=-1)
