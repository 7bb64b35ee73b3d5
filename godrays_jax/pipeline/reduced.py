"""A frame and an effect at a reduced resolution: the tuner's previews and the coarse phase of `fit`."""

import dataclasses
from collections.abc import Mapping

import equinox as eqx
import jax.numpy as jnp

from godrays_jax.effects.base import Effect
from godrays_jax.effects.fields import field_value, replace_fields, size_fields, units_of
from godrays_jax.primitives.buffers import Buffers
from godrays_jax.primitives.resample import box_pool, downsample_box


def pixel_fields(effect: Effect) -> tuple[str, ...]:
    """The fields measured in pixels: an effect's sizes (`size_fields`) whose owner (the effect or a part) has
    `units="px"`."""
    return tuple(name for name in size_fields(effect) if units_of(effect, name) == "px")


def downsample_buffers(buffers: Buffers, factor: int) -> Buffers:
    """The frame at `1 / factor` of its resolution, `ceil(H / factor) x ceil(W / factor)` pixels.

    Colour, coverage and the light and glow passes are box-averaged
    (`downsample_box`); depth takes each block's nearest surface (sky only
    where the whole block is sky); normals and object ids take each block's
    top-left pixel. Full-resolution pixel position `x` is position `x / factor`.
    """
    if factor == 1:
        return buffers

    def box(image):
        return None if image is None else downsample_box(image, factor)

    def plane(image):
        return None if image is None else downsample_box(image[..., None], factor)[..., 0]

    return Buffers(
        color=box(buffers.color),
        depth=None if buffers.depth is None else box_pool(buffers.depth, factor, pooling="min"),
        coverage=plane(buffers.coverage),
        normal=None if buffers.normal is None else buffers.normal[::factor, ::factor],
        object_id=None if buffers.object_id is None else buffers.object_id[::factor, ::factor],
        light_pass=plane(buffers.light_pass),
        glow_pass=box(buffers.glow_pass),
        glow_target=box(buffers.glow_target),
        light_view=buffers.light_view,  # the light's own view: the same scene at any resolution of the frame
        # No silhouettes: read off a frame, they are read again off the smaller one (`Effect.frames_read_once`).
        depth_kind=buffers.depth_kind,
    )


def downsample_frames(frame_data, factor: int) -> tuple:
    """A fit's frames (`problem.as_frames`'s `(frames, lights, targets, in_front, depths, others)`) at `1 / factor`
    of their resolution: the frames as `downsample_buffers`, every light's position in its pixels, the targets
    box-averaged."""
    frames, lights, targets, in_front, depths, others = frame_data
    others = [tuple(dataclasses.replace(light, xy=light.xy / factor) for light in beside) for beside in others]
    return (
        [downsample_buffers(frame, factor) for frame in frames], [light / factor for light in lights],
        [downsample_box(image, factor) for image in targets], in_front, depths, others,
    )  # fmt: skip


def scale_pixel_fields(effect: Effect, scale: float) -> Effect:
    """The effect with every field in `pixel_fields` multiplied by `scale` (to render at another resolution).

    Frame-unit sizes (the default) describe the same picture at any resolution and are left alone.
    """
    names = pixel_fields(effect)
    if not names or scale == 1:
        return effect
    return replace_fields(effect, {name: field_value(effect, name) * scale for name in names})


def clip_to_bounds(effect: Effect, bounds: Mapping[str, tuple[float, float]]) -> Effect:
    """The effect with each field named in `bounds` clipped to its `(low, high)`."""
    names = list(bounds)
    clipped = [jnp.clip(field_value(effect, n), *bounds[n]) for n in names]
    return eqx.tree_at(lambda e: [field_value(e, n) for n in names], effect, clipped)
