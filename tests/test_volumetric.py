"""Scattering from the depth buffer (kernels/volumetric.py) against a slow NumPy loop, and its degenerate cases."""

import functools
import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from frames import slow_where
from jax.test_util import check_grads

from godrays_jax.kernels import fog_march, volumetric
from godrays_jax.kernels.bounded_medium import BoundedMedium, light_approach
from godrays_jax.kernels.fog_march import march_grid
from godrays_jax.kernels.shadow_lines import segment_visibility_by_lines
from godrays_jax.kernels.shadow_reading import ENCLOSED_SKY, ShadowLines, ShadowSamples, Slabs, enclosure
from godrays_jax.kernels.shadow_samples import segment_visibility
from godrays_jax.kernels.volumetric import apply_volumetric_fog, volumetric_fog_terms
from godrays_jax.primitives.derivatives import values_only

HEIGHT, WIDTH = 4, 6
MEDIUM = dict(
    fov_x_deg=60.0, extinction=0.06, max_distance=25.0, height_falloff=0.05, layer_top=4.0, anisotropy=0.6,
    direct_fraction=0.7, ambient_rise=0.08, thickness=0.3, edge_softness=0.1, num_view_steps=3, num_shadow_samples=4,
)  # fmt: skip
COLOURS = dict(light_color=(2.0, 1.5, 1.0), ambient_color=(0.1, 0.2, 0.3))


def kernel_options(flat):
    """The kernel's keywords from the flat names `_Loop` takes: the medium, the slabs and the shadow reading as
    their types (`BoundedMedium`, `Slabs`, `ShadowSamples` or `ShadowLines`), the rest as they are."""
    flat = dict(flat)

    def taken(*names):
        return {name: flat.pop(name) for name in names if name in flat}

    medium = BoundedMedium(**taken("extinction", "max_distance", "anisotropy", "height_falloff", "layer_top"))
    slabs = Slabs(**taken("thickness", "edge_softness"))
    lines = taken("num_shadow_lines", "num_shadow_bins")
    samples = taken("num_shadow_samples")
    if flat.pop("shadows", "samples") == "lines":
        shadows = ShadowLines(**{name.replace("num_shadow_", "num_"): count for name, count in lines.items()})
    else:
        shadows = ShadowSamples(*samples.values())
    return dict(flat, medium=medium, slabs=slabs, shadows=shadows)


def _depth():
    depth = np.full((HEIGHT, WIDTH), np.inf)
    depth[2:] = [[6.0, 9.0, 14.0, 30.0, 11.0, 7.5], [5.0, 6.5, 8.0, 20.0, 9.0, 6.0]]  # ground, one far
    depth[:, 2] = [3.0, 3.2, 3.4, 3.6]  # a near pillar
    return depth


def _image(rng):
    return rng.uniform(0.0, 2.0, (HEIGHT, WIDTH, 4))


def _hg(cosine, g):
    return (1 - g * g) / (4 * math.pi * (1 + g * g - 2 * g * cosine) ** 1.5)


def _ramp(x):
    return min(max(x, 0.0), 1.0)


class _Loop:
    """The model by definition: numeric integrals, 3-D line crossings by least squares, one pixel at a time."""

    def __init__(self, depth, light_xy, *, light_depth, in_front, fov_x_deg, extinction, max_distance,
                 height_falloff, layer_top, anisotropy, direct_fraction, ambient_rise, thickness, edge_softness,
                 num_view_steps, num_shadow_samples):  # fmt: skip
        self.depth, self.light_xy = depth, np.asarray(light_xy, float)
        self.height, self.width = depth.shape
        self.focal = 0.5 * self.width / math.tan(math.radians(fov_x_deg) / 2)
        forward = 1.0 if in_front else -1.0
        toward = self.ray(*self.light_xy) * [1, 1, forward]
        self.toward = toward / np.linalg.norm(toward)
        self.light_depth, self.in_front = light_depth, in_front
        self.sigma, self.radius, self.falloff, self.top = extinction, max_distance, height_falloff, layer_top
        self.g, self.share, self.thickness, self.softness = anisotropy, direct_fraction, thickness, edge_softness
        self.rise = ambient_rise
        self.steps, self.samples = num_view_steps, num_shadow_samples

    def ray(self, x, y):
        return np.array([(x - self.width / 2) / self.focal, (self.height / 2 - y) / self.focal, 1.0])

    def density(self, points):
        inside = (np.linalg.norm(points, axis=-1) < self.radius) & (points[..., 1] < self.top)
        return np.where(inside, self.sigma * np.exp(-self.falloff * points[..., 1]), 0.0)

    def optical_depth(self, origin, direction, length, n=20000):
        """A midpoint sum over `n` steps."""
        du = length / n
        points = origin + ((np.arange(n) + 0.5) * du)[:, None] * direction
        return float(np.sum(self.density(points)) * du)

    def to_light(self, point):
        if math.isinf(self.light_depth):
            return self.toward, 3 * self.radius  # beyond the medium's far side
        offset = self.light_depth * self.toward - point
        return offset / np.linalg.norm(offset), np.linalg.norm(offset)

    def light_transmittance(self, point):
        direction, distance = self.to_light(point)
        return math.exp(-self.optical_depth(point, direction, distance))

    def inside_slab(self, row, col, span):
        """How far the depths `span` of a shadow ray reach into the slab of a texel (clamped to the frame)."""
        front = self.depth[min(max(row, 0), self.height - 1), min(max(col, 0), self.width - 1)]
        if not math.isfinite(front):
            return 0.0
        if math.isfinite(self.light_depth) and front * (1 + self.thickness) >= self.light_depth:
            return 0.0
        width = self.softness * front
        return _ramp((span[1] - front) / width) * _ramp((front * (1 + self.thickness) - span[0]) / width)

    def visibility(self, x, y, view, t):
        point = t * view
        light_point = self.light_depth * self.toward if math.isfinite(self.light_depth) else None
        shadow = self.toward if light_point is None else light_point - point
        p = np.array([x, y])
        if self.in_front:
            step = self.light_xy - p
        else:
            step = p - (np.array([self.width, self.height]) - self.light_xy)
        reach = 1.0 if self.in_front else math.inf
        for axis, limit in ((0, self.width), (1, self.height)):
            if step[axis] > 0:
                reach = min(reach, (limit - p[axis]) / step[axis])
            elif step[axis] < 0:
                reach = min(reach, -p[axis] / step[axis])
        if not math.isfinite(reach) or reach == 0:
            return 1.0
        visible = 1.0
        previous = t  # the shadow ray crosses the pixel's own camera ray at the point
        for k in range(self.samples + 1):  # the last one at the segment's end: the light's pixel when on screen
            q = p + reach * min((k + 0.5) / self.samples, 1.0) * step
            ray = self.ray(*q)
            if k == self.samples and self.in_front and reach == 1.0:
                crossing = self.light_depth  # every shadow ray reaches the light there
            elif np.linalg.norm(np.cross(ray, shadow)) < 1e-9 * np.linalg.norm(ray) * np.linalg.norm(shadow):
                crossing = t  # the shadow ray runs along q's camera ray (the light's own): from the point on
            else:
                # mu' * ray - u * shadow = point, least squares (exact: the three lie in one plane)
                (mu, _), *_ = np.linalg.lstsq(np.stack([ray, -shadow], axis=1), point, rcond=None)
                crossing = mu * np.linalg.norm(ray)
            # the shadow ray's depths between this sample's crossing and the previous one's
            span = sorted((crossing, previous)) if crossing > 0 and previous > 0 else (crossing, crossing)
            previous = crossing
            # the four texels around q, by their bilinear weights
            u, v = q - 0.5
            col, row = math.floor(u), math.floor(v)
            fx, fy = u - col, v - row
            inside = sum(
                wy * wx * self.inside_slab(row + dy, col + dx, span)
                for dy, wy in ((0, 1 - fy), (1, fy)) for dx, wx in ((0, 1 - fx), (1, fx))
            )  # fmt: skip
            visible = min(visible, 1.0 - inside)
        return visible

    def end_of_medium(self, view, depth):
        end = min(depth, self.radius)
        if view[1] > 0 and math.isfinite(self.top):
            end = min(end, self.top / view[1])
        return end

    def pixel(self, row, col, depth):
        return self.at(col + 0.5, row + 0.5, depth)

    def at(self, x, y, depth):
        """`(surface, scattered, ambient)` of the view ray through the pixel position `(x, y)` up to `depth`."""
        view, bounds, transmittance, lit = self.segments(x, y, depth)
        surface = transmittance[-1]
        if math.isfinite(depth):
            surface *= 1 - self.share + self.share * self.light_transmittance(depth * view)
        ambient = max(1 - transmittance[-1] + self.rise * self.scattering_height(view, bounds[-1]), 0.0)
        return surface, sum(lit), ambient

    def scattering_height(self, view, end, n=20000):
        """`integral sigma T(u) y(u) du` from where the ray enters the medium up to `end`, by a midpoint sum, in the
        homogeneous medium with the ray's own optical depth (the kernel's definition)."""
        start = 0.0
        if self.top < 0 and view[1] < 0:  # the camera above the layer: the ray enters it at its top
            start = min(self.top / view[1], end)
        if end <= start:
            return 0.0
        sigma = self.optical_depth(np.zeros(3), view, end) / (end - start)
        du = (end - start) / n
        u = start + (np.arange(n) + 0.5) * du
        return float(np.sum(sigma * np.exp(-sigma * (u - start)) * u * view[1]) * du)

    def even_in_transmittance(self, view, start, end):
        """`steps + 1` bounds from `start` to `end` along the unit ray `view`, each segment an equal share of `1 - T`
        in the homogeneous medium of the piece's optical depth `tau` (at most 12: the kernel's cap), even in distance
        where `tau` is (nearly) 0."""
        tau = min(self.optical_depth(start * view, view, end - start), 12.0)
        fractions = np.arange(self.steps + 1) / self.steps
        if tau < 1e-4:
            return start + (end - start) * fractions
        return start + (end - start) * -np.log(1 - fractions * (1 - math.exp(-tau))) / tau

    def segments(self, x, y, depth):
        """The unit view ray through `(x, y)`, its segments' bounds up to `depth`, the transmittance at each
        bound and each segment's scattered light."""
        view = self.ray(x, y)
        view /= np.linalg.norm(view)
        return self.segments_between(x, y, self.even_in_transmittance(view, 0.0, self.end_of_medium(view, depth)))

    def segments_between(self, x, y, bounds):
        """`segments` with the given bounds along the view ray through `(x, y)` (from the camera)."""
        view = self.ray(x, y)
        view /= np.linalg.norm(view)
        transmittance = [math.exp(-self.optical_depth(np.zeros(3), view, b)) for b in bounds]
        lit = []
        for j in range(len(bounds) - 1):
            # The shadow and the light's way in are taken where the segment's light is halved: its middle for the
            # sun, near a point light its closest approach; a point light's phase is its mean over the segment,
            # weighted by the irradiance.
            middle = 0.5 * (bounds[j] + bounds[j + 1])
            irradiance = 1.0
            point = middle * view
            direction, _ = self.to_light(point)
            phase = _hg(view @ direction, self.g)
            if math.isfinite(self.light_depth) and bounds[j + 1] > bounds[j]:
                ts, cumulative = self.irradiance_along(view, bounds[j], bounds[j + 1])
                irradiance = cumulative[-1] / (bounds[j + 1] - bounds[j])
                middle = np.interp(0.5 * cumulative[-1], cumulative, ts)
                point = middle * view
                phase = self.mean_phase(view, bounds[j], bounds[j + 1])
            lit.append(
                (transmittance[j] - transmittance[j + 1]) * self.visibility(x, y, view, middle)
                * self.light_transmittance(point) * phase * irradiance
            )  # fmt: skip
        return view, bounds, transmittance, lit

    def mean_phase(self, view, start, end, n=4000):
        """A point light's phase over `[start, end]` along the unit ray `view`, weighted by its irradiance (its size
        as in the kernel): midpoint sums of `n` steps on each side of the ray's closest approach, where a ray through
        the light turns from looking at it to looking away."""
        along = self.light_depth * float(self.toward @ view)
        cuts = [start, *([along] if start < along < end else []), end]
        total = weight = 0.0
        for low, high in zip(cuts[:-1], cuts[1:]):
            ts = low + (np.arange(n) + 0.5) * (high - low) / n
            offsets = self.light_depth * self.toward - ts[:, None] * view
            squared = np.sum(offsets**2, axis=-1)
            irradiance = self.light_depth**2 / (squared + (1e-3 * self.light_depth) ** 2)
            step = (high - low) / n
            total += step * np.sum(_hg(offsets @ view / np.sqrt(squared), self.g) * irradiance)
            weight += step * np.sum(irradiance)
        return total / weight

    def irradiance_along(self, view, start, end):
        """Distances from `start` to `end` along the unit ray `view` and the point light's irradiance
        `(light_depth / |S - t view|)^2` (its size as in the kernel) integrated from `start` up to each."""
        ts = np.linspace(start, end, 4001)
        miss = (1e-3 * self.light_depth) ** 2
        values = self.light_depth**2 / (np.sum((self.light_depth * self.toward - ts[:, None] * view) ** 2, axis=-1) + miss)
        return ts, np.concatenate([[0.0], np.cumsum(0.5 * (values[1:] + values[:-1]) * np.diff(ts))])

    def covered_pixel(self, row, col, coverage, uncovered):
        """`coverage` of the surface's terms (on sky, its nearest neighbour's surface) and the rest of the terms at
        the uncovered depth (None: the sky's)."""
        depth = self.depth[row, col]
        if coverage is None:
            return self.pixel(row, col, depth)
        if not math.isfinite(depth):
            depth = self.depth[max(row - 1, 0) : row + 2, max(col - 1, 0) : col + 2].min()
        c = coverage[row, col]
        rest = math.inf if uncovered is None else uncovered[row, col]
        surface, beside = self.pixel(row, col, depth), self.pixel(row, col, rest)
        return tuple(c * a + (1 - c) * b for a, b in zip(surface, beside))

    def reduced_scattered(self, spacing, reading=None):
        """The in-scattering marched on rays at the light's position plus `spacing` times integers (the screen and
        one spacing around it), each through to the medium's end in two pieces of `steps` segments (even in
        transmittance) split at
        the depth of the texel it lies in (sky, or a surface beyond the medium: halfway); at every pixel, its four
        nearest rays' in-scattering up to the pixel's own depth (the segment holding it taken in proportion to the
        light it receives up to there), by bilinear weights; `reading`: the depth each pixel reads up to instead."""
        anchor = self.light_xy % spacing - spacing
        xs = anchor[0] + spacing * np.arange(math.ceil(self.width / spacing) + 2)
        ys = anchor[1] + spacing * np.arange(math.ceil(self.height / spacing) + 2)

        def cumulative(view, bounds, lit, distance):
            """The in-scattering along a ray's segments up to `distance`."""
            total = 0.0
            for j, value in enumerate(lit):
                if distance >= bounds[j + 1]:
                    total += value
                elif distance > bounds[j]:
                    share = (distance - bounds[j]) / (bounds[j + 1] - bounds[j])
                    if math.isfinite(self.light_depth):
                        ts, light = self.irradiance_along(view, bounds[j], bounds[j + 1])
                        share = np.interp(distance, ts, light) / light[-1]
                    total += value * share
            return total

        rays = {}  # (i, j) -> (the segments' bounds, their light)
        for i, y in enumerate(ys):
            for j, x in enumerate(xs):
                depth = self.depth[min(max(math.floor(y), 0), self.height - 1), min(max(math.floor(x), 0), self.width - 1)]
                view = self.ray(x, y) / np.linalg.norm(self.ray(x, y))
                end = self.end_of_medium(view, math.inf)
                split = depth if depth < end else 0.5 * end
                bounds = np.concatenate([self.even_in_transmittance(view, 0.0, split),
                                         self.even_in_transmittance(view, split, end)[1:]])  # fmt: skip
                _, _, _, lit = self.segments_between(x, y, bounds)
                rays[i, j] = (view, bounds, lit)

        out = np.zeros((self.height, self.width))
        for row in range(self.height):
            for col in range(self.width):
                own = min((self.depth if reading is None else reading)[row, col], self.radius)
                for (i, j), (view, bounds, lit) in rays.items():
                    tent = max(1 - abs(col + 0.5 - xs[j]) / spacing, 0) * max(1 - abs(row + 0.5 - ys[i]) / spacing, 0)
                    if tent > 0:
                        out[row, col] += tent * cumulative(view, bounds, lit, own)
        return out

    def terms(self, coverage=None, uncovered=None):
        rows = [[self.covered_pixel(row, col, coverage, uncovered) for col in range(self.width)]
                for row in range(self.height)]  # fmt: skip
        return tuple(np.array([[pixel[i] for pixel in row] for row in rows]) for i in range(3))


def _terms(depth, light_xy, *, coverage=None, uncovered_depth=None, **options):
    """`volumetric_fog_terms` compiled, the options constants: eager, each operation of the march is dispatched and
    compiled alone (test_composite_eager_jit_vmap takes that path)."""
    run = jax.jit(functools.partial(volumetric_fog_terms, **kernel_options(options)))
    return run(jnp.asarray(depth), jnp.asarray(light_xy), coverage=coverage, uncovered_depth=uncovered_depth)


CASES = {
    "sun in front": ((2.3, 0.7), math.inf, True),
    "point light in the medium": ((4.4, 1.2), 12.0, True),
    "sun behind the camera": ((1.7, 2.9), math.inf, False),
    "point light off screen": ((-7.0, 2.5), 9.0, True),
    "point light behind the camera": ((5.2, 0.4), 6.0, False),
}


@pytest.mark.parametrize("case", CASES)
def test_terms_match_loop(x64, case):
    light_xy, light_depth, in_front = CASES[case]
    depth = _depth()
    expected = _Loop(depth, light_xy, light_depth=light_depth, in_front=in_front, **MEDIUM).terms()
    got = _terms(depth, light_xy, light_depth=light_depth, light_in_front=in_front, **MEDIUM)
    for name, want, have in zip(("surface", "scattered", "ambient"), expected, got):
        np.testing.assert_allclose(np.asarray(have), want, rtol=2e-3, atol=1e-6, err_msg=name)


@pytest.mark.parametrize("beside_surfaces", [False, True])
def test_partly_covered_pixels_match_loop(x64, beside_surfaces):
    """A silhouette's pixels blend the surface's terms (a sky pixel: its neighbour's surface) with the sky's, or
    with the terms at the depth the rest of the pixel sees (a surface beside its own); the same where no derivative
    is taken (`values_only`)."""
    depth = _depth()
    coverage = np.isfinite(depth).astype(float)
    coverage[1, 1], coverage[1, 2], coverage[0, 3], coverage[3, 4], coverage[2, 3] = 0.3, 0.6, 0.45, 0.8, 0.7
    uncovered = None
    if beside_surfaces:
        uncovered = np.full(depth.shape, np.inf)
        uncovered[2, 3], uncovered[3, 4] = 11.0, 20.0  # the far ground's pixel partly the near one, and the reverse
    expected = _Loop(depth, (2.3, 0.7), light_depth=12.0, in_front=True, **MEDIUM).terms(coverage, uncovered)
    got = _terms(depth, [2.3, 0.7], light_depth=12.0, coverage=jnp.asarray(coverage), **MEDIUM,
                 uncovered_depth=None if uncovered is None else jnp.asarray(uncovered))  # fmt: skip
    for name, want, have in zip(("surface", "scattered", "ambient"), expected, got):
        np.testing.assert_allclose(np.asarray(have), want, rtol=2e-3, atol=1e-6, err_msg=name)

    def values_alone(depth, coverage, uncovered):
        with values_only():
            return _terms(depth, [2.3, 0.7], light_depth=12.0, coverage=coverage, uncovered_depth=uncovered, **MEDIUM)

    # A render that takes no derivatives marches every pixel's one side, then the other side's own rays at the
    # partly covered pixels alone, two at a time: the last pair starts earlier and marches one again.
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(volumetric, "_MARCHED_PIXELS", 2)
        cheaper = jax.jit(values_alone)(jnp.asarray(depth), jnp.asarray(coverage),
                                        None if uncovered is None else jnp.asarray(uncovered))  # fmt: skip
    for name, want, have in zip(("surface", "scattered", "ambient"), got, cheaper):
        np.testing.assert_allclose(np.asarray(have), np.asarray(want), rtol=1e-12, atol=1e-15, err_msg=name)
    plain = _terms(depth, [2.3, 0.7], light_depth=12.0, **MEDIUM)
    assert not np.allclose(np.asarray(got[1]), np.asarray(plain[1]))


def test_occluder_shadows_the_haze_in_front_of_it(x64):
    """A post below the sun shades the haze in front of it; a ray whose shadow rays miss it stays as in open sky."""
    depth = np.full((HEIGHT, WIDTH), np.inf)
    depth[2:, 2] = 10.0
    options = dict(MEDIUM, layer_top=math.inf, height_falloff=0.0, max_distance=10.0, num_shadow_samples=8)
    light = jnp.asarray([2.6, 0.5])
    _, shadowed, _ = _terms(depth, light, **options)
    _, open_sky, _ = _terms(np.full((HEIGHT, WIDTH), np.inf), light, **options)
    assert float(shadowed[3, 2]) < 0.8 * float(open_sky[3, 2])
    assert float(shadowed[0, 5]) == pytest.approx(float(open_sky[0, 5]), rel=1e-12)


def test_box_hiding_the_sun_shades_the_whole_ray_in_front_of_it(x64):
    """Near the camera the shadow ray crosses the box's camera rays only close to the sun's pixel, in long depth
    steps between shadow samples: a slab between two samples still blocks it."""
    depth = np.full((12, 16), np.inf)
    depth[2:10, 4:12] = 10.0
    options = dict(MEDIUM, layer_top=math.inf, height_falloff=0.0, max_distance=30.0, thickness=0.1, edge_softness=0.01,
                   num_view_steps=8, num_shadow_samples=6)  # fmt: skip
    _, scattered, _ = _terms(depth, [8.2, 5.7], **options)
    _, open_sky, _ = _terms(np.full((12, 16), np.inf), [8.2, 5.7], **options)
    assert float(jnp.max(scattered[3:9, 5:11])) < 1e-3 * float(jnp.min(open_sky[3:9, 5:11]))


def _fog(image, depth, light_xy, **overrides):
    options = dict(MEDIUM, **COLOURS, light_depth=12.0)
    options.update(overrides)
    return apply_volumetric_fog(image, depth, light_xy, **kernel_options(options))


@pytest.mark.slow
def test_composite_eager_jit_vmap(x64, rng):
    image, depth, light = jnp.asarray(_image(rng)), jnp.asarray(_depth()), jnp.asarray([2.3, 0.7])
    surface, scattered, ambient = volumetric_fog_terms(depth, light, light_depth=12.0, **kernel_options(MEDIUM))
    light_rgb = scattered[..., None] * jnp.asarray(COLOURS["light_color"]) + ambient[..., None] * jnp.asarray(COLOURS["ambient_color"])
    expected = jnp.concatenate([image[..., :3] * surface[..., None] + light_rgb, image[..., 3:]], axis=-1)
    eager = _fog(image, depth, light)
    np.testing.assert_allclose(eager, expected, rtol=1e-12)
    compiled = jax.jit(_fog)
    np.testing.assert_allclose(compiled(image, depth, light), eager, rtol=1e-10)
    lights = jnp.asarray([[2.3, 0.7], [-3.0, 5.0], [3.0, 2.0]])
    batched = jax.vmap(_fog, in_axes=(None, None, 0))(image, depth, lights)
    for index, one in enumerate(lights):  # compiled, which equals eager above: op by op is the slow path
        np.testing.assert_allclose(batched[index], compiled(image, depth, one), rtol=1e-10)


@pytest.mark.slow
def test_grad_of_vmap_matches_per_example(x64, rng):
    images = jnp.asarray(rng.uniform(0.0, 2.0, (2, HEIGHT, WIDTH, 3)))
    depth = jnp.asarray(_depth())
    lights = jnp.asarray([[2.3, 0.7], [4.1, 1.9]])

    def loss(extinction, images, lights):
        fogged = jax.vmap(lambda i, l: _fog(i, depth, l, extinction=extinction))(images, lights)
        return jnp.sum(fogged**2)

    gradient = jax.jit(jax.grad(loss, argnums=(0, 1, 2)))
    grads = gradient(0.06, images, lights)
    total = 0.0
    for index in range(2):
        one = gradient(0.06, images[index : index + 1], lights[index : index + 1])
        np.testing.assert_allclose(grads[1][index], one[1][0], rtol=1e-9)
        np.testing.assert_allclose(grads[2][index], one[2][0], rtol=1e-9)
        total = total + one[0]
    np.testing.assert_allclose(grads[0], total, rtol=1e-9)


@pytest.mark.slow
def test_compiled_forward_mode_jacobian_keeps_its_lanes_on_a_partly_covered_frame():
    """A vmapped forward-mode Jacobian (as `jax.jacfwd` and the fit's `forward_mode` take it) of the three terms,
    compiled, against reverse mode, compiled, on a frame of 90 x 160 pixels with coverage and a direct share of the
    surface light: every lane its own. At 36 x 64 and 45 x 80 the same program is right, so the frame is this large.

    Compiled without XLA's YNNPACK fusions (its CPU library calls for short reductions): with them, jaxlib 0.10.2
    gives the anisotropy lane the extinction lane's value on some machines and the right one on others (an AMD
    EPYC), so a test of XLA's default program passes or fails with the
    machine; without them both machines compile it right, and what is left to test is the kernel's own (benchmarks/
    README.md, 'The fit's Jacobian and XLA'). The option is XLA's own: a release that renames it fails here."""
    height, width = 90, 160
    depth = np.full((height, width), np.inf, np.float32)
    depth[height // 2 :] = (3.0 * height / (np.arange(height - height // 2) + 0.5))[:, None]  # the ground
    depth[height // 5 :, 65:95] = 6.0  # a pillar hiding the sun
    coverage, depth = jnp.asarray(np.isfinite(depth), jnp.float32), jnp.asarray(depth)
    weights = jnp.asarray(np.random.default_rng(1).normal(size=(3, height, width)), jnp.float32)

    def weighted_terms(fields):
        terms = volumetric_fog_terms(
            depth, jnp.asarray([80.8, 27.5]), fov_x_deg=60.0,
            medium=BoundedMedium(extinction=fields[0], max_distance=fields[1], anisotropy=fields[2]),
            direct_fraction=0.3, resolution_factor=4, coverage=coverage,
        )  # fmt: skip
        return jnp.stack([jnp.sum(weight * term) for weight, term in zip(weights, terms)])

    fields = jnp.asarray([0.013, 50.0, 0.6], jnp.float32)
    reverse = jax.jit(jax.jacrev(weighted_terms))(fields)
    if float(reverse[1, 2]) == pytest.approx(float(reverse[1, 0]), rel=0.1):
        pytest.fail(f"reverse mode's anisotropy and extinction lanes coincide ({reverse[1]}): the frame tests nothing")
    forward = jax.jit(jax.jacfwd(weighted_terms)).lower(fields).compile({"xla_cpu_experimental_ynn_fusion_type": ""})
    np.testing.assert_allclose(forward(fields), reverse, rtol=1e-3, atol=1e-3)


FITTED = ("extinction", "max_distance", "height_falloff", "layer_top", "anisotropy", "direct_fraction", "ambient_rise",
          "thickness", "edge_softness", "fov_x_deg", "light_depth")  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize("light_depth", [12.0, math.inf])
def test_gradients_float64(x64, rng, light_depth, monkeypatch):
    """Every fitted field's derivative against central differences, with the segments' placement held where the
    start put it, as the kernel holds it (`fog_march.placement_depth`: where the segments lie is a sampling choice)."""
    image, depth = jnp.asarray(_image(rng)), jnp.asarray(_depth())
    values = dict(MEDIUM, light_depth=light_depth)
    names = [name for name in FITTED if not (name == "light_depth" and math.isinf(light_depth))]
    placements, placed = [], fog_march.placement_depth

    def recording(*args, **kwargs):
        placements.append(placed(*args, **kwargs))
        return placements[-1]

    def fogged(light_xy, *scalars):
        options = dict(values, **dict(zip(names, scalars)))
        return _fog(image, depth, light_xy, **options)

    # No depth sample on a pixel edge (nearest sampling steps there): the finite differences stay on one side.
    start = (jnp.asarray([2.33, 0.71]), *(jnp.asarray(values[name], jnp.float64) for name in names))
    direction = jax.tree_util.tree_map(lambda x: jnp.full_like(x, 0.1) * jnp.maximum(jnp.abs(x), 1.0), start)

    def derivative():  # traced anew on each call, so that it sees the placement patched in
        return jax.jit(lambda *primals: jax.jvp(fogged, primals, direction)[1])(*start)

    kernels = derivative()
    monkeypatch.setattr(fog_march, "placement_depth", recording)
    held = jax.jit(lambda *args: (fogged(*args), placements[:]))(*start)[1]
    calls = itertools.count()
    monkeypatch.setattr(fog_march, "placement_depth", lambda *args, **kwargs: held[next(calls) % len(held)])
    np.testing.assert_allclose(derivative(), kernels, rtol=1e-9, atol=1e-12)  # the kernel holds it too
    check_grads(jax.jit(fogged), start, order=1, modes=("fwd", "rev"), eps=1e-5, atol=1e-4, rtol=1e-4)


@pytest.mark.slow
def test_reduced_march_derivative_where_pixels_see_the_sky(x64):
    """A sky pixel reads each ray through its pieces' ends and takes them whole, with their own derivatives: the
    derivative in the medium's extent matches finite differences (a read at exactly the end counted half of it).
    Loosely: the rays' split is a sampling choice that moves with the extent, its derivative held at zero."""
    depth = np.full((12, 16), 6.0)
    depth[3:, 9:11], depth[:4] = 2.0, np.inf
    options = dict(MEDIUM, layer_top=math.inf, resolution_factor=4)
    options.pop("max_distance")

    def total(max_distance):
        fog = kernel_options(dict(options, max_distance=max_distance))
        return jnp.sum(volumetric_fog_terms(jnp.asarray(depth), jnp.asarray([13.3, 1.7]), **fog)[1])

    @jax.jit
    def derivatives(max_distance):
        return jax.jvp(total, (max_distance,), (1.0,))[1], (total(max_distance + 1e-3) - total(max_distance - 1e-3)) / 2e-3

    np.testing.assert_allclose(*derivatives(25.0), rtol=1e-2)


DEGENERATE = {
    "behind the camera": dict(light_xy=(3.0, 2.0), light_in_front=False),
    "far off screen": dict(light_xy=(1e7, -3e6), resolution_factor=2),  # and the reduced march anchored to it
    "on a pixel centre": dict(light_xy=(2.5, 1.5), resolution_factor=1.5),
    "on the optical axis": dict(light_xy=(3.0, 2.0)),
    "at infinity": dict(light_xy=(2.5, 1.5), light_depth=math.inf),
    "at the camera": dict(light_xy=(3.0, 2.0), light_depth=1e-6),
}


RESOLUTION_FACTORS = sorted({case.get("resolution_factor", 1) for case in DEGENERATE.values()})


@pytest.mark.parametrize("resolution_factor", slow_where(RESOLUTION_FACTORS, {1.5, 2}))
def test_degenerate_lights_finite_values_and_gradients(rng, resolution_factor):
    """Every case of `DEGENERATE` at this march spacing, through one compiled loss (the light's distance and side
    traced), on a frame with surfaces and on one all sky."""
    image = jnp.asarray(_image(rng), jnp.float32)

    @jax.jit
    @functools.partial(jax.value_and_grad, argnums=(0, 1, 2, 3, 4))
    def loss(light_xy, extinction, thickness, fov_x_deg, depth, light_depth, light_in_front):
        return jnp.sum(_fog(image, depth, light_xy, extinction=extinction, thickness=thickness, fov_x_deg=fov_x_deg,
                            light_depth=light_depth, light_in_front=light_in_front,
                            resolution_factor=resolution_factor))  # fmt: skip

    cases = {name: case for name, case in DEGENERATE.items() if case.get("resolution_factor", 1) == resolution_factor}
    for name, case in cases.items():
        light = (jnp.asarray(case["light_xy"], jnp.float32), jnp.float32(case.get("light_depth", 12.0)),
                 jnp.asarray(case.get("light_in_front", True)))  # fmt: skip
        for depth in (jnp.asarray(_depth(), jnp.float32), jnp.full((HEIGHT, WIDTH), jnp.inf)):  # and a frame all sky
            value, grads = loss(light[0], 0.06, 0.3, 60.0, depth, *light[1:])
            assert np.isfinite(float(value)), name
            assert all(np.all(np.isfinite(np.asarray(g))) for g in grads), name


def test_zero_density_leaves_the_frame(rng):
    image, depth = jnp.asarray(_image(rng), jnp.float32), jnp.asarray(_depth(), jnp.float32)
    fogged = jax.jit(functools.partial(_fog, extinction=0.0))(image, depth, jnp.asarray([2.3, 0.7]))
    np.testing.assert_array_equal(fogged, image)


def test_camera_above_the_layer_sees_haze_only_below_it(x64):
    depth = np.full((HEIGHT, WIDTH), np.inf)
    options = dict(MEDIUM, layer_top=-1.0)
    _, scattered, ambient = _terms(depth, [2.3, 0.7], **options)
    assert np.all(np.asarray(ambient[: HEIGHT // 2]) == 0)  # rays going up never meet the layer below
    assert np.all(np.asarray(ambient[HEIGHT // 2 :]) > 0)
    assert np.all(np.asarray(scattered[: HEIGHT // 2]) == 0)
    # The ambient's rise counts heights from where each ray enters the layer's top, below the camera.
    expected = _Loop(depth, (2.3, 0.7), light_depth=math.inf, in_front=True, **options).terms()[2]
    np.testing.assert_allclose(np.asarray(ambient), expected, rtol=2e-3, atol=1e-6)
    flat = _terms(depth, [2.3, 0.7], **dict(options, ambient_rise=0.0))[2]
    assert np.all(np.asarray(ambient[HEIGHT // 2 :]) < np.asarray(flat[HEIGHT // 2 :]))  # lower than the camera


def test_reduced_resolution_matches_loop(x64):
    """Rays 2.5 pixels apart (not a divisor of the frame's 6 x 4) anchored to a light off screen (the margin's rays
    read nothing beyond the screen), upsampled by depth."""
    light_xy, light_depth, in_front = CASES["point light off screen"]
    depth = _depth()
    expected = _Loop(depth, light_xy, light_depth=light_depth, in_front=in_front, **MEDIUM).reduced_scattered(2.5)
    _, got, _ = _terms(depth, light_xy, light_depth=light_depth, light_in_front=in_front, resolution_factor=2.5, **MEDIUM)
    np.testing.assert_allclose(np.asarray(got), expected, rtol=2e-3, atol=1e-6)


COVERAGE_CASES = ["no coverage", "beside the sky", "beside surfaces", "every pixel"]


@pytest.mark.parametrize("case", slow_where(COVERAGE_CASES, set(COVERAGE_CASES) - {"no coverage"}))
def test_partly_covered_pixels_at_reduced_resolution_match_loop(x64, case):
    """With march rays between the pixels, a partly covered pixel reads them up to its surface's depth and up to
    what its uncovered part sees, and blends the two. A render that takes no derivatives (`values_only`) reads
    the second side at those pixels alone, in chunks of five (`fog_reading.blend_where_partly_covered`), and each
    ray through the piece holding the depth (`fog_reading.read_holding_piece`): the same values as the render
    that does, whose derivatives go through both sides and every piece. Every pixel partly covered: the last
    chunk starts earlier and reads some again."""
    light_xy, light_depth, in_front = CASES["point light in the medium"]
    depth = _depth()
    coverage = np.isfinite(depth).astype(float)
    coverage[1, 1], coverage[1, 2], coverage[0, 3], coverage[3, 4], coverage[2, 3] = 0.3, 0.6, 0.45, 0.8, 0.7
    if case == "every pixel":
        coverage = np.clip(coverage, 0.2, 0.9)
        assert depth.size % 5, "the chunks of five must not divide the frame"
    uncovered = np.full(depth.shape, np.inf)
    if case in ("beside surfaces", "every pixel"):
        uncovered[2, 3], uncovered[3, 4] = 11.0, 20.0  # the far ground's pixel partly the near one, and the reverse
    loop = _Loop(depth, light_xy, light_depth=light_depth, in_front=in_front, **MEDIUM)
    if case == "no coverage":
        expected = loop.reduced_scattered(2.5)
    else:
        padded = np.pad(depth, 1, constant_values=np.inf)
        height, width = depth.shape
        nearest = np.min([padded[dy : dy + height, dx : dx + width] for dy in range(3) for dx in range(3)], axis=0)
        covering = np.where(np.isfinite(depth), depth, nearest)  # a sky pixel's surface: its nearest neighbour's
        surface, beside = (loop.reduced_scattered(2.5, reading) for reading in (covering, uncovered))
        expected = coverage * surface + (1 - coverage) * beside

    def scattered(extinction):
        options = kernel_options({**MEDIUM, "extinction": extinction})
        covered = {"coverage": jnp.asarray(coverage), "uncovered_depth": jnp.asarray(uncovered)}
        covered = {} if case == "no coverage" else covered
        return volumetric_fog_terms(
            jnp.asarray(depth), jnp.asarray(light_xy), light_depth=light_depth, light_in_front=in_front,
            resolution_factor=2.5, **covered, **options,
        )[1]  # fmt: skip

    def values_alone(extinction):
        with values_only():
            return scattered(extinction)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(volumetric, "_BAND_PIXELS", 5)
        cheaper = jax.jit(values_alone)(MEDIUM["extinction"])
        along, derivative = jax.jit(lambda e: jax.jvp(scattered, (e,), (1.0,)))(MEDIUM["extinction"])
    np.testing.assert_allclose(np.asarray(cheaper), expected, rtol=2e-3, atol=1e-6)
    np.testing.assert_allclose(np.asarray(along), expected, rtol=2e-3, atol=1e-6)
    np.testing.assert_allclose(np.asarray(cheaper), np.asarray(along), rtol=1e-12, atol=1e-15)
    assert np.all(np.isfinite(np.asarray(derivative))) and float(jnp.max(jnp.abs(derivative))) > 0


@pytest.mark.slow
@pytest.mark.parametrize("shadows, resolution_factor", [("samples", 1), ("lines", 2.5)])  # each reading, each spacing
def test_a_sun_known_when_traced_gives_the_traced_suns_terms_and_derivatives(x64, shadows, resolution_factor):
    """A sun given as a Python `inf` drops the point light's branches from the program (`light_geometry`): the
    terms and their derivatives are those of the sun given as a traced `inf`, in a render that takes derivatives
    and in one that does not (`values_only`), on a partly covered frame."""
    light_xy, _, _ = CASES["sun in front"]
    depth = _depth()
    coverage = jnp.asarray(np.isfinite(depth) * 0.75 + 0.25)
    fields = jnp.asarray([MEDIUM["extinction"], MEDIUM["fov_x_deg"]])

    def terms(values, light_depth):
        options = {**MEDIUM, "extinction": values[0], "fov_x_deg": values[1], "shadows": shadows}
        return jnp.stack(volumetric_fog_terms(
            jnp.asarray(depth), light_xy, light_depth=light_depth, light_in_front=True, coverage=coverage,
            resolution_factor=resolution_factor, **kernel_options(options),
        ))  # fmt: skip

    def with_derivatives(light_depth):
        return jax.jit(lambda values: (terms(values, light_depth), jax.jacfwd(terms)(values, light_depth)))

    def values_alone(values, light_depth):
        with values_only():
            return terms(values, light_depth)

    known, traced = with_derivatives(math.inf)(fields), with_derivatives(jnp.asarray(math.inf))(fields)
    cheap = jax.jit(lambda values: values_alone(values, math.inf))(fields)
    cheap_traced = jax.jit(values_alone)(fields, jnp.asarray(math.inf))
    for got, expected in zip((*known, cheap), (*traced, cheap_traced)):
        np.testing.assert_allclose(np.asarray(got), np.asarray(expected), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(np.asarray(cheap), np.asarray(known[0]), rtol=1e-12, atol=1e-15)
    assert float(jnp.max(jnp.abs(known[1]))) > 0 and np.all(np.isfinite(np.asarray(known[1])))


@pytest.mark.slow
def test_reads_by_bands_of_rows_are_the_frames_values_and_derivatives(x64, monkeypatch):
    """On a larger frame the rays are marched and the pixels read them a band of rows at a time (`_BAND_PIXELS`):
    the same terms and derivatives as the whole frame at once, with last bands the rows fill only partly (13 rows in
    bands of 3 pixel rows, 7 rays' rows in bands of 5) and a partly covered frame."""
    light_xy, light_depth, in_front = CASES["point light off screen"]
    depth = np.repeat(np.repeat(np.asarray(_depth()), 3, axis=0), 2, axis=1)[:13]  # 13 x 12
    coverage = jnp.asarray(np.isfinite(depth) * 0.75 + 0.25)
    fields = jnp.asarray([MEDIUM["extinction"], MEDIUM["max_distance"]])

    def evaluated():
        """The terms and their derivatives, traced afresh (a function jitted before would keep its first trace)."""

        def terms(values):
            options = {**MEDIUM, "extinction": values[0], "max_distance": values[1]}
            return jnp.stack(volumetric_fog_terms(
                jnp.asarray(depth), light_xy, light_depth=light_depth, light_in_front=in_front, resolution_factor=2.5,
                coverage=coverage, **kernel_options(options),
            ))  # fmt: skip

        def derivatives(values):  # forward and reverse mode, as a fit and a user's grad take them
            return jax.jacfwd(terms)(values), jax.jacrev(terms)(values)

        return *jax.jit(derivatives)(fields), jax.jit(terms)(fields)

    whole = evaluated()
    monkeypatch.setattr(volumetric, "_BAND_PIXELS", 40)  # bands of 3 rows of 12 pixels, the march's of 5 rows of 7 rays
    banded = evaluated()
    for got, expected in zip(banded, whole):
        np.testing.assert_allclose(np.asarray(got), np.asarray(expected), rtol=1e-10, atol=1e-12)
    assert np.all(np.isfinite(np.asarray(banded[0]))) and float(jnp.max(jnp.abs(banded[0]))) > 0


@pytest.mark.parametrize("anisotropy, tolerance", [(-0.5, 1e-4), (0.3, 1e-5), (0.7, 3e-3), (0.9, 0.1)])
def test_a_segments_phase_is_its_mean_weighted_by_the_light(x64, anisotropy, tolerance):
    """`fog_march.segment_phase` against the irradiance-weighted mean of the phase along segments of a ray that
    passes a point light 0.3 units off (before it, across it, after it) and one through it, by midpoint sums of
    200000 steps on each side of the closest approach; the sun's phase at one distance is left as it was."""
    toward, depth = np.array([0.0, 0.0, 1.0]), 10.0
    medium = BoundedMedium(extinction=0.05, max_distance=40.0, anisotropy=anisotropy)
    for miss in (0.3, 0.0):
        view = np.array([miss, 0.0, depth]) / np.hypot(miss, depth)
        along, across = light_approach(jnp.asarray(view), jnp.asarray(toward), 1.0 / depth)
        lower, upper = np.array([2.0, 8.0, 9.7, 10.5]), np.array([8.0, 12.0, 10.2, 30.0])
        got = fog_march.segment_phase(jnp.asarray(lower), jnp.asarray(upper), along, across, 1.0 / depth, medium)
        loop = _Loop(np.full((1, 1), np.inf), (0.5, 0.5), light_depth=depth, in_front=True, **MEDIUM)
        loop.toward, loop.g = toward, anisotropy
        want = [loop.mean_phase(view, a, b, n=200000) for a, b in zip(lower, upper)]
        np.testing.assert_allclose(np.asarray(got), want, rtol=tolerance, err_msg=f"miss {miss}")
    midpoint = _hg(np.cos(np.pi / 2), anisotropy)  # the angle across the ray, where the phase was read
    assert anisotropy <= 0.3 or want[1] > 2 * midpoint, "the segment across the light must weigh its forward part"
    check_grads(lambda g: fog_march.segment_phase(jnp.asarray(lower), jnp.asarray(upper), along, across, 0.1,
                                                  BoundedMedium(0.05, 40.0, g)), (anisotropy,), order=1, modes=["fwd", "rev"])  # fmt: skip


def test_march_rays_ride_with_the_light(x64):
    """The march rays sit at the light's position plus multiples of the spacing and cover the screen with a margin:
    a light moved by part of a spacing moves every ray by as much, a light moved by whole spacings (far off screen
    too) leaves them where they were."""
    light = np.array([5.3, 2.2])
    xs, ys = march_grid(jnp.asarray(light), 8, 12, 2.5, jnp.float64)
    assert xs[0] <= 0 and xs[-1] >= 12 and ys[0] <= 0 and ys[-1] >= 8
    np.testing.assert_allclose(np.diff(xs), 2.5)
    np.testing.assert_allclose(np.mod(xs - light[0], 2.5), 0, atol=1e-12)
    moved = march_grid(jnp.asarray(light + [0.7, 0.2]), 8, 12, 2.5, jnp.float64)
    np.testing.assert_allclose(moved[0], xs + 0.7, atol=1e-12)
    np.testing.assert_allclose(moved[1], ys + 0.2, atol=1e-12)
    far = march_grid(jnp.asarray(light + [2.5e6, -5.0e5]), 8, 12, 2.5, jnp.float64)
    np.testing.assert_allclose(far[0], xs, atol=1e-6)
    np.testing.assert_allclose(far[1], ys, atol=1e-6)


def test_reduced_march_moves_with_a_panned_scene(x64):
    """A scene and its light moved one pixel sideways (a pan, nearly: the field of view is narrow) give the same
    reduced in-scattering moved by that pixel: the march rays moved with them. A grid fixed to the pixels saw
    other parts of the scene."""
    depth = np.full((8, 16), np.inf)
    depth[3:, 2:4], depth[2:, 9], depth[5:, 12:15] = 6.0, 9.0, 12.0
    options = dict(MEDIUM, fov_x_deg=2.0, resolution_factor=4)
    run = jax.jit(lambda d, l: volumetric_fog_terms(d, l, light_depth=40.0, **kernel_options(options))[1])
    still = np.asarray(run(jnp.asarray(depth), jnp.asarray([8.3, 1.6])))
    panned = np.asarray(run(jnp.asarray(np.roll(depth, 1, axis=1)), jnp.asarray([9.3, 1.6])))
    np.testing.assert_allclose(panned[:, 5:12], still[:, 4:11], rtol=2e-3)  # the margin beyond the screen differs


def test_a_hole_under_a_march_ray_changes_its_neighbours_by_the_sampling_alone(x64):
    """Every pixel reads its nearby rays up to its own depth, whatever surface each ray met: a one-texel hole in a
    wall under a march ray (what a trunk's edge sliding under a ray does in a pan) moves the pixels around it only
    by where that ray's segments lie. Choosing the rays whose own length was alike made them jump."""
    depth = np.full((12, 16), 6.0)
    depth[3:, 9:11] = 2.0  # a post in front of the wall, shadowing the haze toward the camera
    options = dict(MEDIUM, layer_top=math.inf, num_view_steps=64, resolution_factor=4)
    light = jnp.asarray([13.3, 1.7])
    run = jax.jit(lambda d: volumetric_fog_terms(d, light, **kernel_options(options))[1])
    holed = depth.copy()
    holed[5, 5] = np.inf  # under the march ray at (5.3, 5.7)
    wall, hole = np.array(run(jnp.asarray(depth))), np.array(run(jnp.asarray(holed)))
    hole[5, 5] = wall[5, 5]  # the hole's own pixel sees the sky now
    # The ray's second piece now starts halfway to the medium's end, and its segments (even in transmittance) move.
    np.testing.assert_allclose(hole, wall, rtol=5e-3)


def test_shadows_move_smoothly_with_the_light(x64):
    """Each shadow sample reads the four texels around it: a light moved across a texel's edge moves the
    shadow by as little (nearest texels made it jump from lit to dark)."""
    depth = np.full((4, 8), np.inf)
    depth[:, 3] = 5.0  # a post; the light's own pixel sample falls on its edge

    @jax.jit
    def shadow(light_x):
        return segment_visibility(
            jnp.asarray(depth), jnp.stack([light_x, 2.5]), jnp.asarray([[[6.5, 2.5]]]), jnp.asarray([[[2.0]]]),
            fov_x_deg=60.0, thickness=0.3, edge_softness=0.05, num_shadow_samples=1,
        )  # fmt: skip

    def visibility(light_x):
        return np.asarray(shadow(jnp.float64(light_x)))

    np.testing.assert_allclose(visibility(2.999), 0.5, atol=0.01)
    np.testing.assert_allclose(visibility(3.001), 0.5, atol=0.01)
    np.testing.assert_allclose(visibility(2.5), 1.0)
    np.testing.assert_allclose(visibility(3.5), 0.0)


def test_a_frame_with_little_sky_is_read_as_closed_beyond_its_edges():
    """1 up to `ENCLOSED_SKY[0]` of the pixels sky, 0 from `ENCLOSED_SKY[1]`, linear between."""
    low, high = ENCLOSED_SKY
    for share, expected in ((0.0, 1.0), (low, 1.0), (0.5 * (low + high), 0.5), (high, 0.0), (0.4, 0.0)):
        depth = np.full(1000, 7.0)
        depth[: round(share * 1000)] = np.inf
        assert float(enclosure(jnp.asarray(depth.reshape(20, 50)))) == pytest.approx(expected, abs=1e-6), share


@pytest.mark.parametrize("reading", ["samples", "lines"])
def test_a_ray_leaving_a_closed_frame_in_front_of_its_edge_is_shaded(reading):
    """A wall 10 away fills the frame; the sun ahead, off the top edge. A point 3 away reaches the top edge in front
    of the wall: read closed, the ceiling out of view shades it; read open, nothing does. A point beyond the wall's
    slab leaves behind it: lit either way. Both readings agree."""
    depth = jnp.full((8, 16), 10.0)
    pixel_xy, distances = jnp.asarray([[[8.5, 6.5]]]), jnp.asarray([[[3.0, 25.0]]])
    options = dict(fov_x_deg=60.0, thickness=0.1, edge_softness=0.02)

    def visibility(enclosed):
        if reading == "samples":
            return segment_visibility(depth, (8.0, -40.0), pixel_xy, distances, num_shadow_samples=16,
                                      enclosed=enclosed, **options)[0, 0]  # fmt: skip
        return segment_visibility_by_lines(depth, (8.0, -40.0), pixel_xy, distances - 0.05, distances + 0.05,
                                           max_distance=40.0, enclosed=enclosed, **options)[0, 0]  # fmt: skip

    np.testing.assert_allclose(np.asarray(visibility(1.0)), [0.0, 1.0], atol=0.02)
    np.testing.assert_allclose(np.asarray(visibility(0.0)), [1.0, 1.0], atol=0.02)
    # Under jit and vmap (over how closed) as eagerly; finite gradients with the frame halfway closed.
    closed = jnp.asarray([0.0, 0.5, 1.0])
    batched = jax.jit(jax.vmap(visibility))(closed)
    for index, value in enumerate(closed):
        np.testing.assert_allclose(np.asarray(batched[index]), np.asarray(visibility(value)), atol=1e-5)
    gradient = jax.grad(lambda value: jnp.sum(visibility(value)))(jnp.float32(0.5))
    assert np.isfinite(float(gradient))


def test_bad_options_name_the_argument():
    depth, fog = jnp.ones((HEIGHT, WIDTH)), kernel_options(MEDIUM)
    with pytest.raises(ValueError, match="num_view_steps"):
        volumetric_fog_terms(depth, jnp.zeros(2), **dict(fog, num_view_steps=0))
    with pytest.raises(ValueError, match="resolution_factor"):
        volumetric_fog_terms(depth, jnp.zeros(2), **dict(fog, resolution_factor=0.5))
    with pytest.raises(ValueError, match="shadow samples' count"):
        ShadowSamples(2.5)
    with pytest.raises(ValueError, match="num_bins"):
        ShadowLines(num_lines=8, num_bins=1)
    with pytest.raises(ValueError, match="thickness"):
        Slabs(thickness=jnp.ones(2))
    with pytest.raises(ValueError, match="shadows must be a ShadowSamples or a ShadowLines"):
        volumetric_fog_terms(depth, jnp.zeros(2), **dict(fog, shadows="lines"))
    with pytest.raises(ValueError, match="medium must be a BoundedMedium"):
        volumetric_fog_terms(depth, jnp.zeros(2), **dict(fog, medium=dict(extinction=0.1)))
    with pytest.raises(ValueError, match="uncovered_depth needs coverage"):
        volumetric_fog_terms(depth, jnp.zeros(2), uncovered_depth=depth, **fog)
    with pytest.raises(ValueError, match="uncovered_depth"):
        volumetric_fog_terms(depth, jnp.zeros(2), coverage=depth, uncovered_depth=depth[1:], **fog)
