"""A fit's starts estimated from the frame itself: a medium bounded to a layer near the ground, or to a room.

The shipped presets of a layered medium (`VolumetricFog`) start with no top
(`layer_top` on its upper bound), where the top has no gradient: a fit from
them can never find a fog bank that the camera stands in. `ground_layer_start`
reads a finite layer from the frames' geometry, so `fit` has a start from which
the top moves (`godrays-jax fit` adds it to the model's presets). In a frame
with no sky (a room) the presets' medium reaches far beyond the walls, and the
light crosses all of it on its way in: `enclosed_start` bounds the medium to
the surfaces seen, with no top (a beam from a high window crosses the whole
room). Where a depth map seen from the light casts the shadows, `thin_slabs_start`
keeps the depth buffer's own from shading what the light reaches, and
`thin_slabs_room_start` also ends the medium at the farthest wall. A room whose
windows show the sky, which the fog reads as closed beyond its edges, lets the
light in only through them: `closed_room_start` gives it thin slabs and a medium
that ends at the farthest wall.
"""

from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from godrays_jax.effects.base import Effect
from godrays_jax.effects.fields import field_metadata, field_value, replace_fields
from godrays_jax.kernels.lens import view_directions
from godrays_jax.kernels.shadow_reading import enclosure
from godrays_jax.primitives.buffers import Buffers

GROUND_LAYER_FIELDS: tuple[str, ...] = ("layer_top", "medium.extinction", "medium.max_distance", "fov_x_deg")
"""The fields an effect needs for `ground_layer_start` (scene units; the field of view in degrees)."""

GROUND_PERCENTILE = 5.0
"""The percentile of the visible surfaces' heights taken as the ground: the lowest surfaces, not a stray pixel."""


def _surfaces(frames: Sequence[Buffers], fov_x_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Ray depth and height above the camera (its up axis), scene units, of every pixel mostly covered by a surface."""
    depths, heights = [], []
    for frame in frames:
        depth = np.asarray(frame.ray_depth(jnp.asarray(fov_x_deg, jnp.float32)), np.float64)
        up = np.asarray(view_directions(frame.height, frame.width, fov_x_deg=fov_x_deg))[..., 1]
        covered = np.isfinite(depth) & (np.asarray(frame.coverage) >= 0.5)
        depths.append(depth[covered])
        heights.append((depth * up)[covered])
    return np.concatenate(depths), np.concatenate(heights)


def ground_layer_start(effect: Effect, frames: Buffers | Sequence[Buffers]) -> Effect | None:
    """`effect` with a fog layer near the ground read from the frames' depth: a start for `fit(..., starts=...)`.

    The frames' visible surfaces (coverage at least one half, finite depth),
    placed by ray depth and `effect.fov_x_deg` in the camera's frame (scene
    units, height along the camera's up axis), give:

    - `layer_top`: as far above the camera as the ground (the
      `GROUND_PERCENTILE`th percentile of the surfaces' heights) is below
      it, a layer the camera stands in, with a top that has a gradient;
    - `medium.extinction`: one over the surfaces' median depth (an optical
      depth of one to the median surface);
    - `medium.max_distance`: the farthest surface's depth (the medium holds
      every visible surface).

    Each is clipped into its field's bounds; every other field is `effect`'s.
    `None` when the effect lacks one of `GROUND_LAYER_FIELDS`, when no pixel
    shows a surface, or when the ground is not below the camera (no layer
    to estimate). Not differentiable: a start, read once on the host.
    """
    frames = [frames] if isinstance(frames, Buffers) else list(frames)
    infos = field_metadata(effect)
    if any(name not in infos for name in GROUND_LAYER_FIELDS) or any(frame.depth is None for frame in frames):
        return None
    depths, heights = _surfaces(frames, float(field_value(effect, "fov_x_deg")))
    if depths.size == 0:
        return None
    ground = float(np.percentile(heights, GROUND_PERCENTILE))
    if not ground < 0.0:
        return None
    values = {
        "layer_top": -ground,
        "medium.extinction": 1.0 / max(float(np.median(depths)), 1e-6),
        "medium.max_distance": float(np.max(depths)),
    }
    return _with_values(effect, values)


def enclosed_start(effect: Effect, frames: Buffers | Sequence[Buffers]) -> Effect | None:
    """`effect` with its medium bounded to the room its frames show: a start for `fit(..., starts=...)` when no pixel
    of any frame is sky.

    `medium.max_distance` is the farthest surface's depth, `medium.extinction`
    one over the surfaces' median depth, and `layer_top` its upper bound (no
    top), each clipped into its field's bounds; every other field is
    `effect`'s. `None` when a frame has sky (a depth that is not finite, or
    coverage below one half), a surface at the eye (depth 0), or no depth,
    or when the effect lacks one of `GROUND_LAYER_FIELDS`. Not
    differentiable: a start, read once on the host.
    """
    frames = [frames] if isinstance(frames, Buffers) else list(frames)
    infos = field_metadata(effect)
    if any(name not in infos for name in GROUND_LAYER_FIELDS) or any(frame.depth is None for frame in frames):
        return None
    depths = [np.asarray(frame.ray_depth(jnp.asarray(field_value(effect, "fov_x_deg"), jnp.float32))) for frame in frames]
    closed = all(
        np.all(np.isfinite(depth)) and np.all(depth > 0) and np.all(np.asarray(frame.coverage) >= 0.5)
        for frame, depth in zip(frames, depths)
    )  # fmt: skip
    if not closed:
        return None
    every = np.concatenate([depth.ravel() for depth in depths]).astype(np.float64)
    values = {
        "layer_top": infos["layer_top"].bounds[1],
        "medium.extinction": 1.0 / float(np.median(every)),
        "medium.max_distance": float(np.max(every)),
    }
    return _with_values(effect, values)


THIN_SLABS = 0.01
"""`thin_slabs_start`'s `thickness`: the depth buffer's surfaces a hundredth of their depth deep."""


def thin_slabs_start(effect: Effect, frames: Buffers | Sequence[Buffers]) -> Effect | None:
    """`effect` with thin slabs (`thickness` `THIN_SLABS`): a start for `fit(..., starts=...)` when a frame carries
    a depth map seen from the light (`Buffers.light_view`).

    The map casts the shadows of what the frame shows too. The depth buffer's slabs, at the presets' thickness,
    also shade the points that lie behind a surface on screen while the light reaches them around it: a beam that
    a window in view lets in, seen below the wall above the window, is dimmed where the map lets it through. From
    thick slabs a fit of such a frame thins the medium to keep the beam dim, and stays there (benchmarks/README.md,
    "A sunbeam through a window in view"). `None` without a map, or for an effect without `thickness`.
    """
    frames = [frames] if isinstance(frames, Buffers) else list(frames)
    if "thickness" not in field_metadata(effect) or all(frame.light_view is None for frame in frames):
        return None
    return _with_values(effect, {"thickness": THIN_SLABS})


def thin_slabs_room_start(effect: Effect, frames: Buffers | Sequence[Buffers]) -> Effect | None:
    """`thin_slabs_start` with the medium ending at the farthest surface its frames show (finite depth above 0):
    a second start for `fit(..., starts=...)` where a frame carries a depth map seen from the light.

    A room lit through its windows, the map casting their shadows, holds its haze within its walls; from the
    presets' medium, which reaches several rooms beyond them, a fit has far to go and may stop in a thin medium
    reaching far (benchmarks/README.md, "A sunbeam through a window behind the camera"). `medium.max_distance`
    is clipped into its bounds; every other field is `thin_slabs_start`'s. `None` where that is, for an effect
    without one of `CLOSED_ROOM_FIELDS`, a frame without depth or frames with no finite depth above 0. Not
    differentiable: a start, read once on the host.
    """
    thin = thin_slabs_start(effect, frames)
    frames = [frames] if isinstance(frames, Buffers) else list(frames)
    if thin is None or any(name not in field_metadata(effect) for name in CLOSED_ROOM_FIELDS):
        return None
    if any(frame.depth is None for frame in frames):
        return None
    fov = jnp.asarray(field_value(effect, "fov_x_deg"), jnp.float32)
    depths = [np.asarray(frame.ray_depth(fov)) for frame in frames]
    finite = np.concatenate([depth[np.isfinite(depth) & (depth > 0)] for depth in depths])
    if finite.size == 0:
        return None
    return _with_values(thin, {"medium.max_distance": float(np.max(finite))})


CLOSED_ROOM_FIELDS: tuple[str, ...] = ("thickness", "medium.max_distance", "fov_x_deg")
"""The fields an effect needs for `closed_room_start` (the field of view in degrees)."""


def closed_room_start(effect: Effect, frames: Buffers | Sequence[Buffers], *, wholly: bool = False) -> Effect | None:
    """`effect` with thin slabs (`thickness` `THIN_SLABS`) and its medium ending at the farthest surface its frames
    show: a start for `fit(..., starts=...)` when the fog reads every frame as closed beyond its edges
    (`shadow_reading.enclosure` above 0: a room, its windows) and none carries a depth map seen from the light.

    Read closed, a room takes the light in only through the openings its frames show. A beam from a window in view
    lies on screen behind the wall above the window, which slabs of the presets' depth shade; and the presets'
    medium, reaching far beyond the window, fills the window's own pixels with the haze outside, lit. From the
    presets a fit keeps both dim by thinning the medium (benchmarks/README.md, "A sunbeam through a window in
    view"). `medium.max_distance` is the farthest finite depth, clipped into its bounds; every other field is
    `effect`'s. `None` for an effect without one of `CLOSED_ROOM_FIELDS`, a frame without depth, with a light
    view or with a surface at the eye (depth 0: no room, as for `enclosed_start`), or one read as open; with `wholly`, also one read as closed only in part (`enclosure` below 1), so that
    the start is the one `godrays-jax fit` takes in place of every other (docs/fitting.md). Not differentiable: a
    start, read once on the host.
    """
    frames = [frames] if isinstance(frames, Buffers) else list(frames)
    infos = field_metadata(effect)
    if any(name not in infos for name in CLOSED_ROOM_FIELDS) or any(
        frame.depth is None or frame.light_view is not None for frame in frames
    ):
        return None
    fov = jnp.asarray(field_value(effect, "fov_x_deg"), jnp.float32)
    depths = [np.asarray(frame.ray_depth(fov)) for frame in frames]
    if any(np.any(depth <= 0) for depth in depths):
        return None
    closed = [float(enclosure(jnp.asarray(depth))) for depth in depths]
    if not all(value >= 1.0 if wholly else value > 0 for value in closed):
        return None
    finite = np.concatenate([depth[np.isfinite(depth)] for depth in depths])
    if finite.size == 0:
        return None
    return _with_values(effect, {"thickness": THIN_SLABS, "medium.max_distance": float(np.max(finite))})


def _with_values(effect: Effect, values: dict[str, float]) -> Effect:
    """`effect` with `values` for its fields by name, each clipped into its field's bounds."""
    infos = field_metadata(effect)
    dtype = jnp.result_type(field_value(effect, next(iter(values))))
    return replace_fields(
        effect,
        {name: jnp.asarray(np.clip(value, *infos[name].bounds), dtype) for name, value in values.items()},
    )
