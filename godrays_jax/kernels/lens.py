"""The VBex engine article's camera and sky extras: lens dirt, a procedural dirt texture, the sky sun spot.

Both formulas need directions, not just pixel positions. They are computed in
view space (x right, y up, z forward, as `godrays_jax.primitives.camera.Camera.to_view`)
from a horizontal field of view `fov_x_deg` (degrees) and the image size, with
the project's pixel convention (x right, y down, centres at `i + 0.5`, focal
length `f = (W / 2) / tan(fov_x / 2)` pixels). `view_directions` equals
`Camera.ray_directions()` normalised, so either can be used.

The light is given as its projected pixel position `light_xy` plus whether it
is in front of the camera; a light behind the camera (`camera.project_point`
mirrors it through the camera plane) has its forward component negated.
Neither kernel divides by a distance: a light on the view axis, on a
pixel centre, off screen or behind the camera gives finite values and gradients.
"""

import functools
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike
from jaxtyping import Array, ArrayLike, Bool, Float

from godrays_jax.primitives.camera import focal_length_px, unit_vectors
from godrays_jax.primitives.checks import (
    check_image,
    check_light,
    check_scalar,
    is_static_int,
)
from godrays_jax.primitives.sampling import pixel_centres, sample_bilinear

ViewMode = Literal["pixel", "axis"]

LENS_DIRT_ABERRATION = 0.002
"""The VBex article's per-channel texture offset (UV): green reads `+0.002` in v, blue `+0.002` in u."""


def view_directions(
    height: int, width: int, *, fov_x_deg: Float[ArrayLike, ""], dtype: DTypeLike = jnp.float32
) -> Float[Array, "H W 3"]:
    """Unit view-space directions (x right, y up, z forward) through every pixel centre.

    `fov_x_deg` is the horizontal field of view in degrees, in (0, 180).
    """
    check_scalar(fov_x_deg, "fov_x_deg")
    focal = focal_length_px(width, fov_x_deg, dtype)
    x, y = pixel_centres(height, width, dtype)
    return unit_vectors(rays_through(x, y, height, width, focal))


def rays_through(
    x: Float[Array, "*S"], y: Float[Array, "*S"], height: int, width: int, focal: Float[ArrayLike, ""]
) -> Float[Array, "*S 3"]:
    """View-space rays through the pixel positions `(x, y)` (pixels, any real values) of a `height x width` frame
    whose focal length is `focal` pixels, scaled so that the forward component is 1 (x right, y up)."""
    return jnp.stack([(x - 0.5 * width) / focal, (0.5 * height - y) / focal, jnp.ones_like(x)], axis=-1)


def light_direction(
    light_xy: Float[ArrayLike, "2"],
    height: int,
    width: int,
    *,
    fov_x_deg: Float[ArrayLike, ""],
    light_in_front: Bool[ArrayLike, ""] | bool = True,
    dtype: DTypeLike = jnp.float32,
) -> Float[Array, "3"]:
    """Unit view-space direction from the camera toward a light projected at `light_xy` pixels.

    `light_xy` may be anywhere (off screen: a direction far from the axis). A
    light behind the camera is projected through its mirror image in the
    camera plane (`camera.project_point`), so when `light_in_front` is false the
    forward (z) component of the direction through `light_xy` is negated.
    """
    light_xy = check_light(light_xy)
    check_scalar(fov_x_deg, "fov_x_deg")
    light_xy = jnp.asarray(light_xy, dtype)
    focal = focal_length_px(width, fov_x_deg, dtype)
    forward = jnp.where(jnp.asarray(light_in_front), 1.0, -1.0).astype(dtype)
    ray = jnp.stack([(light_xy[0] - 0.5 * width) / focal, (0.5 * height - light_xy[1]) / focal, forward])
    return unit_vectors(ray)


def safe_power(base: Float[Array, "*S"], exponent: Float[ArrayLike, ""]) -> Float[Array, "*S"]:
    """`base ** exponent` for `base >= 0`, with 0 (and zero gradients) where `base <= 0`.

    `jnp.power` has a NaN gradient in the exponent at a zero base (`0 * log 0`).
    """
    positive = base > 0
    log_base = jnp.log(jnp.where(positive, base, 1.0))
    return jnp.where(positive, jnp.exp(exponent * log_base), 0.0)


def linear_depth(depth: Float[Array, "H W"], far_plane: Float[ArrayLike, ""]) -> Float[Array, "H W"]:
    """The VBex article's `LDepth`: `depth / far_plane` clipped to [0, 1]; the sky (`+inf`) is 1."""
    finite = jnp.isfinite(depth)
    far_plane = jnp.asarray(far_plane, depth.dtype)
    return jnp.where(finite, jnp.clip(jnp.where(finite, depth, 0.0) / far_plane, 0.0, 1.0), 1.0)


def lens_dirt_intensity(
    depth: Float[Array, "H W"],
    light_xy: Float[ArrayLike, "2"],
    *,
    fov_x_deg: Float[ArrayLike, ""],
    far_plane: Float[ArrayLike, ""],
    power: Float[ArrayLike, ""] = 20.0,
    scale: Float[ArrayLike, ""] = 2.0,
    light_in_front: Bool[ArrayLike, ""] | bool = True,
    view: ViewMode = "pixel",
    depth_floor: Float[ArrayLike, ""] = 0.8,
    depth_in_power: bool = True,
) -> Float[Array, "H W"]:
    """The VBex article's `pow(saturate(dot(view, -lightdir) * max(LDepth, 0.8)), power) * scale`.

    `-lightdir` is the direction toward the light (`light_direction`). `view` is
    each pixel's own view ray (`"pixel"`, the default: the dirt lights up
    around the sun) or the optical axis for every pixel (`"axis"`: the whole
    texture brightens as the camera turns to the sun). `LDepth` is
    `linear_depth(depth, far_plane)` (scene units), so occluders nearer than
    `0.8 * far_plane` are dimmed by `0.8 ** power`. The VBex article: `power = 20`, `scale = 2`.

    `depth_floor` is the `0.8`. `depth_in_power=False` applies the depth
    factor after the power instead, `pow(saturate(dot), power) * scale *
    max(LDepth, depth_floor)`: near geometry dims the dirt to `depth_floor`
    of the sky's, with no hard line where the depth jumps (a silhouette, the
    horizon).
    """
    if view not in ("pixel", "axis"):
        raise ValueError(f"view must be 'pixel' or 'axis', got {view!r}")
    if jnp.ndim(depth) != 2:
        raise ValueError(f"depth must have shape (H, W), got shape {jnp.shape(depth)}")
    for name, value in (("far_plane", far_plane), ("power", power), ("scale", scale), ("depth_floor", depth_floor)):
        check_scalar(value, name)
    height, width = depth.shape
    dtype = jnp.result_type(depth, jnp.float32)
    toward_light = light_direction(light_xy, height, width, fov_x_deg=fov_x_deg, light_in_front=light_in_front, dtype=dtype)
    if view == "pixel":
        cosine = jnp.matmul(view_directions(height, width, fov_x_deg=fov_x_deg, dtype=dtype), toward_light, precision="highest")
    else:
        cosine = jnp.broadcast_to(toward_light[2], (height, width))
    occlusion = jnp.maximum(linear_depth(depth.astype(dtype), far_plane), jnp.asarray(depth_floor, dtype))
    if depth_in_power:
        return safe_power(jnp.clip(cosine * occlusion, 0.0, 1.0), power) * scale
    return safe_power(jnp.clip(cosine, 0.0, 1.0), power) * scale * occlusion


def lens_dirt(
    dirt: Float[Array, "h w 1"],
    depth: Float[Array, "H W"],
    light_xy: Float[ArrayLike, "2"],
    *,
    fov_x_deg: Float[ArrayLike, ""],
    far_plane: Float[ArrayLike, ""],
    tint: Float[ArrayLike, "3"] = (1.0, 1.0, 1.0),
    power: Float[ArrayLike, ""] = 20.0,
    scale: Float[ArrayLike, ""] = 2.0,
    aberration: Float[ArrayLike, ""] = LENS_DIRT_ABERRATION,
    light_in_front: Bool[ArrayLike, ""] | bool = True,
    view: ViewMode = "pixel",
    depth_floor: Float[ArrayLike, ""] = 0.8,
    depth_in_power: bool = True,
) -> Float[Array, "H W 3"]:
    """The VBex article's lens dirt layer, to be added onto the frame: `dirt colour * lens_dirt_intensity`.

    The one-channel `dirt` texture (any size; `dirt_texture` makes one) is
    stretched over the frame and sampled bilinearly, clamp-to-edge: red at the
    pixel's UV, green at `uv + (0, aberration)`, blue at `uv + (aberration, 0)`
    (UV units; the VBex article: 0.002, a chromatic-aberration fringe), each times that
    channel of `tint` (linear RGB). See `lens_dirt_intensity` for the
    other arguments.
    """
    check_image(dirt, "dirt")
    if dirt.shape[-1] != 1:
        raise ValueError(f"dirt must have one channel, shape (h, w, 1), got shape {dirt.shape}")
    check_scalar(aberration, "aberration")
    if np.shape(tint) != (3,):
        raise ValueError(f"tint must be an RGB triple, shape (3,), got shape {np.shape(tint)}")
    intensity = lens_dirt_intensity(
        depth, light_xy, fov_x_deg=fov_x_deg, far_plane=far_plane, power=power, scale=scale,
        light_in_front=light_in_front, view=view, depth_floor=depth_floor, depth_in_power=depth_in_power,
    )  # fmt: skip
    height, width = intensity.shape
    dtype = intensity.dtype
    x, y = pixel_centres(height, width, dtype)
    u, v = x / width, y / height
    texture = dirt.astype(dtype)
    tex_h, tex_w = dirt.shape[0], dirt.shape[1]
    aberration = jnp.asarray(aberration, dtype)
    red = sample_bilinear(texture, u * tex_w, v * tex_h)
    green = sample_bilinear(texture, u * tex_w, (v + aberration) * tex_h)
    blue = sample_bilinear(texture, (u + aberration) * tex_w, v * tex_h)
    colour = jnp.concatenate([red, green, blue], axis=-1) * jnp.asarray(tint, dtype)
    return colour * intensity[..., None]


def sun_spot(
    height: int,
    width: int,
    light_xy: Float[ArrayLike, "2"],
    *,
    fov_x_deg: Float[ArrayLike, ""],
    sun_distance: Float[ArrayLike, ""],
    sun_sharpness: Float[ArrayLike, ""],
    light_in_front: Bool[ArrayLike, ""] | bool = True,
    dtype: DTypeLike = jnp.float32,
) -> Float[Array, "H W 1"]:
    """The VBex article's sky sun spot `saturate(pow(dot(dir, L), SunDistance * 2000)) * SunSharpness * 30`.

    `dir` is each pixel's unit view ray and `L` the direction toward the light;
    a negative dot gives 0. One channel, unmasked: multiply by the sky
    (`coverage_mask`) and the sun colour, as `effects.SunSpot` does. With
    `sun_distance = 1` the spot falls to half its peak about 1.5 degrees from
    the sun's centre (larger `sun_distance`: smaller spot).
    """
    for name, value in (("sun_distance", sun_distance), ("sun_sharpness", sun_sharpness)):
        check_scalar(value, name)
    toward_light = light_direction(light_xy, height, width, fov_x_deg=fov_x_deg, light_in_front=light_in_front, dtype=dtype)
    cosine = jnp.matmul(view_directions(height, width, fov_x_deg=fov_x_deg, dtype=dtype), toward_light, precision="highest")
    return sun_spot_intensity(cosine, sun_distance=sun_distance, sun_sharpness=sun_sharpness)[..., None]


def sun_spot_intensity(
    cosine: Float[Array, "*S"], *, sun_distance: Float[ArrayLike, ""], sun_sharpness: Float[ArrayLike, ""]
) -> Float[Array, "*S"]:
    """The VBex sky shader's spot at a view ray: `saturate(pow(cosine, SunDistance * 2000)) * SunSharpness * 30`.

    `cosine` is the dot product of the unit view ray and the unit direction
    toward the sun; a negative one gives 0. Used by `sun_spot` and by the
    rasterizer's sky.
    """
    exponent = jnp.asarray(sun_distance, cosine.dtype) * 2000.0
    spot = jnp.clip(safe_power(jnp.clip(cosine, 0.0, 1.0), exponent), 0.0, 1.0)
    return spot * jnp.asarray(sun_sharpness, cosine.dtype) * 30.0


def dirt_texture(
    height: int,
    width: int,
    *,
    seed: int = 0,
    num_smudges: int = 24,
    num_specks: int = 160,
    num_rings: int = 12,
    dtype: DTypeLike = jnp.float32,
) -> Float[Array, "H W 1"]:
    """A procedural one-channel lens-dirt texture in [0, 1]: smudges, specks and water rings.

    Smudges are faint, large, elongated Gaussian blobs (4 to 15 % of the
    image's larger side); specks are small bright soft discs (0.2 to 1 %);
    rings are dried-droplet outlines (2 to 6 %). Densities overlap as
    `1 - exp(-sum)`. The same seed and size give the same texture. The shapes are drawn with NumPy's `default_rng(seed)`: counts, size and
    seed are Python ints, and the texture is data, not a fittable parameter.
    """
    for name, value in (("height", height), ("width", width)):
        if not is_static_int(value) or value < 1:
            raise ValueError(f"{name} must be a Python int >= 1, got {value!r}")
    for name, value in (("num_smudges", num_smudges), ("num_specks", num_specks), ("num_rings", num_rings)):
        if not is_static_int(value) or value < 0:
            raise ValueError(f"{name} must be a Python int >= 0, got {value!r}")
    side = float(max(height, width))
    generator = np.random.default_rng(seed)

    def blobs(count, size_range, strength_range, elongation_max):
        return np.stack(
            [
                generator.uniform(0.0, width, count),
                generator.uniform(0.0, height, count),
                generator.uniform(*size_range, count) * side,
                generator.uniform(*strength_range, count),
                generator.uniform(0.0, np.pi, count),
                generator.uniform(1.0, elongation_max, count),
            ],
            axis=1,
        ).astype(np.float32)

    smudges = blobs(num_smudges, (0.04, 0.15), (0.05, 0.25), 3.0)
    specks = blobs(num_specks, (0.002, 0.01), (0.3, 1.5), 1.5)
    rings = blobs(num_rings, (0.02, 0.06), (0.15, 0.5), 1.3)
    density = _dirt_density(height, width, smudges, specks, rings)
    return (1.0 - jnp.exp(-density))[..., None].astype(dtype)


def _blob_sum(x, y, blobs, profile):
    def add(i, total):
        centre_x, centre_y, size, strength, angle, elongation = (blobs[i, k] for k in range(6))
        dx, dy = x - centre_x, y - centre_y
        along = dx * jnp.cos(angle) + dy * jnp.sin(angle)
        across = -dx * jnp.sin(angle) + dy * jnp.cos(angle)
        radius = jnp.sqrt((along / elongation) ** 2 + across**2) / size
        return total + strength * profile(radius)

    if blobs.shape[0] == 0:
        return jnp.zeros_like(x)
    return jax.lax.fori_loop(0, blobs.shape[0], add, jnp.zeros_like(x))


@functools.partial(jax.jit, static_argnums=(0, 1))
def _dirt_density(height, width, smudges, specks, rings):
    x, y = pixel_centres(height, width, jnp.float32)
    return (
        _blob_sum(x, y, smudges, lambda r: jnp.exp(-2 * r**2))
        + _blob_sum(x, y, specks, lambda r: jnp.clip(1.5 - r, 0.0, 1.0))
        + _blob_sum(x, y, rings, lambda r: jnp.exp(-(((r - 1.0) / 0.08) ** 2)) + 0.15 * (r < 1))
    )
