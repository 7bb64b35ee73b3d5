"""Where the light is, read from its own pixels: a sun's disc or a lamp's bulb in view, far brighter than anything
it lights.

`find_light` places a light from the halo a target shows around it, through the effect, and its light lies where
the effect's few fields match that halo best, a few pixels from the one drawn (benchmarks/README.md, "Finding the
light"). Where the light itself is in the frame, its pixels say where it is to a fraction of a pixel, with no
effect and no fit: `seen_lights` finds them.
"""

import dataclasses
import math

import numpy as np
import scipy.ndimage
import skimage.measure
from jaxtyping import ArrayLike

from godrays_jax.primitives.buffers import Buffers

SEEN_CONTRAST = 100.0
"""A light's own pixels are at least this many times brighter than the frame's 99th percentile (channels averaged,
linear): a light far outshines what it lights, where a sunlit wall in a dark room, a white sky or an 8-bit plate's
highlights do not (a surface lit by a light has its radiance times its albedo over the solid angle it sees the
light in)."""

ROUND_TOLERANCE = 0.5
"""How far, in pixels (RMS), the points where a light's pixels fall to half their peak may lie from a circle
through them for the light to be read as a disc (a sun, a bulb); anti-aliasing and a path tracer's noise move them
by a fraction of a pixel. A larger disc may miss by `ROUND_SHARE` of its radius where that is more."""

ROUND_SHARE = 0.025
"""`ROUND_TOLERANCE` as a share of a disc's radius, for discs over 20 pixels in radius."""

LEAST_ARC_DEG = 180.0
"""The least arc, in degrees around its centre, the unhidden part of a partly hidden disc's edge must span for its
centre to be read from that edge: a shorter arc leaves the centre free to slide along it."""

LEAST_EDGE_POINTS = 8
"""The fewest points on a light's edge that a circle is fitted to; a light of fewer, a few pixels across, is placed
by the centroid of its pixels alone."""

DRAWN_SHARE = 0.1
"""`fit --light auto` draws a light in view beside the brightest where its `flux` is at least this share of the
brightest's: each light drawn costs the fit a render, and a glint on a car or a wet street (a reflection as
bright as the light, a few pixels across) is a small share of it."""

MOST_GROUPS = 32
"""The most groups of bright pixels read, those of the largest sums: sunlit water or a wet street holds
thousands of glints, and each group read costs a contour and a circle."""

NEARER = 0.98
"""A pixel beside a light whose depth is below this fraction of the light's (its pixels at half its peak or more,
their 10th percentile: an edge pixel may hold what hides it) hides part of it (a slat, a branch, a lamp's
housing); a bulb's own pixels lie within its radius of one another."""


@dataclasses.dataclass(frozen=True)
class SeenLight:
    """A light in view, as `seen_lights` reads it; positions in pixels of the frame (x right, y down, pixel
    centres at `i + 0.5`).

    Attributes:
        light_xy: `(2,)` the light's centre: the centroid of its pixels (each weighted by its share of the peak,
            so that a pixel the light's edge crosses counts for the part it covers) where the light is whole, the
            centre of a circle through the unhidden part of its edge where something nearer hides part of it or
            the frame's edge cuts it.
        standard_error: `(2,)` the standard error of that centre in x and in y, pixels, from the circle through
            the light's edge (its points' scatter about it); NaN where no circle fits (a light a few pixels across
            or not round, placed by its centroid).
        radius: the circle's radius, pixels; NaN where no circle fits.
        depth: the light's distance along its camera ray (scene units): its pixels' median; `inf` for a light
            in the sky (the sun) or a frame without depth.
        pixels: how many pixels are brighter than `SEEN_CONTRAST` times the frame's 99th percentile.
        flux: the light's pixels summed (channels averaged): which of several lights outshines the others.
        hidden: whether part of the light is hidden by something nearer or lies beyond the frame's edge.
    """

    light_xy: np.ndarray
    standard_error: np.ndarray
    radius: float
    depth: float
    pixels: int
    flux: float
    hidden: bool


def seen_lights(buffers: Buffers, *, fov_x_deg: float | None = None) -> list[SeenLight]:
    """The lights in view of `buffers`, brightest (by `flux`) first; an empty list where none is.

    A light in view is a group of touching pixels at least `SEEN_CONTRAST` times brighter than the frame's 99th
    percentile (the colour's channels averaged, as stored: linear for an EXR). Its edge is where it falls to half
    its peak (`skimage.measure.find_contours`). A light whose pixels nothing hides is placed at their centroid,
    each weighted by its share of the peak, whatever its shape (a group whose edge is long enough must be round,
    else it is not read as a light); a light partly hidden, by a nearer pixel beside it (frames with depth) or by
    the frame's edge, at the centre of a circle fitted to the rest of its edge, where that rest is round
    (`ROUND_TOLERANCE`) and spans `LEAST_ARC_DEG` of it, else not at all. Where several groups are found, each
    is a light (a street's lamps; a sun's reflection in a window would be one too).

    Args:
        buffers: the frame (its colour, and its depth where it has one).
        fov_x_deg: the horizontal field of view, degrees, for a frame whose depth is planar (`Buffers.ray_depth`):
            a lamp's distance along its ray.

    Raises:
        ValueError: `fov_x_deg` is None and a light is found at a finite planar depth.
    """
    luminance = np.mean(np.asarray(buffers.color, np.float64)[..., :3], axis=-1)
    level = SEEN_CONTRAST * float(np.percentile(luminance, 99.0))
    groups, count = scipy.ndimage.label(luminance > max(level, 0.0), structure=np.ones((3, 3)))
    if count == 0:
        return []
    fluxes = scipy.ndimage.sum_labels(luminance, groups, np.arange(1, count + 1))
    brightest = np.argsort(-fluxes)[:MOST_GROUPS] + 1
    depth = None if buffers.depth is None else np.asarray(buffers.depth, np.float64)
    ray_depth = depth
    if depth is not None and buffers.depth_kind == "planar" and np.any(np.isfinite(depth[groups > 0])):
        ray_depth = np.asarray(buffers.ray_depth(fov_x_deg), np.float64)  # a lamp's distance, not its depth
    boxes = scipy.ndimage.find_objects(groups)
    lights = []
    for index in brightest:
        rows, columns = boxes[index - 1]
        cut = rows.start == 0 or columns.start == 0 or rows.stop == groups.shape[0] or columns.stop == groups.shape[1]
        # Two pixels around the group: its partly covered edge, and the contour's half-way points beyond it.
        box = (slice(max(rows.start - 2, 0), rows.stop + 2), slice(max(columns.start - 2, 0), columns.stop + 2))
        light = _seen_light(
            luminance[box], None if depth is None else depth[box], None if depth is None else ray_depth[box],
            groups[box] == index, cut=cut, corner=(box[1].start, box[0].start),
        )  # fmt: skip
        lights.append(light)
    return sorted([light for light in lights if light is not None], key=lambda light: -light.flux)


def _seen_light(luminance: np.ndarray, depth, ray_depth, group: np.ndarray, *, cut: bool, corner) -> SeenLight | None:
    """One group of bright pixels read as a light, or None where it is not one (its edge not round), from a crop
    of the frame around it whose top left pixel is `corner` (x, y) in the frame; `cut`: whether it touches the
    frame's edge. `depth` as the frame stores it (which pixel is nearer), `ray_depth` along the camera's rays (the
    light's distance)."""
    peak = float(np.max(luminance[group]))
    around = scipy.ndimage.binary_dilation(group, np.ones((3, 3)))  # its edge's pixels partly covered as well
    share = np.where(around, np.clip(luminance / peak, 0.0, 1.0), 0.0)
    own = group & (luminance >= 0.5 * peak)  # its edge's pixels may hold what hides it, nearer
    light_depth = math.inf if depth is None else _quantile(ray_depth[own], 0.5)
    nearer = np.zeros(group.shape, bool)
    if depth is not None:
        nearer = around & (depth < NEARER * _quantile(depth[own], 0.1))
    edge = _edge_points(share, nearer)
    hides = edge[:, 2].astype(bool)
    hidden = cut or bool(np.any(hides))
    circle = _circle(edge[~hides, :2])
    small = len(edge) < LEAST_EDGE_POINTS
    if hidden and circle is None:
        return None
    if not hidden and circle is None and not small:
        return None  # not round: a lit window or a glint, not a light
    rows, columns = np.indices(share.shape) + 0.5
    total = float(np.sum(share))
    centroid = np.asarray([np.sum(share * columns), np.sum(share * rows)]) / total
    centre, error, radius = (centroid, np.full(2, np.nan), math.nan) if circle is None else circle
    return SeenLight(
        light_xy=(centroid if not hidden else centre) + np.asarray(corner, np.float64),
        standard_error=error,
        radius=radius,
        depth=light_depth,
        pixels=int(np.sum(group)),
        flux=float(np.sum(luminance[group])),
        hidden=hidden,
    )


def _quantile(values: np.ndarray, share: float) -> float:
    """The value `share` of the way up `values` sorted, one of them (no interpolation, which `inf` makes NaN)."""
    return float(np.sort(values)[int(share * (len(values) - 1))])


def _edge_points(share: np.ndarray, nearer: np.ndarray) -> np.ndarray:
    """`(N, 3)`: the points where `share` crosses a half (x, y in pixels) and, third, 1 where a pixel around the
    point is `nearer` (the edge there is an occluder's) or the point lies on the border (of a crop that the group
    comes within two pixels of only at the frame's edge), else 0."""
    padded = np.pad(share, 1)  # a light cut by the frame's edge closes along it
    contours = skimage.measure.find_contours(padded, 0.5)
    if not contours:
        return np.zeros((0, 3))
    points = np.concatenate(contours) - 1.0  # (row, column) in pixel indices of the frame
    height, width = share.shape
    low = np.floor(points).astype(int)
    border = (low[:, 0] < 0) | (low[:, 1] < 0) | (low[:, 0] + 1 > height - 1) | (low[:, 1] + 1 > width - 1)
    covered = np.zeros(len(points), bool)
    for drow in (0, 1):
        for dcolumn in (0, 1):
            row = np.clip(low[:, 0] + drow, 0, height - 1)
            column = np.clip(low[:, 1] + dcolumn, 0, width - 1)
            covered |= nearer[row, column]
    return np.stack([points[:, 1] + 0.5, points[:, 0] + 0.5, (covered | border).astype(float)], axis=1)


def _circle(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float] | None:
    """The circle through `points` (`(N, 2)`, pixels) by least squares on `x^2 + y^2 + D x + E y + F = 0`: its
    centre, the centre's standard errors and its radius; None where there are too few points, they span less than
    `LEAST_ARC_DEG` of it or lie farther than `ROUND_TOLERANCE` from it."""
    if len(points) < LEAST_EDGE_POINTS:
        return None
    x, y = points[:, 0], points[:, 1]
    design = np.stack([x, y, np.ones_like(x)], axis=1)
    solution, *_ = np.linalg.lstsq(design, -(x**2 + y**2), rcond=None)
    centre = -solution[:2] / 2.0
    radius_squared = float(centre @ centre - solution[2])
    if radius_squared <= 0.0:
        return None
    radius = math.sqrt(radius_squared)
    misses = np.hypot(x - centre[0], y - centre[1]) - radius
    spread = float(np.sqrt(np.mean(misses**2)))
    angles = np.sort(np.arctan2(y - centre[1], x - centre[0]))
    widest_gap = float(np.max(np.diff(np.concatenate([angles, angles[:1] + 2.0 * math.pi]))))
    round_enough = spread <= max(ROUND_TOLERANCE, ROUND_SHARE * radius)
    if not round_enough or math.degrees(2.0 * math.pi - widest_gap) < LEAST_ARC_DEG:
        return None
    # Each point's miss of the circle is about `2 r` times its miss of the equation: the centre's covariance
    # from the equation's residuals, scaled to pixels.
    residual_variance = (2.0 * radius * spread) ** 2 * len(points) / max(len(points) - 3, 1)
    covariance = residual_variance * np.linalg.inv(design.T @ design)
    return centre, np.sqrt(np.diag(covariance)[:2]) / 2.0, radius


def nearest_seen(lights: list[SeenLight], xy: ArrayLike, reach: float) -> SeenLight | None:
    """The light of `lights` nearest `xy` (pixels) within `reach` pixels, or None."""
    if not lights:
        return None
    distances = [float(np.linalg.norm(light.light_xy - np.asarray(xy, np.float64))) for light in lights]
    index = int(np.argmin(distances))
    return lights[index] if distances[index] <= reach else None
