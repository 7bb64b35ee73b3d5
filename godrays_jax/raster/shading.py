"""Shading: the VBex planet shader's passes (lit albedo, atmosphere rim and shell, night lights) and the sky with its sun spot."""

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from godrays_jax.kernels.lens import sun_spot_intensity
from godrays_jax.primitives.camera import Camera
from godrays_jax.raster.scene import DirectionalLight, PointLight, Scene
from godrays_jax.raster.vectors import dot, times, unit_first
from godrays_jax.raster.visibility import Layer, Layers, object_weight


def world_rays(camera: Camera, px: Float[Array, "P"], py: Float[Array, "P"]) -> Float[Array, "3 P"]:
    """World directions through pixel positions, scaled to unit view depth, component first."""
    right, up, forward = (v[:, None] for v in camera.basis())
    f = camera.focal_px
    return ((px - 0.5 * camera.width) / f) * right + ((0.5 * camera.height - py) / f) * up + forward


def _sphere_waves(count: int, lowest: float, highest: float, slope: float, rng) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`count` plane waves over the unit sphere (random directions, frequencies spaced geometrically from `lowest` to
    `highest` radians per unit, random phases), amplitudes falling as `frequency ** -slope`, scaled to unit RMS."""
    directions = rng.normal(size=(count, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    frequencies = np.geomspace(lowest, highest, count)
    amplitudes = (lowest / frequencies) ** slope
    amplitudes /= np.sqrt(np.sum(amplitudes**2) / 2)
    return (directions * frequencies[:, None]).astype(np.float32), rng.uniform(0, 2 * np.pi, count).astype(np.float32), amplitudes.astype(np.float32)


# Fixed random fields on the sphere (no lattice: random directions): continents, the regions where cities cluster, towns.
_WAVES = np.random.default_rng(2012)
_CONTINENTS = _sphere_waves(32, 1.5, 12.0, 0.8, _WAVES)
_REGIONS = _sphere_waves(32, 5.0, 40.0, 0.5, _WAVES)
_TOWNS = _sphere_waves(64, 120.0, 400.0, 0.0, _WAVES)


def _field(normal: Float[Array, "3 *P"], waves) -> Float[Array, "*P"]:
    vectors, phases, amplitudes = (jnp.asarray(part) for part in waves)
    along = jnp.tensordot(vectors, normal, axes=(1, 0), precision="highest")
    waves = jnp.sin(along + phases.reshape(-1, *([1] * (along.ndim - 1))))
    return jnp.tensordot(amplitudes, waves, axes=1, precision="highest")


def _smoothstep(low: float, high: float, x):
    t = jnp.clip((x - low) / (high - low), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


LAND_LEVEL = 0.3
"""Where `continents` turns to land (about a quarter of the sphere): below it is the sea, which `city_lights` leaves
dark."""


def continents(normal: Float[Array, "3 *P"]) -> Float[Array, "*P"]:
    """The night-light map's continents at unit normals: a smooth random field over the sphere (unit RMS), land above
    `LAND_LEVEL`."""
    return _field(normal, _CONTINENTS)


def city_lights(normal: Float[Array, "3 *P"]) -> Float[Array, "*P"]:
    """Procedural stand-in for an emissive night-light map, in [0, 1] at unit normals: city lights.

    The `continents` hold towns (small bright spots of a fine random field)
    clustered in regions and along the coasts, with a faint glow of the dense
    regions between them; the sea is dark.
    """
    height = continents(normal)
    land = _smoothstep(LAND_LEVEL, 0.45, height)
    coast = land * (1.0 - _smoothstep(0.45, 1.05, height))
    density = _smoothstep(0.0, 1.6, _field(normal, _REGIONS) + 0.8 * coast)
    towns = _smoothstep(1.3, 2.3, _field(normal, _TOWNS))
    return jnp.clip(land * density * (3.0 * towns + 0.1 * density), 0.0, 1.0)


def _stack_materials(scene: Scene):
    """Every material field stacked over objects, colours component-first `(3, objects)`."""
    materials = [obj.material for obj in scene.objects]
    return jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves, axis=-1), *materials)


def _light_direction(light: DirectionalLight | PointLight, world_position: Float[Array, "3 P"]) -> Float[Array, "3 P"]:
    if isinstance(light, DirectionalLight):
        return jnp.broadcast_to(unit_first(light.direction)[:, None], world_position.shape)
    return unit_first(light.position[:, None] - world_position)


def shade(scene: Scene, camera: Camera, surface: Layer, world_rays: Float[Array, "3 P"]):
    """One layer's shading, the VBex planet shader's passes: `(opaque colour, shell, emissive, opaque)`.

    The opaque sphere: albedo lit, emission, the atmosphere's colour from the
    basic rim `1 - saturate(view . N)` (lit), night lights on the dark side;
    where the rim sharpened for clipping, `min(1, 10 * rim ** (30 * sharpness))`,
    reaches 1 the opaque pixel is discarded (only for materials with an
    atmosphere). The transparent shell: the atmosphere's colour times that
    sharpened rim, lit by `saturate(N . L)` in the shader (the article's glow
    is not lit by the deferred pass). The emissive part (emission and night
    lights: the engine's emissive light) also goes to the glow target.
    Every light of `scene.lights` lights the albedo, the rim and the shell
    alike, their light added; the night lights take the first light's dark
    side (the sun's).
    """
    materials = _stack_materials(scene)
    obj = jnp.maximum(surface.object_id, 0)
    to_world = jnp.stack(camera.basis())
    normal = times(surface.normal, to_world)
    world_position = camera.position[:, None] + times(surface.position, to_world)
    n_dot_ls = [dot(normal, _light_direction(light, world_position)) for light in scene.lights]
    lits = [jnp.clip(n_dot_l, 0.0, 1.0) for n_dot_l in n_dot_ls]
    lit = sum(lits)
    lit_color = sum(light.color[:, None] * light_lit for light, light_lit in zip(scene.lights, lits))
    # Kept off 0 so that rim ** p has finite gradients for any p > 0.
    rim = 1.0 - jnp.clip(-dot(unit_first(world_rays), normal), 0.0, 1.0 - 1e-6)
    sharpened_rim = jnp.minimum(1.0, 10.0 * rim ** (30.0 * materials.atmosphere_sharpness[obj]))
    dark_side = jnp.clip(-n_dot_ls[0] * materials.night_sharpness[obj], 0.0, 1.0)
    atmosphere = materials.atmosphere_color[:, obj]
    emissive = materials.emission[:, obj] + materials.night_color[:, obj] * (city_lights(normal) * dark_side)
    opaque_colour = (
        materials.albedo[:, obj] * (scene.ambient[:, None] + lit_color)
        + atmosphere * (rim * lit)
        + emissive
    )
    clipped = jnp.any(atmosphere > 0, axis=0) & (sharpened_rim >= 1.0)
    return opaque_colour, atmosphere * (sharpened_rim * lit), emissive, jnp.where(clipped, 0.0, 1.0)


def _sun_direction(scene: Scene, camera: Camera) -> Float[Array, "3"]:
    if isinstance(scene.light, DirectionalLight):
        direction = scene.light.direction
    else:
        direction = scene.light.position - camera.position
    return direction / jnp.linalg.norm(direction)


def sky(scene: Scene, camera: Camera, world_rays: Float[Array, "3 P"]) -> tuple[Float[Array, "3 P"], Float[Array, "P"]]:
    """Sky colour and the sun spot's intensity (the VBex article)."""
    unit = unit_first(world_rays)
    height = jnp.clip(dot(unit, (camera.up / jnp.linalg.norm(camera.up))[:, None]), 0.0, 1.0)
    sky = scene.sky
    cosine = dot(unit, _sun_direction(scene, camera)[:, None])
    spot = sun_spot_intensity(cosine, sun_distance=sky.sun_distance, sun_sharpness=sky.sun_sharpness)
    color = sky.horizon_color[:, None] + (sky.zenith_color - sky.horizon_color)[:, None] * height + sky.sun_color[:, None] * spot
    return color, spot


def shade_pixels(scene: Scene, camera: Camera, layers: Layers | None, px: Float[Array, "P"], py: Float[Array, "P"]) -> dict:
    """Every buffer but the glow pass, for P pixels at positions `px`, `py`: the two layers shaded and composited
    over the sky (`layers` None: sky alone); what `rasterize` calls for each batch of tiles."""
    to_world = jnp.stack(camera.basis())
    rays = world_rays(camera, px, py)
    sky_color, sun_spot = sky(scene, camera, rays)
    light = jnp.clip(sun_spot, 0.0, 1.0)
    if layers is None:
        return dict(
            color=sky_color.T, depth=jnp.full(px.shape, jnp.inf), coverage=jnp.zeros(px.shape), normal=jnp.zeros((*px.shape, 3)),
            object_id=jnp.full(px.shape, -1, jnp.int32), light_pass=light if scene.sun is None else jnp.zeros(px.shape),
            glow_target=(scene.sky.sun_color[:, None] * sun_spot).T,
        )
    (front_color, front_shell, front_emissive, front_opaque), (behind_color, behind_shell, behind_emissive, behind_opaque) = (
        shade(scene, camera, layer, rays) for layer in (layers.front, layers.behind)
    )
    # The shell covers the whole outline; the opaque surface only where its rim is not clipped.
    shell_f, shell_b = layers.front.coverage, layers.behind.coverage
    cf, cb = shell_f * front_opaque, shell_b * behind_opaque
    shell = shell_f * front_shell + (1.0 - shell_f) * shell_b * behind_shell
    coverage = cf + (1.0 - cf) * cb
    hit = layers.hit
    clipped_hit = (hit.object_id == layers.front.object_id) & (front_opaque == 0) & (cb == 0)
    has_hit = (hit.object_id >= 0) & ~clipped_hit
    # Sky pixels' positions are placeholders: keep the norm's gradient finite there.
    position = jnp.where(has_hit, hit.position, 1.0)
    depth = jnp.where(has_hit, jnp.sqrt(dot(position, position)), jnp.inf)
    sky_glow = scene.sky.sun_color[:, None] * sun_spot
    return dict(
        color=(cf * front_color + (1.0 - cf) * (cb * behind_color + (1.0 - cb) * sky_color) + shell).T,
        depth=depth,
        coverage=coverage,
        normal=jnp.where(has_hit, times(hit.normal, to_world), 0.0).T,
        object_id=jnp.where(has_hit, hit.object_id, -1),
        light_pass=(1.0 - coverage) * light if scene.sun is None else object_weight(layers, scene.sun),
        glow_target=(cf * front_emissive + (1.0 - cf) * (cb * behind_emissive + (1.0 - cb) * sky_glow) + shell).T,
    )
