"""Scene description: materials, spheres, triangle meshes, lights, sky.

Every class is an `equinox.Module`, so a scene is a pytree: positions, radii,
colours and shading constants are float arrays you can differentiate (use
`equinox.filter_grad`: mesh faces are integer arrays). Values are checked when a
class is built with concrete values; a bad value raises `ValueError` naming the
field.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int


def _float(value: ArrayLike) -> Array:
    return jnp.asarray(value, dtype=jnp.float32)


def _concrete(*values) -> bool:
    return not any(isinstance(v, jax.core.Tracer) for v in values)


def _check_shape(owner: str, name: str, value: Array, shape: tuple[int, ...]) -> None:
    if value.shape != shape:
        raise ValueError(f"{owner}.{name} must have shape {shape}, got {value.shape}")


def _check_finite(owner: str, name: str, value: Array) -> None:
    if _concrete(value) and not np.all(np.isfinite(np.asarray(value))):
        raise ValueError(f"{owner}.{name} must be finite")


class Material(eqx.Module):
    """Surface shading, all colours linear RGB (HDR allowed).

    Shaded colour = `albedo * (ambient + light_color * saturate(N.L))`
    `+ emission` (the sun: unlit, visible in the dark)
    `+ atmosphere_color * rim * saturate(N.L)` with `rim = 1 - saturate(view . N)`
    (the VBex planet shader's basic rim gives the atmosphere's colour)
    `+ night_color * city_pattern(N) * saturate(-N.L * night_sharpness)`
    (the VBex article's emissive night lights, only on the dark side; `city_pattern`
    is a fixed procedural stand-in for an emissive light map, in [0, 1]).

    An object with an atmosphere (`atmosphere_color` non-zero) is also drawn
    as the article's transparent glowing shell: `atmosphere_color * RimOfAtmos
    * saturate(N.L)`, `RimOfAtmos = min(1, 10 * rim ** (30 * atmosphere_sharpness))`
    (the rim sharpened for clipping), added to the colour and to the glow
    target; its opaque pixels where `RimOfAtmos` reaches 1 are clipped, so
    the outline is the shell's (larger `atmosphere_sharpness`: a thinner
    shell). Emission and night lights go to the glow target too.
    """

    albedo: Float[Array, "3"] = eqx.field(converter=_float, default=(0.8, 0.8, 0.8))
    emission: Float[Array, "3"] = eqx.field(converter=_float, default=(0.0, 0.0, 0.0))
    atmosphere_color: Float[Array, "3"] = eqx.field(converter=_float, default=(0.0, 0.0, 0.0))
    atmosphere_sharpness: Float[Array, ""] = eqx.field(converter=_float, default=0.1)
    night_color: Float[Array, "3"] = eqx.field(converter=_float, default=(0.0, 0.0, 0.0))
    night_sharpness: Float[Array, ""] = eqx.field(converter=_float, default=4.0)

    def __check_init__(self):
        for name in ("albedo", "emission", "atmosphere_color", "night_color"):
            _check_shape("Material", name, getattr(self, name), (3,))
            _check_finite("Material", name, getattr(self, name))
        for name in ("atmosphere_sharpness", "night_sharpness"):
            value = getattr(self, name)
            _check_shape("Material", name, value, ())
            if _concrete(value) and not float(value) > 0:
                raise ValueError(f"Material.{name} must be > 0, got {float(value)}")


class Sphere(eqx.Module):
    """An analytic sphere (exact silhouette, exact depth).

    Attributes:
        center: world position, shape (3,).
        radius: world units, > 0.
        material: its `Material`.
    """

    center: Float[Array, "3"] = eqx.field(converter=_float)
    radius: Float[Array, ""] = eqx.field(converter=_float)
    material: Material = eqx.field(default_factory=Material)

    def __check_init__(self):
        _check_shape("Sphere", "center", self.center, (3,))
        _check_finite("Sphere", "center", self.center)
        _check_shape("Sphere", "radius", self.radius, ())
        if _concrete(self.radius) and not float(self.radius) > 0:
            raise ValueError(f"Sphere.radius must be > 0, got {float(self.radius)}")


def _rotation_matrix(rotation_deg: Float[Array, "3"]) -> Float[Array, "3 3"]:
    """Rotation about x, then y, then z (extrinsic), angles in degrees."""
    ax, ay, az = jnp.deg2rad(rotation_deg)
    cx, sx, cy, sy, cz, sz = jnp.cos(ax), jnp.sin(ax), jnp.cos(ay), jnp.sin(ay), jnp.cos(az), jnp.sin(az)
    one, zero = jnp.ones_like(ax), jnp.zeros_like(ax)
    rx = jnp.array([[one, zero, zero], [zero, cx, -sx], [zero, sx, cx]])
    ry = jnp.array([[cy, zero, sy], [zero, one, zero], [-sy, zero, cy]])
    rz = jnp.array([[cz, -sz, zero], [sz, cz, zero], [zero, zero, one]])
    return jnp.matmul(jnp.matmul(rz, ry, precision="highest"), rx, precision="highest")


class Mesh(eqx.Module):
    """A triangle mesh with a transform: `world = R(rotation_deg) @ (scale * local) + translation`.

    Attributes:
        vertices: local positions, `(V, 3)`.
        faces: vertex indices, `(F, 3)` int; counter-clockwise seen from the front.
        normals: optional per-vertex local normals `(V, 3)` (smooth shading);
            `None` shades each face flat.
        translation, rotation_deg (x, y, z Euler angles, degrees), scale (per axis,
            > 0): the transform. Scaling for the glow pass happens about the
            mesh origin, before this transform, as in the sun-overcasting article's vertex shader.
        double_sided: draw back faces too (static); single-sided meshes are
            culled like a GPU's back-face culling, which also keeps the
            silhouette's antialiasing exact for closed meshes.
    """

    vertices: Float[Array, "V 3"] = eqx.field(converter=_float)
    faces: Int[Array, "F 3"] = eqx.field(converter=lambda f: jnp.asarray(f, dtype=jnp.int32))
    material: Material = eqx.field(default_factory=Material)
    normals: Float[Array, "V 3"] | None = eqx.field(converter=lambda n: None if n is None else _float(n), default=None)
    translation: Float[Array, "3"] = eqx.field(converter=_float, default=(0.0, 0.0, 0.0))
    rotation_deg: Float[Array, "3"] = eqx.field(converter=_float, default=(0.0, 0.0, 0.0))
    scale: Float[Array, "3"] = eqx.field(converter=lambda s: jnp.broadcast_to(_float(s), (3,)), default=1.0)
    double_sided: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3 or self.vertices.shape[0] < 3:
            raise ValueError(f"Mesh.vertices must have shape (V, 3) with V >= 3, got {self.vertices.shape}")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3 or self.faces.shape[0] < 1:
            raise ValueError(f"Mesh.faces must have shape (F, 3) with F >= 1, got {self.faces.shape}")
        if self.normals is not None:
            _check_shape("Mesh", "normals", self.normals, self.vertices.shape)
        for name in ("translation", "rotation_deg", "scale"):
            _check_shape("Mesh", name, getattr(self, name), (3,))
            _check_finite("Mesh", name, getattr(self, name))
        if _concrete(self.scale) and not np.all(np.asarray(self.scale) > 0):
            raise ValueError(f"Mesh.scale must be > 0, got {np.asarray(self.scale).tolist()}")
        if not _concrete(self.vertices, self.faces):
            return
        faces = np.asarray(self.faces)
        vertices = np.asarray(self.vertices, np.float64)
        if faces.min() < 0 or faces.max() >= len(vertices):
            raise ValueError(f"Mesh.faces index a vertex outside [0, {len(vertices) - 1}]")
        _check_finite("Mesh", "vertices", self.vertices)
        corners = vertices[faces]
        doubled_area = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
        extent = np.ptp(vertices, axis=0).max()
        degenerate = np.flatnonzero(doubled_area <= 1e-12 * max(extent, 1e-30) ** 2)
        if degenerate.size:
            raise ValueError(
                f"Mesh.faces[{degenerate[0]}] is a degenerate triangle (zero area)"
                + (f", and {degenerate.size - 1} more" if degenerate.size > 1 else "")
            )

    def world_triangles(self, *, local_scale: float | Array = 1.0) -> tuple[Float[Array, "F 3 3"], Float[Array, "F 3 3"]]:
        """World-space corners `(F, 3, 3)` and unit shading normals at each corner."""
        rotation = _rotation_matrix(self.rotation_deg)
        world_vertices = jnp.matmul(self.vertices * (self.scale * local_scale), rotation.T, precision="highest") + self.translation
        corners = world_vertices[self.faces]
        if self.normals is None:
            face_normal = jnp.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
            normals = jnp.broadcast_to(face_normal[:, None, :], corners.shape)
        else:
            normals = jnp.matmul(self.normals / self.scale, rotation.T, precision="highest")[self.faces]
        normals = normals / jnp.maximum(jnp.linalg.norm(normals, axis=-1, keepdims=True), 1e-30)
        return corners, normals


class DirectionalLight(eqx.Module):
    """A light at infinity. `direction` points from the scene towards the light."""

    direction: Float[Array, "3"] = eqx.field(converter=_float)
    color: Float[Array, "3"] = eqx.field(converter=_float, default=(1.0, 1.0, 1.0))

    def __check_init__(self):
        _check_shape("DirectionalLight", "direction", self.direction, (3,))
        _check_shape("DirectionalLight", "color", self.color, (3,))
        if _concrete(self.direction) and not np.linalg.norm(np.asarray(self.direction)) > 0:
            raise ValueError("DirectionalLight.direction must be non-zero")


class PointLight(eqx.Module):
    """A point light at `position` (no distance falloff: the scenes here are
    sun-like lights far from the objects they light)."""

    position: Float[Array, "3"] = eqx.field(converter=_float)
    color: Float[Array, "3"] = eqx.field(converter=_float, default=(1.0, 1.0, 1.0))

    def __check_init__(self):
        _check_shape("PointLight", "position", self.position, (3,))
        _check_shape("PointLight", "color", self.color, (3,))


class Sky(eqx.Module):
    """Background: a vertical gradient plus the VBex article's sun spot.

    Sky colour = `mix(horizon_color, zenith_color, saturate(dir . up))`
    `+ sun_color * saturate(saturate(dir . L) ** (sun_distance * 2000)) * sun_sharpness * 30`,
    `dir` the unit view ray, `up` the camera's up vector, `L` the direction to
    the light. `sun_sharpness = 0` draws no spot.
    """

    zenith_color: Float[Array, "3"] = eqx.field(converter=_float, default=(0.0, 0.0, 0.0))
    horizon_color: Float[Array, "3"] = eqx.field(converter=_float, default=(0.0, 0.0, 0.0))
    sun_color: Float[Array, "3"] = eqx.field(converter=_float, default=(1.0, 0.9, 0.7))
    sun_distance: Float[Array, ""] = eqx.field(converter=_float, default=1.0)
    sun_sharpness: Float[Array, ""] = eqx.field(converter=_float, default=0.0)

    def __check_init__(self):
        for name in ("zenith_color", "horizon_color", "sun_color"):
            _check_shape("Sky", name, getattr(self, name), (3,))
        for name in ("sun_distance", "sun_sharpness"):
            value = getattr(self, name)
            _check_shape("Sky", name, value, ())
            if _concrete(value) and not float(value) >= 0:
                raise ValueError(f"Sky.{name} must be >= 0, got {float(value)}")


class Scene(eqx.Module):
    """Objects, their lights, the sky and ambient light.

    Attributes:
        objects: spheres and meshes; an object's id is its index here.
        light: a `DirectionalLight` or `PointLight` (Lambert shading), the scene's first light: the one the sky's
            sun spot, the sun object and the night lights' dark side belong to.
        sky: the background.
        ambient: linear RGB light added everywhere, multiplied by albedo.
        sun: index of the object that is the visible light source (drawn white
            in the light pass, enlarged and tinted in the glow pass), or `None`
            (then the sky's sun spot plays that role). Static.
        other_lights: the lights beside it (`DirectionalLight`s or `PointLight`s), each shading the surfaces as
            `light` does, their light added (`lights`: all of them, `light` first).
    """

    objects: tuple[Sphere | Mesh, ...]
    light: DirectionalLight | PointLight = eqx.field(default_factory=lambda: DirectionalLight(direction=(0.0, 0.0, 1.0)))
    sky: Sky = eqx.field(default_factory=Sky)
    ambient: Float[Array, "3"] = eqx.field(converter=_float, default=(0.0, 0.0, 0.0))
    sun: int | None = eqx.field(static=True, default=None)
    other_lights: tuple[DirectionalLight | PointLight, ...] = ()

    @property
    def lights(self) -> tuple[DirectionalLight | PointLight, ...]:
        """Every light of the scene, `light` first."""
        return (self.light, *self.other_lights)

    def __check_init__(self):
        if not isinstance(self.objects, tuple) or not all(isinstance(o, (Sphere, Mesh)) for o in self.objects):
            raise ValueError("Scene.objects must be a tuple of Sphere and Mesh")
        if not isinstance(self.light, (DirectionalLight, PointLight)):
            raise ValueError("Scene.light must be a DirectionalLight or a PointLight")
        if not isinstance(self.other_lights, tuple) or not all(
            isinstance(light, (DirectionalLight, PointLight)) for light in self.other_lights
        ):
            raise ValueError("Scene.other_lights must be a tuple of DirectionalLight and PointLight")
        _check_shape("Scene", "ambient", self.ambient, (3,))
        if self.sun is not None and not (isinstance(self.sun, int) and 0 <= self.sun < len(self.objects)):
            raise ValueError(f"Scene.sun must be None or an object index in [0, {len(self.objects) - 1}], got {self.sun!r}")
