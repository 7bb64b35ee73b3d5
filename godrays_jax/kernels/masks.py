"""Masks that select what emits the rays: sky, flare, light source, depth test, coverage, bright pass; dilate, erode.

Masks are `(H, W)` planes in [0, 1] unless said otherwise; multiply them into an
`(H, W, C)` image with `mask[..., None]`.
"""

import jax.numpy as jnp
from jax.typing import DTypeLike
from jaxtyping import Array, ArrayLike, Bool, Float

from godrays_jax.primitives.checks import (
    check_image,
    check_light,
    check_plane,
    check_scalar,
    checked_range,
    is_static_int,
)
from godrays_jax.primitives.sampling import pixel_centres, sample_bilinear


def sky_mask(depth: Float[Array, "H W"], *, far: Float[ArrayLike, ""] = jnp.inf) -> Float[Array, "H W"]:
    """1 where nothing was hit, else 0.

    kbEngine's `1 - sign(depth)` for a buffer that stores 0 on the sky,
    generalised to linear depth: a pixel is sky when its depth is `+inf` or at
    least `far` (for renderers that write the far plane instead of infinity).
    """
    if jnp.ndim(depth) != 2:
        raise ValueError(f"depth must have shape (H, W), got shape {jnp.shape(depth)}")
    return (depth >= far).astype(jnp.result_type(depth, jnp.float32))


def coverage_mask(coverage: Float[Array, "H W"]) -> Float[Array, "H W"]:
    """The antialiased sky fraction `1 - coverage`, clipped to [0, 1].

    Unlike `sky_mask` it is fractional at silhouettes, so gradients flow
    through an occluder's edge when the coverage comes from the rasterizer.
    """
    if jnp.ndim(coverage) != 2:
        raise ValueError(f"coverage must have shape (H, W), got shape {jnp.shape(coverage)}")
    return 1.0 - jnp.clip(coverage, 0.0, 1.0)


def flare_mask(flare: Float[Array, "H W C"], sky: Float[Array, "H W"]) -> Float[Array, "H W C"]:
    """kbEngine's masked flare texture: the flare where the sky shows, 0 on geometry."""
    check_image(flare, "flare")
    check_plane(sky, "sky", flare.shape[0], flare.shape[1])
    return flare * sky[..., None]


def light_source_mask(
    height: int,
    width: int,
    light_xy: Float[ArrayLike, "2"],
    *,
    radius: Float[ArrayLike, ""],
    texture: Float[Array, "h w C"] | None = None,
    light_in_front: Bool[ArrayLike, ""] | bool = True,
    dtype: DTypeLike = jnp.float32,
) -> Float[Array, "H W C"]:
    """The XNA crepuscular-rays article's light-source mask: a flare centred on the light, `2 * pow(flare, 2)`.

    The flare covers the square `light +- radius` pixels (the XNA crepuscular-rays article sizes it as
    `SunSize / clip-space z`; pass that size converted to pixels). With no
    `texture` the flare is the analytic disc `saturate(1 - distance / radius)`,
    one channel; a `texture` is stretched over the square and sampled
    bilinearly with clamp-to-edge addressing, as the XNA crepuscular-rays article does. Off-screen
    lights draw the part of the flare that overlaps the image. A light behind
    the camera (`light_in_front` false) draws nothing.
    """
    check_light(light_xy)
    check_scalar(radius, "radius")
    light_xy = jnp.asarray(light_xy, dtype)
    radius = jnp.maximum(jnp.asarray(radius, dtype), 1e-6)
    x, y = pixel_centres(height, width, dtype)
    if texture is None:
        # In radii, clipped before squaring: a far light's squared pixel distance overflows float32 (and its
        # gradient turns NaN), and beyond 1.5 radii on either axis the flare is 0 whatever the exact distance.
        dx = jnp.clip((x - light_xy[0]) / radius, -1.5, 1.5)
        dy = jnp.clip((y - light_xy[1]) / radius, -1.5, 1.5)
        flare = jnp.clip(1.0 - jnp.sqrt(dx**2 + dy**2 + 1e-12 / radius**2), 0.0, 1.0)[..., None]
    else:
        check_image(texture, "texture")
        tex_h, tex_w = texture.shape[0], texture.shape[1]
        u = (x - light_xy[0]) / (2 * radius) + 0.5
        v = (y - light_xy[1]) / (2 * radius) + 0.5
        flare = sample_bilinear(texture.astype(dtype), u * tex_w, v * tex_h)
    return 2.0 * flare**2 * jnp.asarray(light_in_front, dtype)


def depth_test_mask(
    depth: Float[Array, "H W"],
    *,
    light_depth: Float[ArrayLike, ""],
    bias: Float[ArrayLike, ""] = 0.0,
) -> Float[Array, "H W"]:
    """The XNA crepuscular-rays article's scene mask: 0 where the scene is in front of the light, else 1.

    `depth` and `light_depth` are linear distances in scene units (`+inf` sky
    always passes); `bias` (scene units) keeps surfaces at the light's own depth
    from masking themselves, as the XNA crepuscular-rays article's `0.00025` does in hardware depth.
    """
    if jnp.ndim(depth) != 2:
        raise ValueError(f"depth must have shape (H, W), got shape {jnp.shape(depth)}")
    check_scalar(light_depth, "light_depth")
    return (depth >= light_depth - bias).astype(jnp.result_type(depth, jnp.float32))


def bright_pass(image: Float[Array, "H W C"], *, threshold: Float[ArrayLike, ""]) -> Float[Array, "H W C"]:
    """The XNA crepuscular-rays article's bright pass `saturate((c - T) / (1 - T))`, per channel, for `T` in [0, 1).

    The output is clipped to [0, 1], as in the article.
    """
    check_image(image)
    check_scalar(threshold, "threshold")
    return jnp.clip((image - threshold) / (1.0 - threshold), 0.0, 1.0)


def dilate(
    mask: Float[Array, "H W"], *, radius: Float[ArrayLike, ""], max_radius: int
) -> Float[Array, "H W"]:
    """Grey-scale dilation of a mask by a disc of `radius` pixels (fittable), clamp-to-edge.

    `out(p) = max_o mask(p + o) * w(o)` over integer offsets `o`, where the
    structuring element is the antialiased disc `w(o) = clip(radius + 0.5 - |o|, 0, 1)`
    (1 at `o = 0`, so `radius = 0` returns the mask). `radius` must lie in
    `[0, max_radius]` (a static Python int, the loop's reach); it is checked
    with `equinox.error_if`. Pixels beyond the border repeat the edge.
    """
    return _morphology(mask, radius, max_radius, "mask")


def erode(
    mask: Float[Array, "H W"], *, radius: Float[ArrayLike, ""], max_radius: int
) -> Float[Array, "H W"]:
    """Grey-scale erosion, `1 - dilate(1 - mask, radius=radius)`: shrinks the parts of a [0, 1] mask that are 1."""
    return 1.0 - _morphology(1.0 - jnp.asarray(mask), radius, max_radius, "mask")


def _morphology(mask, radius, max_radius, name):
    if jnp.ndim(mask) != 2:
        raise ValueError(f"{name} must have shape (H, W), got shape {jnp.shape(mask)}")
    check_scalar(radius, "radius")
    if not is_static_int(max_radius) or max_radius < 0:
        raise ValueError(f"max_radius must be a Python int >= 0, got {max_radius!r}")
    mask = jnp.asarray(mask)
    dtype = jnp.result_type(mask, jnp.float32)
    radius = jnp.asarray(checked_range(radius, 0, max_radius, f"radius must lie in [0, max_radius={max_radius}]"), dtype)
    height, width = mask.shape
    padded = jnp.pad(mask.astype(dtype), max_radius, mode="edge")
    result = mask.astype(dtype)
    for dy in range(-max_radius, max_radius + 1):
        for dx in range(-max_radius, max_radius + 1):
            distance = (dx * dx + dy * dy) ** 0.5
            if distance == 0 or distance >= max_radius + 0.5:
                continue
            shifted = padded[max_radius + dy : max_radius + dy + height, max_radius + dx : max_radius + dx + width]
            result = jnp.maximum(result, shifted * jnp.clip(radius + 0.5 - distance, 0.0, 1.0))
    return result
