"""Masks that select what emits the rays: sky, flare, light source, depth test, coverage, bright pass.

Masks are `(H, W)` planes in [0, 1] unless said otherwise; multiply them into an
`(H, W, C)` image with `mask[..., None]`.
"""

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from godrays_jax._checks import check_image, check_light, check_plane, check_scalar
from godrays_jax.sampling import pixel_centres, sample_bilinear


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
    in_front: Bool[ArrayLike, ""] | bool = True,
    dtype=jnp.float32,
) -> Float[Array, "H W C"]:
    """Seed 003's light-source mask: a flare centred on the light, `2 * pow(flare, 2)`.

    The flare covers the square `light +- radius` pixels (seed 003 sizes it as
    `SunSize / clip-space z`; pass that size converted to pixels). With no
    `texture` the flare is the analytic disc `saturate(1 - distance / radius)`,
    one channel; a `texture` is stretched over the square and sampled
    bilinearly with clamp-to-edge addressing, as seed 003 does. Off-screen
    lights draw the part of the flare that overlaps the image. A light behind
    the camera (`in_front` false) draws nothing.
    """
    check_light(light_xy)
    check_scalar(radius, "radius")
    light_xy = jnp.asarray(light_xy, dtype)
    radius = jnp.maximum(jnp.asarray(radius, dtype), 1e-6)
    x, y = pixel_centres(height, width, dtype)
    if texture is None:
        distance = jnp.sqrt((x - light_xy[0]) ** 2 + (y - light_xy[1]) ** 2 + 1e-12)
        flare = jnp.clip(1.0 - distance / radius, 0.0, 1.0)[..., None]
    else:
        check_image(texture, "texture")
        tex_h, tex_w = texture.shape[0], texture.shape[1]
        u = (x - light_xy[0]) / (2 * radius) + 0.5
        v = (y - light_xy[1]) / (2 * radius) + 0.5
        flare = sample_bilinear(texture.astype(dtype), u * tex_w, v * tex_h)
    return 2.0 * flare**2 * jnp.asarray(in_front, dtype)


def depth_test_mask(
    depth: Float[Array, "H W"],
    light_depth: Float[ArrayLike, ""],
    *,
    bias: Float[ArrayLike, ""] = 0.0,
) -> Float[Array, "H W"]:
    """Seed 003's scene mask: 0 where the scene is in front of the light, else 1.

    `depth` and `light_depth` are linear distances in scene units (`+inf` sky
    always passes); `bias` (scene units) keeps surfaces at the light's own depth
    from masking themselves, as seed 003's `0.00025` does in hardware depth.
    """
    if jnp.ndim(depth) != 2:
        raise ValueError(f"depth must have shape (H, W), got shape {jnp.shape(depth)}")
    check_scalar(light_depth, "light_depth")
    return (depth >= light_depth - bias).astype(jnp.result_type(depth, jnp.float32))


def bright_pass(image: Float[Array, "H W C"], threshold: Float[ArrayLike, ""]) -> Float[Array, "H W C"]:
    """Seed 003's bright pass `saturate((c - T) / (1 - T))`, per channel, for `T` in [0, 1).

    The output is clipped to [0, 1], as in the seed.
    """
    check_image(image)
    check_scalar(threshold, "threshold")
    return jnp.clip((image - threshold) / (1.0 - threshold), 0.0, 1.0)
