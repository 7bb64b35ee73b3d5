"""Masks that select what emits the rays: sky, flare, light source, depth test, coverage, bright pass; dilate, erode.

Masks are `(H, W)` planes in [0, 1] unless said otherwise; multiply them into an
`(H, W, C)` image with `mask[..., None]`.
"""

import jax
import jax.numpy as jnp
import numpy as np
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


def sky_mask(depth: Float[Array, "H W"], *, sky_depth: Float[ArrayLike, ""] = jnp.inf) -> Float[Array, "H W"]:
    """1 where nothing was hit, else 0.

    kbEngine's `1 - sign(depth)` for a buffer that stores 0 on the sky,
    generalised to linear depth: a pixel is sky when its depth is `+inf` or at
    least `sky_depth` (for renderers that write the far plane instead of infinity).
    """
    if jnp.ndim(depth) != 2:
        raise ValueError(f"depth must have shape (H, W), got shape {jnp.shape(depth)}")
    return (depth >= sky_depth).astype(jnp.result_type(depth, jnp.float32))


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


def flare_image(
    height: int,
    width: int,
    light_xy: Float[ArrayLike, "2"],
    *,
    flare_size: Float[ArrayLike, ""] | Float[ArrayLike, "2"],
    texture: Float[Array, "h w C"] | None = None,
    light_in_front: Bool[ArrayLike, ""] | bool = True,
    dtype: DTypeLike = jnp.float32,
) -> Float[Array, "H W C"]:
    """A flare texture drawn centred on the light (kbEngine's base flare texture), as sampled: no squaring.

    The flare covers the rectangle `light +- flare_size` pixels: `flare_size` is one
    number (a square) or `(rx, ry)` (the article's `SunSize / clip-space z`
    is a half-extent in UV units, so on a `W x H` frame it is
    `(size * W, size * H)` pixels: wider than tall on a landscape frame, as on
    the GPU). With no `texture` the flare is the analytic cone
    `saturate(1 - r)`, `r` the distance from the light in units of the
    half-extent, one channel; a `texture` is stretched over the rectangle, its
    texel `i` centred at `light - flare_size + (i + 0.5) * 2 * flare_size / w`, and
    sampled bilinearly with clamp-to-edge addressing as the article's sampler
    does (so a texture whose border is not black lights the whole frame).
    `procedural_flare` makes a texture. Off-screen lights draw the part of
    the flare that overlaps the image. A light behind the camera
    (`light_in_front` false) draws nothing.
    """
    light_xy = check_light(light_xy)
    if jnp.shape(flare_size) not in ((), (2,)):
        raise ValueError(f"flare_size must be a scalar or a pair (rx, ry), got shape {jnp.shape(flare_size)}")
    light_xy = jnp.asarray(light_xy, dtype)
    flare_size = jnp.maximum(jnp.broadcast_to(jnp.asarray(flare_size, dtype), (2,)), 1e-6)
    x, y = pixel_centres(height, width, dtype)
    u = (x - light_xy[0]) / (2 * flare_size[0]) + 0.5
    v = (y - light_xy[1]) / (2 * flare_size[1]) + 0.5
    if texture is None:
        # Clipped before squaring: a far light's squared distance overflows float32 (and its gradient
        # turns NaN), and beyond 1.5 radii on either axis the flare is 0 whatever the exact distance.
        dx = jnp.clip(2 * u - 1, -1.5, 1.5)
        dy = jnp.clip(2 * v - 1, -1.5, 1.5)
        flare = jnp.clip(1.0 - jnp.sqrt(dx**2 + dy**2 + 1e-12), 0.0, 1.0)[..., None]
    else:
        check_image(texture, "texture")
        tex_h, tex_w = texture.shape[0], texture.shape[1]
        flare = sample_bilinear(texture.astype(dtype), u * tex_w, v * tex_h)
    return flare * jnp.asarray(light_in_front, dtype)


def light_source_mask(
    height: int,
    width: int,
    light_xy: Float[ArrayLike, "2"],
    *,
    flare_size: Float[ArrayLike, ""] | Float[ArrayLike, "2"],
    texture: Float[Array, "h w C"] | None = None,
    light_in_front: Bool[ArrayLike, ""] | bool = True,
    dtype: DTypeLike = jnp.float32,
) -> Float[Array, "H W C"]:
    """The XNA crepuscular-rays article's light-source mask `2 * pow(tex2D(Flare, coord), 2)`: `2 * flare_image**2`.

    `light_xy` and `flare_size` are in pixels; see `flare_image` for the flare's
    placement, size, texture and sampling.
    """
    flare = flare_image(
        height, width, light_xy, flare_size=flare_size, texture=texture, light_in_front=light_in_front, dtype=dtype
    )
    return 2.0 * flare**2


def procedural_flare(
    height: int = 256, width: int = 256, *, halo: float = 0.5, core: float = 0.08
) -> Float[np.ndarray, "H W 1"]:
    """A sun-glow flare texture in [0, 1], one channel, black at its border: `halo * (1 - r)**2 + (1 - halo) * exp(-(r / core)**2)`.

    `r` is the distance from the texture's centre in units of its half-sides
    (texel centres at `(i + 0.5) / size` on each axis), clipped to `r <= 1`. A small bright
    core (`core`, same units) over a wide dim halo: through the XNA article's
    `2 * pow(tex, 2)`, rays and bright pass only the core saturates, where a
    flat disc would clip everywhere. Plain NumPy data (not fittable).
    """
    for name, value in (("height", height), ("width", width)):
        if not is_static_int(value) or value < 2:
            raise ValueError(f"{name} must be a Python int >= 2, got {value!r}")
    if not (0.0 <= halo <= 1.0 and core > 0.0):
        raise ValueError(f"halo must lie in [0, 1] and core be > 0, got halo={halo!r}, core={core!r}")
    across = (np.arange(width) + 0.5) / width * 2 - 1
    down = (np.arange(height) + 0.5) / height * 2 - 1
    r = np.minimum(np.hypot(*np.meshgrid(across, down)), 1.0)
    texture = halo * (1 - r) ** 2 + (1 - halo) * np.exp(-((r / core) ** 2))
    return texture.astype(np.float32)[..., None]


def depth_test_mask(
    depth: Float[Array, "H W"],
    *,
    light_depth: Float[ArrayLike, ""],
    bias: Float[ArrayLike, ""] = 0.0,
) -> Float[Array, "H W"]:
    """The XNA crepuscular-rays article's scene mask: 0 where the scene is in front of the light, else 1.

    `depth >= light_depth - bias`, in any depth encoding that grows with distance: the article compares
    hardware depth (`hardware_depth`, z/w) with `bias = 0.00025`, so that surfaces at the light's own depth
    do not mask themselves; linear distances (scene units, `+inf` sky always passes) work as well.
    """
    if jnp.ndim(depth) != 2:
        raise ValueError(f"depth must have shape (H, W), got shape {jnp.shape(depth)}")
    check_scalar(light_depth, "light_depth")
    return (depth >= light_depth - bias).astype(jnp.result_type(depth, jnp.float32))


def clip_space_depth(
    depth: Float[ArrayLike, "*S"], *, near_plane: float, far_plane: float
) -> Float[Array, "*S"]:
    """A point's clip-space z, `(d - near) * far / (far - near)`, from its planar depth `d` (scene units).

    The z that a Direct3D/XNA perspective matrix (`Matrix.CreatePerspectiveFieldOfView`) gives before the
    divide by `w = d`: 0 on the near plane, `far_plane` on the far plane, negative in front of the near plane.
    A point at or beyond the far plane (the sky, a light at infinity: `+inf`) is read as on it (`far_plane`),
    as a sky box is drawn (`z = w`). The XNA crepuscular-rays article sizes its flare `SunSize / z` and clamps
    its step by `z`.
    """
    depth = jnp.asarray(depth)
    dtype = jnp.result_type(depth, jnp.float32)
    depth = depth.astype(dtype)
    beyond = depth >= far_plane
    within = jnp.where(beyond, far_plane, depth)  # the far plane where beyond: no inf in the gradient
    return jnp.where(beyond, far_plane, (within - near_plane) * (far_plane / (far_plane - near_plane))).astype(dtype)


def hardware_depth(
    depth: Float[ArrayLike, "*S"], *, near_plane: float, far_plane: float
) -> Float[Array, "*S"]:
    """What a Direct3D/XNA depth buffer holds, `z / w = far / (far - near) * (1 - near / d)`, from planar depth `d`.

    `d` is the distance along the camera's axis in scene units; 0 on the near plane, 1 on the far plane; the
    sky and anything at or beyond the far plane read 1 (the cleared buffer: nothing was drawn there). Pixels
    nearer than the near plane read negative. The XNA crepuscular-rays article's depth test compares these.
    """
    depth = jnp.asarray(depth)
    dtype = jnp.result_type(depth, jnp.float32)
    depth = depth.astype(dtype)
    beyond = depth >= far_plane
    safe = jnp.where(beyond | (depth <= 0), far_plane, depth)
    inside = far_plane / (far_plane - near_plane) * (1.0 - near_plane / safe)
    return jnp.where(beyond, 1.0, jnp.where(depth <= 0, -jnp.inf, inside)).astype(dtype)


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



def bright_sky(
    luminance: Float[Array, "H W"],
    light_xy: Float[ArrayLike, "2"],
    *,
    threshold: Float[ArrayLike, ""] = 0.5,
    softness: Float[ArrayLike, ""] = 0.2,
    window: float = 0.15,
) -> Float[Array, "H W"]:
    """The open sky of a frame without depth: its bright parts, relative to the frame around the light.

    What Blender's Sun Beams node and Nuke's GodRays leave to the user's key,
    drawn from the frame itself. Around the light (the pixels within `window`,
    a fraction of the frame's larger side, of the light's position clamped
    onto the frame, so an off-screen light reads the edge nearest it) the
    dark end `lo` (5th percentile of `luminance`) and the bright end `hi`
    (90th: the open sky, not a sun that fills a tenth of the window) are
    found, `lo` kept between `hi / 1000` and `hi / 16` (a window of open sky
    alone still has a span). A pixel's place between them on a
    log scale, `u = log(Y / lo) / log(hi / lo)`, is open sky by `smoothstep`
    over `threshold -+ softness / 2`: with the default 0.5, brighter than
    the geometric mean of the two ends. Returns `(H, W)` in [0, 1], 1 on open
    sky, 0 on what is darker (the occluders); a black window gives no sky.
    Differentiated through the smoothstep only: the window's quantiles are held constant.
    """
    if jnp.ndim(luminance) != 2:
        raise ValueError(f"luminance must have shape (H, W), got shape {jnp.shape(luminance)}")
    light_xy = check_light(light_xy)
    if not window > 0.0:
        raise ValueError(f"window must be > 0 (a fraction of the frame's larger side), got {window!r}")
    height, width = luminance.shape
    dtype = jnp.result_type(luminance, jnp.float32)
    luminance = luminance.astype(dtype)
    x, y = pixel_centres(height, width, dtype)
    light_xy = jnp.asarray(light_xy, dtype)
    centre_x = jnp.clip(light_xy[0], 0.5, width - 0.5)
    centre_y = jnp.clip(light_xy[1], 0.5, height - 0.5)
    near = (x - centre_x) ** 2 + (y - centre_y) ** 2 <= (window * max(height, width)) ** 2
    # The window's two quantiles only set the scale: held constant, so the gradient (through the NaN-padded sort,
    # which differs under vmap) is the smoothstep's alone and the same for a frame alone or in a batch.
    low, high = jax.lax.stop_gradient(
        jnp.nanquantile(jnp.where(near, luminance, jnp.nan), jnp.asarray([0.05, 0.9], dtype))
    )
    low = jnp.clip(low, high / 1000.0, high / 16.0)
    positive = (high > 0) & (luminance > 0)
    place = jnp.log(jnp.where(positive, luminance, 1.0) / jnp.where(high > 0, low, 1.0)) / jnp.log(
        jnp.where(high > 0, high / low, 16.0)
    )
    softness = jnp.maximum(jnp.asarray(softness, dtype), 1e-6)
    t = jnp.clip((place - (threshold - softness / 2)) / softness, 0.0, 1.0)
    return jnp.where(positive, t * t * (3.0 - 2.0 * t), 0.0)
