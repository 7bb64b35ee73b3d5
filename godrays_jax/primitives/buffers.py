"""The frame buffers every effect reads: colour, depth, coverage and optional passes."""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Int

from godrays_jax.primitives.camera import DEPTH_KINDS, DepthKind, planar_to_ray_depth
from godrays_jax.primitives.light_view import LightView


class Silhouettes(eqx.Module):
    """A frame's silhouettes as `kernels.silhouettes.silhouette_mix` reads them off its colour, depth and coverage.

    Attributes:
        coverage: how much of each pixel its surface covers, `(H, W)` in [0, 1].
        uncovered_depth: what the rest of the pixel sees, `(H, W)`, scene units along the ray (`+inf`: the sky).
    """

    coverage: Float[Array, "H W"]
    uncovered_depth: Float[Array, "H W"]


class Buffers(eqx.Module):
    """One rendered frame.

    Attributes:
        color: linear HDR colour, `(H, W, C)` with C = 1, 3 or 4.
        depth: linear depth in scene units, `(H, W)`; `+inf` where nothing
            was hit (sky). Distance along each pixel's camera ray, or along
            the camera's axis when `depth_kind` is `"planar"`; effects read
            it through `ray_depth`. `None` for a frame without depth (a
            photograph, a plate): coverage then says what is open sky.
        coverage: fraction of each pixel covered by geometry, `(H, W)` in [0, 1].
        normal: world-space unit normals `(H, W, 3)`, zero on sky, if rendered.
        object_id: index of the object seen in each pixel, `-1` on sky, if rendered.
        light_pass: the galaxy-engine VLS article's pass (the light white, everything else black),
            `(H, W)`, if rendered.
        glow_pass: the sun-overcasting article's overcast pass (the source enlarged and tinted,
            occluders shrunk and transparent black), `(H, W, 4)` RGBA, if rendered.
        glow_target: the VBex article's glow target, what the bloom spreads (the
            sky's sun spot, emissive surfaces and night lights, the
            atmosphere's glowing shell), `(H, W, 3)` linear HDR, if rendered.
        light_view: a depth map seen from the light and its camera (`LightView`),
            for what casts shadows outside the frame, if rendered; the
            volumetric fog reads it.
        silhouettes: the frame's silhouettes read beforehand (`Silhouettes`),
            which effects that read them take instead of reading them again:
            they depend on the frame alone, so a fit reads them once per
            frame (`Effect.frames_read_once`) rather than in every step.
        depth_kind: `"ray"` (the default; `render`, Mitsuba) or `"planar"`
            (Blender's Cycles `Z` pass; `camera.DEPTH_KINDS`), static.
    """

    color: Float[Array, "H W C"]
    depth: Float[Array, "H W"] | None
    coverage: Float[Array, "H W"]
    normal: Float[Array, "H W 3"] | None = None
    object_id: Int[Array, "H W"] | None = None
    light_pass: Float[Array, "H W"] | None = None
    glow_pass: Float[Array, "H W 4"] | None = None
    glow_target: Float[Array, "H W 3"] | None = None
    light_view: LightView | None = None
    silhouettes: Silhouettes | None = None
    depth_kind: DepthKind = eqx.field(static=True, default="ray")

    def __check_init__(self):
        """Shapes and dtypes at construction, each error naming the field.

        Leading batch axes are allowed (stacked frames for `jax.vmap`) as long
        as every field has the same ones. Values are not checked here (they may
        be traced); `check_buffers` checks them on the host.
        """
        if self.depth_kind not in DEPTH_KINDS:
            raise ValueError(f"buffers.depth_kind must be one of {', '.join(DEPTH_KINDS)}, got {self.depth_kind!r}")
        color_shape = _shape_of(self.color)
        if color_shape is None:
            return  # a filter spec or other non-array pytree (e.g. for eqx.partition)
        if len(color_shape) < 3 or color_shape[-1] not in (1, 2, 3, 4):
            raise ValueError(f"buffers.color must have shape (H, W, C) with C in 1..4, got {color_shape}")
        if min(color_shape[-3:-1]) < 1:
            raise ValueError(f"buffers.color must be at least 1x1, got shape {color_shape}")
        if not jnp.issubdtype(self.color.dtype, jnp.floating):
            raise ValueError(f"buffers.color must have a floating-point dtype, got {self.color.dtype}")
        plane = color_shape[:-1]
        expected = {"depth": plane, "coverage": plane, "normal": (*plane, 3), "object_id": plane,
                    "light_pass": plane, "glow_pass": (*plane, 4), "glow_target": (*plane, 3)}  # fmt: skip
        for name, shape in expected.items():
            value = getattr(self, name)
            actual = _shape_of(value)
            if actual is not None and actual != shape:
                raise ValueError(f"buffers.{name} must have shape {shape} to match color {color_shape}, got {actual}")
            kind = jnp.integer if name == "object_id" else jnp.floating
            if actual is not None and not jnp.issubdtype(value.dtype, kind):
                kind_text = "an integer" if kind is jnp.integer else "a floating-point"
                raise ValueError(f"buffers.{name} must have {kind_text} dtype, got {value.dtype}")
        if self.silhouettes is not None:
            for name in ("coverage", "uncovered_depth"):
                actual = _shape_of(getattr(self.silhouettes, name))
                if actual is not None and actual != plane:
                    raise ValueError(f"buffers.silhouettes.{name} must have shape {plane} to match color, got {actual}")
        if self.light_view is not None and not isinstance(self.light_view, LightView):
            raise ValueError(f"buffers.light_view must be a LightView or None, got {type(self.light_view).__name__}")

    def ray_depth(self, fov_x_deg: Float[ArrayLike, ""] | None = None) -> Float[Array, "H W"]:
        """Depth as distance along each pixel's camera ray (scene units, `+inf` on sky), what effects read.

        Ray depth is returned as stored. Planar depth is converted with the
        horizontal field of view `fov_x_deg` (degrees; an effect passes its
        own, so a fitted field of view converts consistently), which it then
        needs (`ValueError` naming it otherwise). Differentiable in `fov_x_deg`.
        """
        if self.depth is None:
            raise ValueError(
                "buffers.depth: this frame has no depth (a photograph or plate); an effect that measures distance "
                "cannot run on it"
            )
        if self.depth_kind == "ray":
            return self.depth
        if fov_x_deg is None:
            raise ValueError(
                "fov_x_deg: this frame's depth is planar (along the camera's axis) and converting it to distance "
                "along the ray needs the field of view (give the frame's, e.g. apply --fov-x-deg)"
            )
        return planar_to_ray_depth(self.depth, fov_x_deg=fov_x_deg)

    @property
    def height(self) -> int:
        return self.color.shape[-3]

    @property
    def width(self) -> int:
        return self.color.shape[-2]


def _shape_of(value) -> tuple[int, ...] | None:
    """The shape of an array-like field (NumPy, JAX, tracer, ShapeDtypeStruct); None for anything else."""
    shape = getattr(value, "shape", None)
    return tuple(shape) if shape is not None and hasattr(value, "dtype") else None


def coverage_from_depth(depth: Float[Array, "H W"]) -> Float[Array, "H W"]:
    """Hard coverage for buffers that carry none: 1 where depth is finite, 0 on sky."""
    return jnp.isfinite(depth).astype(jnp.result_type(depth, jnp.float32))
