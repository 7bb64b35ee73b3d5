"""Each view segment's visibility of the light, read from the depth buffer along lines through the light's position.

The light is the point `S = light_depth * d_L` (`d_L` = `lens.light_direction`)
or, for `light_depth = inf`, the sun in direction `d_L`; a surface seen at
pixel `q`, depth `D_q` (distance along its camera ray `d_q`, scene units), is a
slab `[D_q, D_q * (1 + thickness)]` along that ray, as in
`shadow_samples.segment_visibility`.

Why lines. A point `X` on pixel `p`'s view ray, the light and the camera span
one plane, and the shadow ray from `X` to the light crosses exactly the camera
rays of the pixels on the screen segment from `p` toward the light's position
(away from it, out to the screen's edge, for a light behind the camera: there
the path runs away from the point reflection of `light_xy` through the image
centre, the "hub" below). Within that plane every point has one coordinate that
a shadow ray keeps: `s = light_depth * angle(O - S, P - S)`, the angle at the
light between the camera and the point, times the light's distance
(`line_coordinate`; for the sun `D * |d x d_L|`, the distance from the axis
through the camera toward the sun). So along one screen line through the hub
every texel's slab is an interval of `s`, and a point is in shadow where the
intervals of the texels between it and the light cover its `s`: the test
`segment_visibility` makes at a few samples, here made for every texel on the
line and every distance along the view ray at once. Reading it this way
removes the three samplings whose crawl under a camera pan makes the samples'
reading shimmer (benchmarks/README.md, "Shadows read per screen line through
the light").

Discretised: `num_lines` lines through the hub, each cut into cells `cell_px`
pixels long outward from it; the four texels around each cell's centre, by
bilinear weights, each one's interval spanning the cell's range of `s` (so
that consecutive cells meet), with linear faces `edge_softness` times its nearer `s` wide (a
slab thinner than its two faces is a tent); their blend's maximum along the
line from the light is the coverage, on `num_bins` bins of `s` even in
`log s` over `[s_max / 5e3, s_max]`, `s_max = pi * max_distance`, beyond every
`s` inside the medium, the lowest holding what covers any `s` below it. Each face is spread over at most
`_FACE_BINS` bins. A pixel reads its two nearest lines up to its own cell, and
each segment `[lower, upper]` of its view ray takes the mean coverage over its
range of `s` (at least one bin wide), so a shadow's edge inside a segment
counts in proportion. Sky, the emitter (a slab reaching the light) and
texels off screen block nothing, unless the frame is read as closed beyond its
edges (`enclosed`, `shadow_reading.enclosure`): then, for a light in front of
the camera, the first cell on screen of each line from the light (where a
shadow ray leaves the screen) and the cell off screen just before it, which
reads the edge's texels, have their near faces moved toward the eye
(at `enclosed = 1` to it), so that a shadow ray that leaves the screen in front
of the far face of the surface seen there is shaded, as by the room's ceiling
and walls out of view.

Where the lines go. With the hub on screen the lines are at fixed angles
`2 pi k / num_lines` and the cells start at the hub: under a pan they ride
with the light. With the hub off screen the lines fan evenly over the angle
the screen spans as seen from it and the cells start at the screen's nearest
point, in coordinates relative to the screen's centre, so that a light up to
`MAX_LIGHT_PX` away keeps float32 precision; those lines do not ride with the
light. Where the lines lie is a sampling choice and carries no gradient; the
light's position, depth and direction reach the result through `s`, the
texels read and the lines' shared hub.

Memory is `num_lines * num_bins` times the cells a line has (its length over
`cell_px`, a frame's diagonal), whatever the frame's size, and the reads of
`_READ_CHUNK` pixels at a time, four rows of `num_bins` each.
"""

import functools
import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from godrays_jax.kernels.bounded_medium import dot, light_geometry
from godrays_jax.kernels.lens import rays_through
from godrays_jax.primitives.camera import focal_length_px
from godrays_jax.primitives.checks import check_light, check_scalar, is_static_int
from godrays_jax.primitives.sampling import bilinear_corners

# The bins' span, s_max / s_min: below s_min (a point within this fraction of the medium's reach of the axis toward
# the light) the coverage is the lowest bin's.
_BIN_SPAN = 5e3
# A slab face's ramp is spread over at most this many bins; a softer face is cut to it (still reaching 1).
_FACE_BINS = 2
# The pixels whose reads of the table are held at once (`segment_visibility_by_lines`).
_READ_CHUNK = 1 << 14
REFERENCE_SIDE = 320
"""The frame side (pixels, the larger side) up to which the fog samples by the pixel: its lines' cells are one
pixel long (`default_cell_px`) and its march rays `resolution_factor` pixels apart (`effects.volumetric`'s
`march_factor`); on a larger frame each keeps its fraction of the frame, so a preset looks the same at any size."""


def default_cell_px(height: int, width: int) -> float:
    """The cells' length in pixels on a `height x width` frame: 1 up to 320 pixels on its larger side, the same
    fraction of that side beyond, so a frame's lines hold the same cells at any size."""
    return max(1.0, max(height, width) / REFERENCE_SIDE)


def line_coordinate(
    distance: Float[ArrayLike, "*S"],
    sine: Float[ArrayLike, "*S"],
    cosine: Float[ArrayLike, "*S"],
    inverse_depth: Float[ArrayLike, ""],
) -> Float[Array, "*S"]:
    """`s` of the point `distance * d` (scene units) whose camera ray `d` makes the angle of `sine`, `cosine`
    with the light's direction: `light_depth` times the angle at the light between the camera and the point
    (`inverse_depth = 1 / light_depth`; 0, the sun: `distance * sine`). Along a camera ray it grows with
    `distance`; every point of a shadow ray has the same `s`."""
    finite = inverse_depth > 0
    k = jnp.where(finite, inverse_depth, 1.0)
    across, along = distance * sine * k, 1.0 - distance * cosine * k
    # At the light itself the angle is 0 (the atan2 of two zeros has no gradient).
    at_light = (jnp.abs(across) < 1e-30) & (jnp.abs(along) < 1e-30)
    angle = jnp.arctan2(across, jnp.where(at_light, 1.0, along))
    return jnp.where(finite, angle / k, distance * sine)


def _bin_coordinate(s, s_min, log_step):
    """Node coordinate of `s`: node 0 at s = 0, node i >= 1 at `s_min * exp((i - 1) * log_step)`; linear below s_min."""
    above = 1.0 + jnp.log(jnp.maximum(s, s_min) / s_min) / log_step
    return jnp.where(s < s_min, s / s_min, above)


def _coordinate_at_bin(b, s_min, log_step):
    """`_bin_coordinate`'s inverse."""
    return jnp.where(b < 1.0, b * s_min, s_min * jnp.exp((jnp.maximum(b, 1.0) - 1.0) * log_step))


def _off_axis(x, y, toward, height, width, focal):
    """The sine and cosine of the angle between the camera rays through pixel positions `(x, y)` and the light."""
    rays = rays_through(x, y, height, width, focal)
    rays = rays / jnp.linalg.norm(rays, axis=-1, keepdims=True)
    across = jnp.cross(rays, toward)
    # Floored: on the light's own ray the sine's square root would have no gradient.
    return jnp.sqrt(jnp.maximum(dot(across, across), 1e-30)), dot(rays, toward)


class _Lines:
    """Where the lines and cells lie: the hub, and for a hub off screen the frame relative to the screen's centre."""

    def __init__(self, hub, height, width, num_lines, cells, cell_px, dtype):
        self.num_lines, self.cells, self.step = num_lines, cells, cell_px
        self.hub = hub
        self.centre = jnp.asarray([0.5 * width, 0.5 * height], dtype)
        held = jax.lax.stop_gradient(hub)
        self.full = (held[0] >= 0) & (held[0] <= width) & (held[1] >= 0) & (held[1] <= height)
        offset = self.centre - hub
        distance = jnp.sqrt(jnp.maximum(dot(offset, offset), 1e-30))
        apart = distance > 1e-6
        self.axis = jnp.where(apart, offset / jnp.where(apart, distance, 1.0), jnp.asarray([1.0, 0.0], dtype))
        self.normal = jnp.stack([-self.axis[1], self.axis[0]])
        self.distance = distance
        corners = jnp.asarray([[0.0, 0.0], [width, 0.0], [0.0, height], [width, height]], dtype)
        angles = jax.lax.stop_gradient(self._relative(corners)[0])
        low, high = jnp.min(angles), jnp.max(angles)
        self.low = low
        self.spacing = jnp.where(self.full, 2 * math.pi / num_lines, (high - low) / max(num_lines - 1, 1))
        nearest = jnp.hypot(jnp.maximum(jnp.maximum(-held[0], held[0] - width), 0.0),
                            jnp.maximum(jnp.maximum(-held[1], held[1] - height), 0.0))  # fmt: skip
        # The first cell's start, as an offset from the distance between the hub and the centre.
        self.start = jnp.where(self.full, -distance, jax.lax.stop_gradient(nearest - distance))

    def _relative(self, points):
        """The angle from the hub relative to the direction toward the centre, and the distance from the hub
        minus the hub's distance to the centre, of `points` (`(..., 2)`), both precise for a far hub."""
        along = dot(points - self.centre, self.axis)
        across = dot(points - self.centre, self.normal)
        ahead = along + self.distance
        squared = ahead * ahead + across * across
        # A point on the hub: angle 0, distance 0 (atan2 and the square root of zeros have no gradient).
        apart = squared > 0
        angle = jnp.arctan2(across, jnp.where(apart, ahead, 1.0))
        radius = jnp.sqrt(jnp.where(apart, squared, 1.0))
        offset = (along * (along + 2 * self.distance) + across * across) / (radius + self.distance)
        return angle, jnp.where(apart, offset, -self.distance)

    def positions(self, radial_shift):
        """The `(num_lines, cells)` pixel positions `(x, y)` of the cells' centres moved `radial_shift` cells outward."""
        index = jnp.arange(self.num_lines, dtype=self.hub.dtype)[:, None]
        offset = self.start + (jnp.arange(self.cells, dtype=self.hub.dtype)[None, :] + 0.5 + radial_shift) * self.step
        # On screen: fixed angles from the hub.
        angle = self.spacing * index
        radius = jnp.maximum(offset + self.distance, 0.0)
        x_on, y_on = self.hub[0] + radius * jnp.cos(angle), self.hub[1] + radius * jnp.sin(angle)
        # Off screen: angles relative to the centre's direction, positions relative to the centre.
        relative = self.low + self.spacing * index
        along = offset * jnp.cos(relative) - 2 * self.distance * jnp.sin(0.5 * relative) ** 2
        across = (self.distance + offset) * jnp.sin(relative)
        x_off = self.centre[0] + along * self.axis[0] + across * self.normal[0]
        y_off = self.centre[1] + along * self.axis[1] + across * self.normal[1]
        return jnp.where(self.full, x_on, x_off), jnp.where(self.full, y_on, y_off)

    def coordinates(self, points):
        """Each point's fractional line index (wrapping on screen) and cell index."""
        dx, dy = points[..., 0] - self.hub[0], points[..., 1] - self.hub[1]
        on_hub = dx * dx + dy * dy < 1e-24  # angle 0 there (atan2 of zeros has no gradient)
        on_line = jnp.mod(jnp.arctan2(dy, jnp.where(on_hub, 1.0, dx)), 2 * math.pi) / self.spacing
        angle, offset = self._relative(points)
        off_line = jnp.clip((angle - self.low) / self.spacing, 0.0, self.num_lines - 1.0)
        line = jnp.where(self.full, on_line, off_line)
        cell = jnp.clip((offset - self.start) / self.step - 0.5, 0.0, self.cells - 1.0)
        return line, cell


def _face_deltas(start, width, s_min, log_step, num_bins, lowest=0):
    """The bins (`(..., _FACE_BINS)`) a ramp from 0 at `start` to 1 at `start + width` rises over, from bin
    `lowest` on, and its rise in each, summing to 1: its values at the bins' centres are the running sums."""
    held = jax.lax.stop_gradient(start)
    first = jnp.ceil(jnp.log(jnp.maximum(held, s_min * 1e-3) / s_min) / log_step)
    first = jnp.clip(first, lowest, num_bins).astype(jnp.int32)
    index = first[..., None] + jnp.arange(_FACE_BINS)
    centre = s_min * jnp.exp(index.astype(start.dtype) * log_step)
    # A face narrower than a thousandth of the first bin (a surface at the eye: none at all) rises as a step: a
    # ramp that steep falls between the bins' centres all the same, and its derivatives stay finite.
    value = jnp.clip((centre - start[..., None]) / jnp.maximum(width, s_min * 1e-3)[..., None], 0.0, 1.0)
    value = value.at[..., -1].set(1.0)
    return index, jnp.diff(value, axis=-1, prepend=0.0)


def _coverage_table(depth, lines, toward, inverse, focal, thickness, softness, s_min, log_step, num_bins, in_front,
                    enclosed):  # fmt: skip
    """Each cell's coverage at the bins, the maximum of its texels' blend from the light out to it:
    `(cells, num_lines, num_bins)`, and whether its cells are stored last first (a bool, traced when `in_front`
    is). `enclosed`: how closed the frame is beyond its edges (the module's docstring)."""
    height, width = depth.shape
    dtype = depth.dtype
    x, y = lines.positions(0.0)
    row, col, weight = bilinear_corners(x - 0.5, y - 0.5, height, width)
    front = depth[row, col]  # (4, lines, cells)
    on_screen = (x >= 0) & (x <= width) & (y >= 0) & (y <= height)
    # Where a shadow ray toward a light in front leaves the screen: the first cell on screen from the light (none
    # when the hub is on screen), and the cell off screen just before it, which the pixels along the edge read with
    # it (its texels the edge's, clamped). A light behind the camera may shine through an opening behind it, which
    # the frame cannot show: its rays leave as before.
    closed = jnp.asarray(enclosed, dtype) * jnp.asarray(in_front, dtype)
    before = jnp.concatenate([jnp.broadcast_to(lines.full, (x.shape[0], 1)), on_screen[:, :-1]], axis=1)
    after = jnp.concatenate([on_screen[:, 1:], jnp.zeros_like(on_screen[:, :1])], axis=1)
    leaving = (on_screen & ~before) | (~on_screen & after & (closed > 0))
    # A surface at the eye (depth 0) is a slab of no depth: it blocks nothing, as the sky does not.
    blocks = jnp.isfinite(front) & (front > 0) & (on_screen | leaving) & (front * (1 + thickness) * inverse < 1.0)
    front = jnp.where(blocks, front, 1.0)
    ends = [_off_axis(*lines.positions(shift), toward, height, width, focal) for shift in (-0.5, 0.5)]
    near = [line_coordinate(front, sine, cosine, inverse) for sine, cosine in ends]
    far = [line_coordinate(front * (1 + thickness), sine, cosine, inverse) for sine, cosine in ends]
    low, high = jnp.minimum(*near), jnp.maximum(*far)
    low = jnp.where(leaving, (1.0 - closed) * low, low)
    face = jnp.minimum(softness * low, 0.5 * (high - low))
    rise_at, rise = _face_deltas(low, face, s_min, log_step, num_bins)
    # The lowest bin holds what covers any `s` below `s_min` (not what covers `s_min` itself): every point there reads
    # it, and within a pixel or so of the light every point of a view ray is there, while the slabs that shadow them
    # end there too (the light's own pixel on a surface that hides it would otherwise read lit).
    fall_at, fall = _face_deltas(high - face, face, s_min, log_step, num_bins, lowest=1)
    amount = jnp.where(blocks, weight, 0.0)[..., None]
    # Per cell (the scan's axis first): each line's texels' face changes and the bins they fall in, a face's rise
    # past the last bin (beyond the medium) dropped.
    index = jnp.moveaxis(jnp.concatenate([rise_at, fall_at], axis=-1), 2, 0)  # (cells, 4, lines, 2 * _FACE_BINS)
    change = jnp.moveaxis(jnp.concatenate([rise, -fall], axis=-1) * amount, 2, 0)
    num_lines = x.shape[0]
    bins = jnp.arange(num_bins, dtype=jnp.int32)

    def along_line(covered, cell):
        # The blend's coverage at the bins: the running sum of its changes, each counted at every bin from its own
        # on (per cell, where a table of every cell's changes would be the size of the coverage's); its maximum from
        # the light out to this cell. A sum of the few changes as steps, in one fused pass over the bins: a scatter
        # of them and a cumulative sum cost a pass each and more (benchmarks/README.md, "The fit as users run it").
        cell_index, cell_change = cell  # (4, lines, 2 * _FACE_BINS)
        steps = (
            jnp.where(bins >= cell_index[corner, :, k, None], cell_change[corner, :, k, None], 0.0)
            for corner in range(cell_index.shape[0]) for k in range(cell_index.shape[-1])
        )  # fmt: skip
        covered = jnp.maximum(covered, functools.reduce(jnp.add, steps))
        return covered, covered

    start = jnp.zeros((num_lines, num_bins), dtype)
    if isinstance(in_front, bool):
        return jax.lax.scan(along_line, start, (index, change), reverse=not in_front)[1], False
    # A light whose side is traced (a batch's frames, each its own): one scan over the cells in the light's order,
    # each step taking its cell from the light's side (not a choice between the cells' changes and their reverse:
    # two copies of them), instead of a scan each way and a choice between two tables.
    inward = jnp.logical_not(in_front)
    last = index.shape[0] - 1

    def from_the_light(covered, step):
        cell = jnp.where(inward, last - step, step)
        return along_line(covered, (index[cell], change[cell]))

    return jax.lax.scan(from_the_light, start, jnp.arange(last + 1))[1], inward


def _prefix_integral(covered, s_min, log_step):
    """The integral over `s` of a coverage at the bins (`(..., num_bins)`) from 0 to each node, by trapezoids at the
    nodes, node 0 (s = 0) holding the lowest bin's coverage: `(..., num_bins + 1)`."""
    num_bins = covered.shape[-1]
    gaps = jnp.diff(_coordinate_at_bin(jnp.arange(num_bins + 1, dtype=covered.dtype), s_min, log_step))
    nodes = jnp.concatenate([covered[..., :1], covered], axis=-1)
    steps = 0.5 * (nodes[..., 1:] + nodes[..., :-1]) * gaps
    return jnp.concatenate([jnp.zeros_like(steps[..., :1]), jnp.cumsum(steps, axis=-1)], axis=-1)


def segment_visibility_by_lines(
    depth: Float[Array, "H W"],
    light_xy: Float[ArrayLike, "2"],
    pixel_xy: Float[Array, "h w 2"],
    lower: Float[Array, "h w M"],
    upper: Float[Array, "h w M"],
    *,
    fov_x_deg: Float[ArrayLike, ""],
    light_depth: Float[ArrayLike, ""] = math.inf,
    light_in_front: Bool[ArrayLike, ""] | bool = True,
    thickness: Float[ArrayLike, ""],
    edge_softness: Float[ArrayLike, ""],
    max_distance: Float[ArrayLike, ""],
    num_lines: int = 512,
    num_bins: int = 192,
    cell_px: float | None = None,
    enclosed: Float[ArrayLike, ""] = 0.0,
) -> Float[Array, "h w M"]:
    """How much of the light reaches each segment `[lower, upper]` of the view rays through `pixel_xy`, in [0, 1]:
    the mean over the segment's range of `s` (the module's docstring).

    Args:
        depth: the frame's distance along each camera ray, scene units, `+inf` on sky.
        light_xy: the light's projected position in pixels (mirrored through the
            camera plane when behind it, as `camera.project_point`), any real value.
        pixel_xy: the pixel positions whose view rays are read (x right, y down,
            pixel centres at `i + 0.5`), on screen or near it.
        lower, upper: each segment's ends along those rays, scene units, `lower <= upper`.
        fov_x_deg: horizontal field of view in degrees, in (0, 180).
        light_depth: the light's distance along its camera ray, scene units; `inf`: the sun.
        light_in_front: whether the light is in front of the camera.
        thickness: each surface's slab depth as a fraction of its own depth, >= 0.
        edge_softness: the width of the slab's soft faces, a fraction of `s`, > 0.
        max_distance: the medium's radius around the camera (scene units): the
            bins reach the largest `s` inside it; a segment beyond reads the last.
        num_lines: lines through the light's position (static int, >= 2).
        num_bins: bins of `s` (static int, >= 2).
        cell_px: the cells' length in pixels (a Python number > 0); None:
            `default_cell_px`, one pixel on a frame of 320 pixels.
        enclosed: how closed the frame is beyond its edges, in [0, 1] (`shadow_reading.enclosure`): 0, texels
            off screen block nothing; 1, a shadow ray toward a light in front of the camera that leaves the
            screen in front of the far face of the surface seen where it leaves is shaded. No gradient.
    """
    for name, count in (("num_lines", num_lines), ("num_bins", num_bins)):
        if not is_static_int(count) or count < 2:
            raise ValueError(f"{name} must be a Python int >= 2, got {count!r}")
    if jnp.ndim(depth) != 2:
        raise ValueError(f"depth must have shape (H, W), got shape {jnp.shape(depth)}")
    light_xy = check_light(light_xy)
    for name, value in (("fov_x_deg", fov_x_deg), ("light_depth", light_depth), ("thickness", thickness),
                        ("edge_softness", edge_softness), ("max_distance", max_distance),
                        ("enclosed", enclosed)):  # fmt: skip
        check_scalar(value, name)
    if jnp.ndim(pixel_xy) != 3 or jnp.shape(pixel_xy)[-1] != 2:
        raise ValueError(f"pixel_xy must have shape (h, w, 2), got shape {jnp.shape(pixel_xy)}")
    for name, bounds in (("lower", lower), ("upper", upper)):
        if jnp.ndim(bounds) != 3 or jnp.shape(bounds)[:2] != jnp.shape(pixel_xy)[:2]:
            raise ValueError(f"{name} must have shape (h, w, M) matching pixel_xy, got shape {jnp.shape(bounds)}")
    height, width = depth.shape
    if cell_px is None:
        cell_px = default_cell_px(height, width)
    if not isinstance(cell_px, (int, float)) or isinstance(cell_px, bool) or not cell_px > 0:
        raise ValueError(f"cell_px must be a Python number > 0, got {cell_px!r}")
    dtype = jnp.result_type(depth, jnp.float32)
    depth = jnp.asarray(depth, dtype)
    pixel_xy, lower, upper = (jnp.asarray(a, dtype) for a in (pixel_xy, lower, upper))
    static_front = light_in_front if isinstance(light_in_front, bool) else None
    return _visibility(
        depth, jnp.asarray(light_xy, dtype), pixel_xy, lower, upper, fov_x_deg, light_depth,
        jnp.asarray(light_in_front), thickness, edge_softness, max_distance, enclosed, num_lines=num_lines,
        num_bins=num_bins, cell_px=float(cell_px), static_front=static_front,
    )  # fmt: skip


@functools.partial(jax.jit, static_argnames=("num_lines", "num_bins", "cell_px", "static_front"))
def _visibility(depth, light_xy, pixel_xy, lower, upper, fov_x_deg, light_depth, light_in_front, thickness,
                edge_softness, max_distance, enclosed, *, num_lines, num_bins, cell_px, static_front):  # fmt: skip
    """`segment_visibility_by_lines` after its checks, compiled once per shape and count (called eagerly, a scan
    over a function defined in the call would be traced and compiled again on every call); `static_front`: the
    light's side when the caller gave it as a Python bool, else None (`light_in_front` traced)."""
    read = lines_reader(
        depth, light_xy, fov_x_deg=fov_x_deg, light_depth=light_depth,
        light_in_front=light_in_front if static_front is None else static_front, thickness=thickness,
        edge_softness=edge_softness, max_distance=max_distance, num_lines=num_lines, num_bins=num_bins, cell_px=cell_px,
        enclosed=enclosed,
    )  # fmt: skip
    return read(pixel_xy, lower, upper)


def lines_reader(
    depth, light_xy, *, fov_x_deg, light_depth, light_in_front, thickness, edge_softness, max_distance, num_lines,
    num_bins, cell_px, enclosed=0.0,
) -> Callable[[Array, Array, Array], Array]:
    """The lines' table of a frame (`depth` in the caller's dtype, `light_xy` as `segment_visibility_by_lines`
    takes them, checked), and the function `read(pixel_xy, lower, upper)` that reads segments from it: built once,
    read by every band of a march. `light_in_front` a Python bool or a traced one."""
    height, width = depth.shape
    dtype = depth.dtype
    in_front = light_in_front
    focal = focal_length_px(width, fov_x_deg, dtype)
    toward, inverse = light_geometry(light_xy, height, width, fov_x_deg, light_depth, in_front, dtype)
    centre = jnp.asarray([0.5 * width, 0.5 * height], dtype)
    hub = jnp.where(in_front, light_xy, 2 * centre - light_xy)
    cells = int(math.ceil(math.hypot(width, height) / cell_px)) + 2
    lines = _Lines(hub, height, width, num_lines, cells, cell_px, dtype)
    # Every point within `max_distance` of the camera has `s` below pi * max_distance, whatever the light's distance
    # (for the sun, below max_distance): the bins' reach, held where it lies (a sampling choice, as the segments').
    s_max = jax.lax.stop_gradient(jnp.maximum(math.pi * jnp.asarray(max_distance, dtype), 1e-12))
    s_min = s_max / _BIN_SPAN
    log_step = math.log(_BIN_SPAN) / (num_bins - 1)
    thickness = jnp.asarray(thickness, dtype)
    softness = jnp.maximum(jnp.asarray(edge_softness, dtype), 1e-6)
    enclosed = jax.lax.stop_gradient(jnp.asarray(enclosed, dtype))
    covered, reversed_cells = _coverage_table(depth, lines, toward, inverse, focal, thickness, softness, s_min,
                                              log_step, num_bins, in_front, enclosed)  # fmt: skip

    def read(pixel_xy, lower, upper):
        """The visibility of the segments `[lower, upper]` (`(n, M)`) of the rays through `pixel_xy` (`(n, 2)`)."""
        # Each pixel's four (line, cell) corners and their weights; each segment's ends as node coordinates.
        line, cell = lines.coordinates(pixel_xy)
        line0, cell0 = jnp.floor(line), jnp.floor(cell)
        line_frac, cell_frac = (line - line0)[..., None], (cell - cell0)[..., None]
        line0, cell0 = line0.astype(jnp.int32), cell0.astype(jnp.int32)

        def stored(cell):  # where the table holds a cell
            cell = cell.clip(0, cells - 1)
            return jnp.where(reversed_cells, cells - 1 - cell, cell)

        corners = [
            (stored(cell0 + dc) * num_lines + (line0 + dl) % num_lines, wl * wc)
            for dl, wl in ((0, 1.0 - line_frac), (1, line_frac))
            for dc, wc in ((0, 1.0 - cell_frac), (1, cell_frac))
        ]
        sine, cosine = _off_axis(pixel_xy[..., 0], pixel_xy[..., 1], toward, height, width, focal)
        sine, cosine = sine[..., None], cosine[..., None]
        b_low, b_high = (
            _bin_coordinate(line_coordinate(d, sine, cosine, inverse), s_min, log_step) for d in (lower, upper)
        )
        # A segment reads at least one bin: its mean coverage over a narrower range would be a difference of nearly
        # equal prefix sums.
        middle = jnp.clip(0.5 * (b_low + b_high), 0.5, num_bins - 0.5)
        narrow = b_high - b_low < 1.0
        b_low = jnp.clip(jnp.where(narrow, middle - 0.5, b_low), 0.0, num_bins)
        b_high = jnp.clip(jnp.where(narrow, middle + 0.5, b_high), 0.0, num_bins)

        # Each pixel's own row of coverage, blended from its four corners once, and its prefix integral over `s` (the
        # integral is linear: the blend of the corners' integrals): the reads at its segments' ends are then two
        # neighbouring nodes of one row. The four corners are one gather of the table's rows: in a fit's vectorised
        # Jacobian each gather of the table moves its lanes first, a copy of the whole table.
        rows = covered.reshape(cells * num_lines, num_bins)[jnp.stack([index for index, _ in corners])]
        row = _prefix_integral(jnp.sum(jnp.stack([weight for _, weight in corners]) * rows, axis=0), s_min, log_step)

        def prefix_at(b):
            node = jnp.clip(jnp.floor(b), 0, num_bins - 1)
            frac = b - node
            node = node.astype(jnp.int32)
            below, above = (jnp.take_along_axis(row, index, axis=-1) for index in (node, node + 1))
            return (1.0 - frac) * below + frac * above

        span = _coordinate_at_bin(b_high, s_min, log_step) - _coordinate_at_bin(b_low, s_min, log_step)
        mean = (prefix_at(b_high) - prefix_at(b_low)) / jnp.maximum(span, 1e-30)
        return 1.0 - jnp.clip(mean, 0.0, 1.0)

    def read_in_chunks(pixel_xy, lower, upper):
        """`read` of `(h, w, ...)` pixels a chunk at a time: each pixel reads four rows of the table, `num_bins`
        values each (and in a fit's Jacobian as many again per lane), which for a whole frame would outweigh the
        table itself."""
        return _in_chunks(read, pixel_xy, lower, upper)

    return read_in_chunks


def _in_chunks(read, pixel_xy, lower, upper):
    """`read(pixel_xy, lower, upper)` of `(n, 2)`, `(n, M)`, `(n, M)` applied to `(h, w, ...)` arrays
    `_READ_CHUNK` pixels at a time."""
    shape = lower.shape
    count = shape[0] * shape[1]
    flat = [pixel_xy.reshape(count, 2), lower.reshape(count, -1), upper.reshape(count, -1)]
    if count <= _READ_CHUNK:
        return read(*flat).reshape(shape)
    chunks = -(-count // _READ_CHUNK)
    # The pixels that fill the last chunk repeat the last one (finite, with finite derivatives) and are cut off.
    padded = [jnp.pad(a, [(0, chunks * _READ_CHUNK - count), (0, 0)], mode="edge") for a in flat]
    visible = jax.lax.map(lambda chunk: read(*chunk), [a.reshape(chunks, _READ_CHUNK, -1) for a in padded])
    return visible.reshape(chunks * _READ_CHUNK, -1)[:count].reshape(shape)
