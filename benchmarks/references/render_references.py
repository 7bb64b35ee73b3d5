"""Render the path-traced reference frames with Mitsuba 3: per scene a clean frame and two fog frames.

    DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM-19.so \\
        python benchmarks/references/render_references.py [SCENE ...] [--spp 256] [--variant llvm_ad_rgb]
            [--geometry-only] [--light-view] [--size 320x180] [--out FOLDER]

Every scene is 320x180 (`--size WxH` renders it at another size, to fit a
frame as a user renders it rather than one made larger by repeating pixels),
camera looking along -z with a horizontal field of view of 50 degrees, ground
at y = 0. Per scene NAME it writes into this folder:

- `NAME_clean.exr`: the frame without a medium (path tracer, max depth 3,
  four times the fog's samples per pixel): `R, G, B` (linear), `A` (the
  fraction of a 16x16 grid of rays in the pixel that hit geometry: a 4x4 grid's
  steps of a quarter left one-pixel lines along every silhouette in a fit's
  difference), `Z` (the
  distance along the pixel centre's camera ray, scene units, `+inf` on sky).
- `NAME_fog_a.exr`, `NAME_fog_b.exr`: the same frame inside a homogeneous
  medium (volumetric path tracer, max depth 3), seeds 1 and 2: `R, G, B`.

`--geometry-only` casts the clean frames' `A` and `Z` again and rewrites them
beside the colour already stored, which it keeps (no render, seconds a scene).

`--light-view` writes, for a scene whose (first) light is a sun, `NAME_light_view.exr`:
a shadow map, the depth of the geometry seen from the sun (no medium, no
render of the frame; other scenes are skipped). One channel `Z` (float32,
1024x1024, zip): the planar depth along the light camera's forward axis (the
direction the sunlight travels) from its image plane, scene units, `+inf` where
the pixel centre's ray meets nothing. The light camera is orthographic, its
image plane 300 units from the frame camera toward the sun, centred on the
frame camera, covering 96x96 units (the medium's sphere of radius 40 and a
margin); its up is the world's up made perpendicular to its forward. Its
header carries `godrays:light_view_projection` (`orthographic`),
`godrays:light_view_from_camera` (the row-major 3x4 `[R | t]` taking a point
`X` in the frame camera's view space to the light camera's, `R @ X + t`, both
x right, y up, z forward, scene units) and `godrays:light_view_scale` (pixels
per scene unit); numbers as `repr` writes them, one space apart. A point at
`(lx, ly, lz)` in light view falls at pixel `(W/2 + scale lx, H/2 - scale ly)`
(x right, y down, centres at `i + 0.5`), lit if `lz` is not beyond the map's
depth there.

Colour is stored as half floats, depth as float32, zip compressed. Every file's
header carries `godrays:light_px` (x right, y down, pixel centres at
`i + 0.5`; for a light behind the camera, `window_behind`'s sun, its
projection mirrored through the camera plane, as `godrays_jax`'s
`project_point` makes it), `godrays:light_in_front` (0 there),
`godrays:light_depth` (the light's distance along its camera ray, scene
units, `inf` for the sun) and
`godrays:fov_x_deg`. Where a scene has several lights (`Scene.more_lights`:
`street_two_lamps`) those three light attributes are the first light's, and
its files also carry every light in `godrays_jax`'s words (`lights_metadata`, read by
`read_lights`): `godrays:lights` (`x,y` each, `x,y,behind` for a light behind
the camera), `godrays:lights_depth` (each light's distance) and
`godrays:lights_tint` (each light's irradiance at the camera, the medium left
out, over the first's, channel by channel: a lamp's radiance times pi
radius^2 over its squared distance, a sun's radiance times its disc's solid
angle; the first's 1 in each channel), `;` between lights, floats as `repr`
writes them.

`scenes.json` (read by `scenes.py`) gets each scene's light (for several
lights also the three `godrays:lights*` texts), medium, samples, render
seconds (wall and CPU) and noise floor: half the display-space MSE between the
two fog frames, display space `x / (1 + |x|)` per channel as `godrays-jax fit`
compares (`kernels.losses.mse_loss`).

The sun is a disc in an environment map (at infinity, so its shafts are
parallel); a lamp is a small emitting sphere inside the medium. The
medium is a sphere around the camera (its radius is the medium's extent),
for `ground_fog` a layer near the ground that the camera stands in, or, for
`window_ahead_room`, the inside of the room alone (its window shows clear sky).

`llvm_ad_rgb` (the default) needs an LLVM newer than 15 (`DRJIT_LIBLLVM_PATH`;
19 works); `--variant scalar_rgb` runs without one, slower. One
render thread (`--threads`), so that a render takes one core.
"""

import argparse
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
WIDTH, HEIGHT = 320, 180
FOV_X_DEG = 50.0
MAX_DEPTH = 3
CLEAN_SPP_FACTOR = 4
PASS_SPP = 32  # samples per launch: the LLVM variant holds one launch's paths in memory at once
SEEDS = {"clean": 0, "fog_a": 1, "fog_b": 2}
GROUND_REFLECTANCE = (0.35, 0.32, 0.27)
ENVMAP_SIZE = (1024, 2048)
COVERAGE_GRID = 16
LIGHT_VIEW_PIXELS = 1024  # the shadow map's width and height
LIGHT_VIEW_SPAN = 96.0  # scene units across it: the medium's sphere (radius 40) and a margin
LIGHT_VIEW_DISTANCE = 300.0  # its image plane's distance from the frame camera toward the sun


# ----------------------------------------------------------------------------- scene description


@dataclass(frozen=True)
class Sun:
    """A disc of `radiance` in a constant sky, `azimuth_deg` right of -z, `elevation_deg` above the horizon."""

    azimuth_deg: float
    elevation_deg: float
    radiance: tuple[float, float, float] = (2500.0, 2100.0, 1600.0)
    radius_deg: float = 1.0
    sky: tuple[float, float, float] = (0.06, 0.08, 0.12)

    def direction(self) -> np.ndarray:
        az, el = math.radians(self.azimuth_deg), math.radians(self.elevation_deg)
        return np.array([math.sin(az) * math.cos(el), math.sin(el), -math.cos(az) * math.cos(el)])


@dataclass(frozen=True)
class Lamp:
    """A small emitting sphere (a bulb) at `position` in a constant night sky."""

    position: tuple[float, float, float]
    radiance: tuple[float, float, float] = (3000.0, 2400.0, 1600.0)
    radius: float = 0.08
    sky: tuple[float, float, float] = (0.002, 0.003, 0.006)


@dataclass(frozen=True)
class Medium:
    """Homogeneous: extinction `sigma_t` (per scene unit), single-scattering `albedo`, Henyey-Greenstein `g`.

    `extent`: a sphere of this radius around the camera, `("layer", top)`:
    the slab from below the ground up to height `top`, 200 units wide, or
    `("box", (x0, x1, y0, y1, z0, z1))`: that box (a room's inside).
    """

    sigma_t: float
    albedo: float
    g: float
    extent: float | tuple[str, float] | tuple[str, tuple[float, ...]]

    def describe(self) -> str:
        if isinstance(self.extent, tuple) and self.extent[0] == "box":
            x0, x1, y0, y1, z0, z1 = self.extent[1]
            where = f"box x {x0:g} to {x1:g}, y {y0:g} to {y1:g}, z {z0:g} to {z1:g} (camera inside)"
        elif isinstance(self.extent, tuple):
            where = f"layer from the ground to y = {self.extent[1]:g} (camera inside)"
        else:
            where = f"sphere of radius {self.extent:g} around the camera"
        return where


@dataclass(frozen=True)
class Scene:
    """`light` is the first light (its sky is the scene's); `more_lights` any others, each a `Lamp` (a sphere of its
    own) or a `Sun` (a disc of its own in the first light's sky)."""

    name: str
    shows: str
    light: Sun | Lamp
    medium: Medium
    camera: tuple[float, float, float] = (0.0, 1.6, 0.0)
    shapes: list = field(default_factory=list)  # (kind, to_world matrix as nested lists, reflectance)
    more_lights: tuple[Sun | Lamp, ...] = ()

    @property
    def lights(self) -> tuple[Sun | Lamp, ...]:
        return (self.light, *self.more_lights)


def box(center, half_size, reflectance=(0.5, 0.5, 0.5)):
    """An axis-aligned box (Mitsuba's cube is [-1, 1]^3)."""
    cx, cy, cz = center
    sx, sy, sz = half_size
    return ("cube", [[sx, 0, 0, cx], [0, sy, 0, cy], [0, 0, sz, cz], [0, 0, 0, 1]], reflectance)


def post(x, z, radius, height, reflectance=(0.45, 0.42, 0.38)):
    """A vertical cylinder on the ground (Mitsuba's cylinder runs along +z from 0 to 1)."""
    return ("cylinder", [[radius, 0, 0, x], [0, 0, height, 0], [0, -radius, 0, z], [0, 0, 0, 1]], reflectance)


def ball(center, radius, reflectance=(0.6, 0.55, 0.5)):
    cx, cy, cz = center
    return ("sphere", [[radius, 0, 0, cx], [0, radius, 0, cy], [0, 0, radius, cz], [0, 0, 0, 1]], reflectance)


def _sun_at(distance, sun: Sun, camera):
    return np.asarray(camera) + distance * sun.direction()


def _hidden_sun() -> Scene:
    sun = Sun(azimuth_deg=-4.0, elevation_deg=5.0)
    center = _sun_at(15.0, sun, (0.0, 1.6, 0.0))
    return Scene(
        "hidden_sun", "a block 15 units away hides the sun: the haze in front of it in its shadow, a halo around it",
        sun, Medium(0.03, 0.9, 0.75, 50.0),
        shapes=[box((center[0], 2.75, center[2]), (1.8, 2.75, 1.0), (0.45, 0.4, 0.35))],
    )


def _blinds() -> Scene:
    sun = Sun(azimuth_deg=6.0, elevation_deg=6.0)
    wall = (0.5, 0.47, 0.43)
    window = [box((-5.1, 1.5, -7.0), (3.5, 1.5, 0.15), wall), box((5.1, 1.5, -7.0), (3.5, 1.5, 0.15), wall),
              box((0.0, 0.4, -7.0), (1.6, 0.4, 0.15), wall), box((0.0, 2.8, -7.0), (1.6, 0.2, 0.15), wall)]
    slats = [box((0.0, 0.95 + 0.3 * i, -7.0), (1.6, 0.07, 0.05), (0.6, 0.57, 0.52)) for i in range(6)]
    return Scene(
        "blinds", "a wall 7 units away, the sun behind blinds in its window: shafts through the gaps toward the camera",
        sun, Medium(0.04, 0.9, 0.7, 40.0), shapes=window + slats,
    )


def _forest() -> Scene:
    sun = Sun(azimuth_deg=2.0, elevation_deg=2.5, radiance=(2500.0, 1700.0, 900.0))
    rng = np.random.default_rng(7)
    trees = []
    while len(trees) < 70:
        x, z = rng.uniform(-22.0, 22.0), rng.uniform(-45.0, -5.0)
        if abs(x) < 1.0 and z > -8.0:
            continue  # keep the view open just in front of the camera
        trees.append(post(x, z, rng.uniform(0.18, 0.45), rng.uniform(7.0, 12.0), (0.3, 0.24, 0.18)))
    return Scene(
        "forest_low_sun", "70 trunks, the sun 2.5 degrees above the horizon behind them: long shafts between trunks",
        sun, Medium(0.025, 0.95, 0.8, 60.0), shapes=trees,
    )


def _sun_off_screen() -> Scene:
    sun = Sun(azimuth_deg=-42.0, elevation_deg=14.0)
    pillars = [post(-4.5, -3.0 - 3.0 * i, 0.45, 6.0) for i in range(10)]
    beam = [box((-4.5, 6.2, -16.5), (0.5, 0.2, 14.0), (0.45, 0.42, 0.38))]
    return Scene(
        "sun_off_screen", "the sun off the left edge behind a colonnade: shafts slant across the view",
        sun, Medium(0.03, 0.9, 0.7, 40.0), shapes=pillars + beam,
    )


def _point_light() -> Scene:
    lamp = Lamp(position=(0.8, 2.4, -10.0))
    fence = [post(-1.85 + 0.55 * i, -7.5, 0.07, 3.2, (0.3, 0.3, 0.3)) for i in range(8)]
    pole = [post(1.1, -10.3, 0.06, 2.3, (0.25, 0.25, 0.25))]
    walls = [box((-7.0, 3.0, -14.0), (0.3, 3.0, 8.0), (0.5, 0.48, 0.45)), box((6.0, 2.5, -16.0), (2.0, 2.5, 2.0))]
    return Scene(
        "point_light", "a lamp 10 units away inside the medium behind a fence: a glow and shadow shafts from the posts",
        lamp, Medium(0.05, 0.9, 0.5, 40.0), shapes=fence + pole + walls,
    )


def _thin_haze() -> Scene:
    sun = Sun(azimuth_deg=16.0, elevation_deg=10.0)
    near = [ball((-0.6, 0.9, -3.2), 0.9, (0.7, 0.35, 0.25))]
    far = [box((-14.0 + 7.0 * i, 2.0 + 1.2 * (i % 3), -38.0 - 4.0 * (i % 2)), (2.5, 2.0 + 1.2 * (i % 3), 2.5))
           for i in range(5)]
    return Scene(
        "thin_haze", "a clear near ball in thin haze, far blocks faded by it, the sun in the upper right",
        sun, Medium(0.006, 0.95, 0.8, 80.0), shapes=near + far,
    )


def _ground_fog() -> Scene:
    sun = Sun(azimuth_deg=5.0, elevation_deg=8.0)
    pillars = [post(-6.0 + 3.0 * i, -14.0 - 2.0 * (i % 2), 0.4, 5.0) for i in range(5)]
    pillars += [post(-9.0, -6.0, 0.35, 5.0), post(8.0, -9.0, 0.35, 5.0)]
    return Scene(
        "ground_fog", "a fog layer 2.5 units deep, the camera in it, the sun above it: surfaces and haze lit through the fog",
        sun, Medium(0.1, 0.95, 0.6, ("layer", 2.5)), camera=(0.0, 1.2, 0.0), shapes=pillars,
    )


def _street_two_lamps() -> Scene:
    near = Lamp(position=(-2.6, 3.0, -8.4), radiance=(1800.0, 1350.0, 810.0), sky=(0.002, 0.002, 0.002))
    far = Lamp(position=(3.6, 3.0, -16.5), radiance=(1800.0, 2100.0, 3000.0))
    # each lamp a globe on its post, the post a little nearer the camera: a shadow fanning down toward it
    lamp_posts = [post(-2.6, -8.2, 0.07, 2.9, (0.25, 0.25, 0.25)), post(3.6, -16.3, 0.08, 2.9, (0.25, 0.25, 0.25))]
    # in front of the halos, their shadows passing near the camera: a tall post just right of the near lamp, one
    # just left of the far lamp, a kiosk under the far lamp
    occluders = [post(-1.37, -5.0, 0.1, 5.0, (0.3, 0.3, 0.3)), post(2.0, -11.0, 0.1, 5.0, (0.3, 0.3, 0.3)),
                 box((2.8, 1.0, -13.5), (0.8, 1.0, 0.6), (0.4, 0.38, 0.35))]
    facades = [box((-7.0, 4.0, -22.0), (0.3, 4.0, 16.0), (0.45, 0.42, 0.4)),
               box((8.5, 4.0, -24.0), (0.3, 4.0, 16.0), (0.45, 0.42, 0.4))]
    return Scene(
        "street_two_lamps", "a night street in fog, two lamps (a warm one 9 units away on the left, a cool one 17 "
        "units away on the right), posts and a kiosk in front of them: two glows with shadow shafts",
        near, Medium(0.05, 0.9, 0.7, 40.0), shapes=lamp_posts + occluders + facades, more_lights=(far,),
    )


def _canopy_sun_above() -> Scene:
    # 30 degrees up (off the top edge at y = -109): high enough to leave the frame, low enough that the view meets
    # its shafts 30 degrees from the sun, where the phase function is 2.4 times what it is at 45
    sun = Sun(azimuth_deg=4.0, elevation_deg=30.0)
    rng = np.random.default_rng(23)

    def roof_height(x, z):  # the canopy's mid height: a gentle swell between 4.8 and 6.2
        return 5.5 + 0.4 * math.sin(0.45 * x + 1.0) + 0.3 * math.cos(0.37 * z)

    # 16 openings in the roof where the view meets their shafts, at least a unit apart
    gaps = []
    while len(gaps) < 16:
        x, z, r = rng.uniform(-9.0, 9.0), rng.uniform(-34.0, -8.0), rng.uniform(1.4, 2.6)
        if all((x - gx) ** 2 + (z - gz) ** 2 > (r + gr + 1.0) ** 2 for gx, gz, gr in gaps):
            gaps.append((x, z, r))
    # the roof: 2000 leaves 1-2 units across (about 95% cover between the gaps), x in [-18, 18], z in [-50, -4], wide
    # and deep enough that the sun reaches no fog in view except through it
    leaves = []
    while len(leaves) < 2000:
        x, z = rng.uniform(-18.0, 18.0), rng.uniform(-50.0, -4.0)
        if any((x - gx) ** 2 + (z - gz) ** 2 < r * r for gx, gz, r in gaps):
            continue
        y = roof_height(x, z) + rng.uniform(-0.6, 0.6)
        shade = rng.uniform(0.8, 1.2)
        leaves.append(box((x, y, z), (rng.uniform(0.5, 1.0), 0.03, rng.uniform(0.5, 1.0)),
                          (0.12 * shade, 0.2 * shade, 0.07 * shade)))
    trunks = [post(x, z, r, roof_height(x, z), (0.3, 0.24, 0.18))
              for x, z, r in ((-5.5, -9.0, 0.3), (4.5, -12.5, 0.35), (-2.0, -19.0, 0.3), (7.5, -22.0, 0.35),
                              (-8.5, -25.0, 0.35), (1.5, -28.0, 0.3))]
    return Scene(
        "canopy_sun_above", "a roof of leaves on trunks 4-7 units up, the sun 30 degrees up beyond it, off the top "
        "edge: the roof dark against bright gaps, shafts slanting down through the gaps onto the ground",
        sun, Medium(0.04, 0.9, 0.7, 40.0), shapes=trunks + leaves,
    )


def _window_behind() -> Scene:
    # 35 degrees up behind the camera, 10 degrees to its left, through a window high in the wall 2 units behind the
    # camera: the beam slants forward and down across the view onto the floor 7-9.5 units ahead, where the floor is in
    # view (from 6.1 ahead: the frame's lower edge is 14.7 degrees down). At 35 degrees only a window 6.5 units up
    # throws the patch that far, so the room is 8.5 high. Looking away from the sun the haze scatters 130-150 degrees
    # (g = 0.7: a hundredth of the forward lobe), so the sun is 40 times the others' for a beam in view.
    sun = Sun(azimuth_deg=190.0, elevation_deg=35.0, radiance=(100000.0, 84000.0, 64000.0))
    wall, bar = (0.5, 0.47, 0.43), (0.6, 0.57, 0.52)

    def slab(x0, x1, y0, y1, z0, z1, reflectance=wall):  # a box from its bounds
        return box(((x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2), ((x1 - x0) / 2, (y1 - y0) / 2, (z1 - z0) / 2),
                   reflectance)

    # inside: x in [-4, 4], y in [0, 8.5], z in [-14, 2]; walls 0.2 thick, down into the ground
    room = [slab(-4.2, 4.2, 8.5, 8.7, -14.2, 2.2), slab(-4.2, -4.0, -0.1, 8.5, -14.2, 2.2),
            slab(4.0, 4.2, -0.1, 8.5, -14.2, 2.2), slab(-4.0, 4.0, -0.1, 8.5, -14.2, -14.0)]
    left, right, bottom, top = -1.8, 0.2, 6.5, 8.1  # the window in the back wall: 2 wide, 1.6 high
    mid_x, mid_y = (left + right) / 2, (bottom + top) / 2
    back = [slab(-4.0, left, -0.1, 8.5, 2.0, 2.2), slab(right, 4.0, -0.1, 8.5, 2.0, 2.2),
            slab(left, right, -0.1, bottom, 2.0, 2.2), slab(left, right, top, 8.5, 2.0, 2.2)]
    cross = [slab(mid_x - 0.08, mid_x + 0.08, bottom, top, 2.05, 2.15, bar),
             slab(left, right, mid_y - 0.08, mid_y + 0.08, 2.05, 2.15, bar)]
    return Scene(
        "window_behind", "a closed room 8 wide, 8.5 high, 16 deep, the sun 35 degrees up behind the camera through a "
        "cross-barred window high in the wall 2 units behind it: a beam slanting down across the view onto a "
        "window-shaped patch on the floor 7-9.5 units ahead, the rest dark but for its bounce",
        sun, Medium(0.06, 0.9, 0.7, 17.0), shapes=room + back + cross,
    )


def _window_ahead(name: str = "window_ahead", haze_inside: bool = False) -> Scene:
    # The sun 40 degrees up straight ahead (off the top edge: the frame's half height is 14.7 degrees), through a
    # window in the far wall 12 units ahead, 2.5-4 units up (in view, 4-11 degrees up): the beam slants down toward
    # the camera onto the floor 7-9 units ahead, where the floor is in view (from 6.1). The window shows the sky and
    # the haze outside, lit; the room's other walls are dark but for the light bounced off the patch.
    sun = Sun(azimuth_deg=0.0, elevation_deg=40.0)
    wall = (0.5, 0.47, 0.43)

    def slab(x0, x1, y0, y1, z0, z1, reflectance=wall):  # a box from its bounds
        return box(((x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2), ((x1 - x0) / 2, (y1 - y0) / 2, (z1 - z0) / 2),
                   reflectance)

    # inside: x in [-4, 4], y in [0, 6], z in [-12, 3]; walls 0.2 thick, down into the ground
    room = [slab(-4.2, 4.2, 6.0, 6.2, -12.2, 3.2), slab(-4.2, -4.0, -0.1, 6.0, -12.2, 3.2),
            slab(4.0, 4.2, -0.1, 6.0, -12.2, 3.2), slab(-4.0, 4.0, -0.1, 6.0, 3.0, 3.2)]
    left, right, bottom, top = -1.2, 1.2, 2.5, 4.0  # the window in the far wall: 2.4 wide, 1.5 high
    far = [slab(-4.0, left, -0.1, 6.0, -12.2, -12.0), slab(right, 4.0, -0.1, 6.0, -12.2, -12.0),
           slab(left, right, -0.1, bottom, -12.2, -12.0), slab(left, right, top, 6.0, -12.2, -12.0)]
    bar = slab(-0.06, 0.06, bottom, top, -12.15, -12.05, (0.6, 0.57, 0.52))  # a mullion down the window's middle
    shows = ("a room 8 wide, 6 high, 15 deep, a window with a mullion in the far wall 12 units ahead, the sun 40 "
             "degrees up beyond it, off the top edge: a beam from the window slanting down toward the camera onto a "
             "window-shaped patch on the floor 7-9 units ahead, the mullion's shadow down the beam")
    # The haze inside the room alone (a hundredth inside its walls, down into the ground): the window shows clear sky.
    inside = ("box", (-3.99, 3.99, -0.5, 5.99, -11.99, 2.99))
    return Scene(name, shows + ("; the haze fills the room alone" if haze_inside else ""), sun,
                 Medium(0.06, 0.9, 0.7, inside if haze_inside else 17.0), shapes=room + far + [bar])


SCENES = {s.name: s for s in (_hidden_sun(), _blinds(), _forest(), _sun_off_screen(), _point_light(),
                              _thin_haze(), _ground_fog(), _street_two_lamps(), _canopy_sun_above(),
                              _window_behind(), _window_ahead(), _window_ahead("window_ahead_room", True))}


# ----------------------------------------------------------------------------- camera


def project(scene: Scene, light: Sun | Lamp | None = None) -> tuple[tuple[float, float], bool, float]:
    """A light's pixel position (x right, y down, centres at i + 0.5; a light behind the camera's projection mirrored
    through the camera plane, as `godrays_jax`'s `project_point`), whether in front, its depth along its ray; `light`
    defaults to the scene's first."""
    light = scene.light if light is None else light
    focal = (WIDTH / 2) / math.tan(math.radians(FOV_X_DEG) / 2)  # pixels per unit of x / -z
    if isinstance(light, Sun):
        x, y, z = light.direction()
        depth = math.inf
    else:
        x, y, z = np.asarray(light.position) - np.asarray(scene.camera)
        depth = float(math.sqrt(x * x + y * y + z * z))
    forward = -z
    scale = focal / max(abs(forward), 1e-6)  # behind the camera: mirrored through its plane, as `project_point`
    return (WIDTH / 2 + scale * x, HEIGHT / 2 - scale * y), bool(forward > 0), depth


def irradiance(light: Sun | Lamp, depth: float) -> np.ndarray:
    """The light's irradiance (RGB) at the camera's distance `depth`, the medium left out: a sun's radiance times its
    disc's solid angle; a lamp's radiant intensity (radiance times pi radius^2) over the squared distance."""
    if isinstance(light, Sun):
        return np.asarray(light.radiance, np.float64) * 2 * math.pi * (1 - math.cos(math.radians(light.radius_deg)))
    return np.asarray(light.radiance, np.float64) * math.pi * light.radius**2 / depth**2


def lights_attributes(scene: Scene) -> dict[str, str] | None:
    """For a scene of several lights, the header's `godrays:lights` (`x,y` or `x,y,behind` each),
    `godrays:lights_depth` and `godrays:lights_tint` (each light's irradiance at the camera over the first's, channel
    by channel: the first's tint 1), `;` between lights, as `godrays_jax`'s `lights_metadata` writes them; `None` for
    a scene of one light."""
    if not scene.more_lights:
        return None
    projected = [project(scene, light) for light in scene.lights]
    first = irradiance(scene.light, projected[0][2])
    if not np.all(first > 0):
        raise ValueError(f"{scene.name}: the first light must shine in every channel to tint the others by it")
    tints = [np.ones(3)] + [irradiance(light, depth) / first
                            for light, (_, _, depth) in zip(scene.more_lights, projected[1:])]
    return {
        "godrays:lights": ";".join(",".join([repr(float(x)), repr(float(y)), *([] if in_front else ["behind"])])
                                   for (x, y), in_front, _ in projected),
        "godrays:lights_depth": ";".join(repr(float(depth)) for _, _, depth in projected),
        "godrays:lights_tint": ";".join(",".join(repr(float(c)) for c in tint) for tint in tints),
    }


# ----------------------------------------------------------------------------- Mitsuba


def _envmap(mi, lights):
    """A latitude-longitude sky (Mitsuba's convention: u = atan2(x, -z) / 2 pi, v = acos(y) / pi): the first light's
    sky, every sun a disc."""
    rows, cols = ENVMAP_SIZE
    pixels = np.empty((rows, cols, 3), np.float32)
    pixels[...] = lights[0].sky
    suns = [light for light in lights if isinstance(light, Sun)]
    if suns:
        theta = (np.arange(rows) + 0.5) / rows * np.pi
        phi = (np.arange(cols) + 0.5) / cols * 2 * np.pi
        theta, phi = np.meshgrid(theta, phi, indexing="ij")
        direction = np.stack([np.sin(theta) * np.sin(phi), np.cos(theta), -np.sin(theta) * np.cos(phi)], -1)
        for sun in suns:
            disc = direction @ sun.direction() >= math.cos(math.radians(sun.radius_deg))
            pixels[disc] = sun.radiance
    return {"type": "envmap", "bitmap": mi.Bitmap(pixels)}


def look_at(origin, target, up) -> np.ndarray:
    """Mitsuba's `look_at` camera-to-world in float64 (its own rounds to float32): columns left, up, forward,
    position."""
    origin = np.asarray(origin, np.float64)
    forward = np.asarray(target, np.float64) - origin
    forward /= np.linalg.norm(forward)
    left = np.cross(np.asarray(up, np.float64), forward)
    left /= np.linalg.norm(left)
    matrix = np.eye(4)
    matrix[:3, 0], matrix[:3, 1], matrix[:3, 2], matrix[:3, 3] = left, np.cross(forward, left), forward, origin
    return matrix


def frame_to_world(scene: Scene) -> np.ndarray:
    """The frame camera's camera-to-world: at `scene.camera`, looking along -z, up +y."""
    camera = np.asarray(scene.camera, np.float64)
    return look_at(camera, camera - [0.0, 0.0, 1.0], [0.0, 1.0, 0.0])


def light_to_world(scene: Scene) -> np.ndarray:
    """The sun's orthographic light camera's camera-to-world: `LIGHT_VIEW_DISTANCE` from the frame camera toward the
    sun, looking along the sunlight at the frame camera, its up the world's +y made perpendicular to that (-z for a
    sun within 8 degrees of straight overhead)."""
    camera = np.asarray(scene.camera, np.float64)
    toward = scene.light.direction()
    up = [0.0, 1.0, 0.0] if abs(toward[1]) < 0.99 else [0.0, 0.0, -1.0]
    return look_at(camera + LIGHT_VIEW_DISTANCE * toward, camera, up)


def view_from_world(to_world: np.ndarray) -> np.ndarray:
    """The 3x4 world-to-view `[R | t]` of a camera-to-world (Mitsuba's: columns left, up, forward, position), in
    `godrays_jax`'s view space: x right, y up, z forward."""
    rotation = to_world[:3, :3].T * np.array([[-1.0], [1.0], [1.0]])  # Mitsuba's camera x is left
    return np.concatenate([rotation, -(rotation @ to_world[:3, 3])[:, None]], 1)


def scene_dict(mi, scene: Scene, *, fog: bool, emitters: bool = True) -> dict:
    """Mitsuba's description of `scene`, with or without its medium (and its lights, for the geometry pass)."""
    T = mi.ScalarTransform4f
    camera = scene.camera
    sensor = {
        "type": "perspective",
        "fov": FOV_X_DEG,
        "fov_axis": "x",
        "to_world": T(frame_to_world(scene)),
        "film": {"type": "hdrfilm", "width": WIDTH, "height": HEIGHT, "rfilter": {"type": "box"},
                 "pixel_format": "rgb", "component_format": "float32"},
        "sampler": {"type": "independent"},
    }
    d = {
        "type": "scene",
        "integrator": {"type": "volpath" if fog else "path", "max_depth": MAX_DEPTH},
        "ground": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale([200, 200, 1]),
                   "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(GROUND_REFLECTANCE)}}},
    }
    for i, (kind, matrix, reflectance) in enumerate(scene.shapes):
        d[f"shape_{i}"] = {"type": kind, "to_world": T(matrix),
                           "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(reflectance)}}}
    if emitters:
        d["sky"] = _envmap(mi, scene.lights)
        lamps = [light for light in scene.lights if isinstance(light, Lamp)]
        for i, lamp in enumerate(lamps):
            d["lamp" if i == 0 else f"lamp_{i + 1}"] = {
                "type": "sphere", "center": list(lamp.position), "radius": lamp.radius,
                "emitter": {"type": "area", "radiance": {"type": "rgb", "value": list(lamp.radiance)}}}
    if fog:
        m = scene.medium
        # declared once, referred to by the shape that bounds it and by the camera inside it
        d["fog"] = {"type": "homogeneous", "id": "fog", "sigma_t": m.sigma_t, "albedo": m.albedo,
                    "phase": {"type": "hg", "g": m.g}}
        if isinstance(m.extent, tuple) and m.extent[0] == "box":
            x0, x1, y0, y1, z0, z1 = m.extent[1]
            bounds = {"type": "cube", "to_world": T().translate([(x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2]).scale(
                [(x1 - x0) / 2, (y1 - y0) / 2, (z1 - z0) / 2])}
        elif isinstance(m.extent, tuple):
            top, bottom = m.extent[1], -1.0  # below the ground, so the ground never coincides with a face
            bounds = {"type": "cube", "to_world": T().translate([0, (top + bottom) / 2, 0]).scale(
                [100, (top - bottom) / 2, 100])}
        else:
            bounds = {"type": "sphere", "center": list(camera), "radius": m.extent}
        d["medium_bounds"] = bounds | {"bsdf": {"type": "null"}, "interior": {"type": "ref", "id": "fog"}}
        sensor["medium"] = {"type": "ref", "id": "fog"}
    d["sensor"] = sensor
    return d


def render_color(mi, scene: Scene, *, fog: bool, spp: int, seed: int) -> np.ndarray:
    """Mean of `spp` samples per pixel, launched `PASS_SPP` at a time with seeds derived from `seed`."""
    loaded = mi.load_dict(scene_dict(mi, scene, fog=fog))
    total = np.zeros((HEIGHT, WIDTH, 3), np.float64)
    launches = max(1, math.ceil(spp / PASS_SPP))
    for launch in range(launches):
        image = mi.render(loaded, spp=spp // launches, seed=seed * 100_003 + launch)
        total += np.asarray(image, np.float64)[..., :3]
    return (total / launches).astype(np.float32)


def render_geometry(mi, scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """Depth along the pixel centre's ray (`+inf` on a miss) and the fraction of a grid of rays that hit."""
    import drjit as dr

    lamps = any(isinstance(light, Lamp) for light in scene.lights)  # the bulbs are geometry too
    loaded = mi.load_dict(scene_dict(mi, scene, fog=False, emitters=lamps))
    sensor = loaded.sensors()[0]

    def cast(offset_x, offset_y):
        j, i = np.mgrid[0:HEIGHT, 0:WIDTH]
        u = ((i + offset_x) / WIDTH).ravel().astype(np.float32)
        v = ((j + offset_y) / HEIGHT).ravel().astype(np.float32)
        ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(u, v), mi.Point2f(0.5, 0.5))
        si = loaded.ray_intersect(ray)
        t = np.asarray(dr.select(si.is_valid(), si.t, dr.inf))
        return t.reshape(HEIGHT, WIDTH)

    depth = cast(0.5, 0.5)
    grid = (np.arange(COVERAGE_GRID) + 0.5) / COVERAGE_GRID
    hits = sum(np.isfinite(cast(ox, oy)) for ox in grid for oy in grid)
    return depth.astype(np.float32), (hits / COVERAGE_GRID**2).astype(np.float32)


def render_light_view(mi, scene: Scene) -> tuple[np.ndarray, np.ndarray, float]:
    """The sun's shadow map: planar depth from the orthographic light camera's image plane along its forward axis at
    every pixel centre (`+inf` on a miss, no medium), the 3x4 frame-view-to-light-view `[R | t]` and the scale
    (pixels per scene unit)."""
    import drjit as dr

    if not isinstance(scene.light, Sun):
        raise ValueError(f"{scene.name}: a light view needs a sun as the first light")
    lamps = any(isinstance(light, Lamp) for light in scene.lights)  # the bulbs are geometry too
    loaded = mi.load_dict(scene_dict(mi, scene, fog=False, emitters=lamps))
    frame = view_from_world(frame_to_world(scene))
    light_world = light_to_world(scene)
    light = view_from_world(light_world)
    rotation = light[:, :3] @ frame[:, :3].T  # X_light = R_l (R_f^T (X - t_f)) + t_l
    light_from_camera = np.concatenate([rotation, (light[:, 3] - rotation @ frame[:, 3])[:, None]], 1)

    n, scale = LIGHT_VIEW_PIXELS, LIGHT_VIEW_PIXELS / LIGHT_VIEW_SPAN
    offsets = (np.arange(n) + 0.5 - n / 2) / scale  # pixel centres in light-view units
    lx, ly = np.meshgrid(offsets, -offsets)  # rows top (up) to bottom
    right, up, forward = light[:, :3]
    position = light_world[:3, 3]
    origins = position + lx.reshape(-1, 1) * right + ly.reshape(-1, 1) * up  # on the image plane (lz = 0)
    origins = origins.astype(np.float32)
    ray = mi.Ray3f(mi.Point3f(origins[:, 0], origins[:, 1], origins[:, 2]),
                   mi.Vector3f(*(float(c) for c in forward)))
    si = loaded.ray_intersect(ray)
    depth = np.asarray(dr.select(si.is_valid(), si.t, dr.inf)).reshape(n, n)
    return depth.astype(np.float32), light_from_camera, scale


# ----------------------------------------------------------------------------- files


def display_mse(a: np.ndarray, b: np.ndarray) -> float:
    """Mean squared difference over pixels and RGB of `x / (1 + |x|)`: `godrays-jax fit`'s loss."""
    a, b = (np.asarray(x, np.float64)[..., :3] for x in (a, b))
    return float(np.mean((a / (1 + np.abs(a)) - b / (1 + np.abs(b))) ** 2))


def write_frame(path: Path, color: np.ndarray, scene: Scene, depth=None, coverage=None) -> None:
    """Half-float colour (and coverage), float32 depth, zip; the light and field of view in the header."""
    import OpenImageIO as oiio

    planes, names, formats = [color], ["R", "G", "B"], [oiio.TypeHalf] * 3
    if depth is not None:
        planes += [coverage[..., None], depth[..., None]]
        names += ["A", "Z"]
        formats += [oiio.TypeHalf, oiio.TypeFloat]
    pixels = np.ascontiguousarray(np.concatenate(planes, -1), dtype=np.float32)
    spec = oiio.ImageSpec(WIDTH, HEIGHT, len(names), oiio.HALF)
    spec.channelnames = tuple(names)
    if depth is not None:
        spec.channelformats = tuple(formats)
    if depth is not None:
        spec.alpha_channel, spec.z_channel = 3, 4
    spec.attribute("compression", "zip")
    light_px, in_front, light_depth = project(scene)
    spec.attribute("godrays:light_px", oiio.TypeFloat2, light_px)
    spec.attribute("godrays:light_in_front", oiio.TypeInt, int(in_front))
    spec.attribute("godrays:light_depth", oiio.TypeFloat, light_depth)
    spec.attribute("godrays:fov_x_deg", oiio.TypeFloat, FOV_X_DEG)
    for name, value in (lights_attributes(scene) or {}).items():
        spec.attribute(name, value)
    out = oiio.ImageOutput.create(str(path))
    if out is None or not out.open(str(path), spec) or not out.write_image(pixels) or not out.close():
        raise OSError(f"cannot write {path}: {oiio.geterror()}")


def write_light_view(path: Path, depth: np.ndarray, light_from_camera: np.ndarray, scale: float) -> None:
    """One float32 channel `Z`, zip; the projection, the frame-view-to-light-view matrix and the scale in the
    header."""
    import OpenImageIO as oiio

    height, width = depth.shape
    spec = oiio.ImageSpec(width, height, 1, oiio.FLOAT)
    spec.channelnames = ("Z",)
    spec.z_channel = 0
    spec.attribute("compression", "zip")
    spec.attribute("godrays:light_view_projection", "orthographic")
    spec.attribute("godrays:light_view_from_camera", " ".join(repr(float(x)) for x in light_from_camera.ravel()))
    spec.attribute("godrays:light_view_scale", repr(float(scale)))
    out = oiio.ImageOutput.create(str(path))
    pixels = np.ascontiguousarray(depth[..., None], dtype=np.float32)
    if out is None or not out.open(str(path), spec) or not out.write_image(pixels) or not out.close():
        raise OSError(f"cannot write {path}: {oiio.geterror()}")


def describe_light(light: Sun | Lamp, sky: bool = True) -> str:
    if isinstance(light, Sun):
        text = (f"sun: disc of radius {light.radius_deg:g} deg, radiance {list(light.radiance)}, "
                f"azimuth {light.azimuth_deg:g} deg, elevation {light.elevation_deg:g} deg")
    else:
        text = f"lamp: sphere of radius {light.radius:g} at {list(light.position)}, radiance {list(light.radiance)}"
    return f"{text}; sky {list(light.sky)}" if sky else text


def record(scene: Scene, spp: int, seconds: dict, floor: float, variant: str) -> dict:
    light_px, in_front, light_depth = project(scene)
    m = scene.medium
    several = lights_attributes(scene)
    if several:
        light = "; ".join(f"{i + 1}. {describe_light(light, sky=False)}" for i, light in enumerate(scene.lights))
        light += f"; sky {list(scene.light.sky)}"
        lights = {"lights": several["godrays:lights"], "lights_depth": several["godrays:lights_depth"],
                  "lights_tint": several["godrays:lights_tint"]}
    else:
        light, lights = describe_light(scene.light), {}
    return {
        "shows": scene.shows,
        "clean": f"{scene.name}_clean.exr",
        "fog": [f"{scene.name}_fog_a.exr", f"{scene.name}_fog_b.exr"],
        "light_px": list(light_px),
        "light_in_front": in_front,
        "light_depth": None if math.isinf(light_depth) else light_depth,
        "fov_x_deg": FOV_X_DEG,
        **lights,
        "light": light,
        "medium": {"sigma_t": m.sigma_t, "albedo": m.albedo, "g": m.g, "extent": m.describe()},
        "camera": list(scene.camera),
        "spp": {"fog": spp, "clean": spp * CLEAN_SPP_FACTOR},
        "seconds": seconds,
        "variant": variant,
        "noise_floor": floor,
    }


def main() -> None:
    global WIDTH, HEIGHT
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("scenes", nargs="*", help=f"default: all of {', '.join(SCENES)}")
    parser.add_argument("--spp", type=int, default=256, help="fog samples per pixel (clean: 4x)")
    parser.add_argument("--variant", default="llvm_ad_rgb")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, default=HERE)
    parser.add_argument("--size", default=f"{WIDTH}x{HEIGHT}", help="the frames' width x height in pixels")
    parser.add_argument("--geometry-only", action="store_true",
                        help="rewrite the clean frames' coverage and depth, keeping their stored colour")
    parser.add_argument("--light-view", action="store_true",
                        help="write a sun scene's shadow map (NAME_light_view.exr) and nothing else, skipping "
                             "scenes without a sun (with --geometry-only: both)")
    args = parser.parse_args()

    try:
        WIDTH, HEIGHT = (int(side) for side in args.size.lower().split("x"))
    except ValueError:
        parser.error(f"--size must be WIDTHxHEIGHT in pixels, got {args.size!r}")
    unknown = [name for name in args.scenes if name not in SCENES]
    if unknown:
        parser.error(f"unknown scene {', '.join(unknown)}; scenes: {', '.join(SCENES)}")
    import drjit as dr
    import mitsuba as mi

    mi.set_variant(args.variant)
    dr.set_thread_count(args.threads)
    index_path = args.out / "scenes.json"
    for name in args.scenes or list(SCENES):
        scene = SCENES[name]
        seconds = {}
        if args.light_view:
            if isinstance(scene.light, Sun):
                start, cpu = time.perf_counter(), time.process_time()
                light_depth, light_from_camera, scale = render_light_view(mi, scene)
                write_light_view(args.out / f"{name}_light_view.exr", light_depth, light_from_camera, scale)
                print(f"{name}: light view written ({time.perf_counter() - start:.1f} s, "
                      f"{time.process_time() - cpu:.1f} s CPU)", flush=True)
            else:
                print(f"{name}: no sun, no light view", flush=True)
            if not args.geometry_only:
                continue
        start, cpu = time.perf_counter(), time.process_time()
        depth, coverage = render_geometry(mi, scene)
        if args.geometry_only:
            import OpenImageIO as oiio

            path = args.out / f"{name}_clean.exr"
            write_frame(path, oiio.ImageBuf(str(path)).get_pixels(oiio.FLOAT)[..., :3], scene, depth, coverage)
            print(f"{name}: coverage and depth rewritten", flush=True)
            continue
        clean = render_color(mi, scene, fog=False, spp=args.spp * CLEAN_SPP_FACTOR, seed=SEEDS["clean"])
        seconds["clean"] = [round(time.perf_counter() - start, 1), round(time.process_time() - cpu, 1)]
        write_frame(args.out / f"{name}_clean.exr", clean, scene, depth, coverage)
        fogs = []
        for key in ("fog_a", "fog_b"):
            start, cpu = time.perf_counter(), time.process_time()
            fogs.append(render_color(mi, scene, fog=True, spp=args.spp, seed=SEEDS[key]))
            seconds[key] = [round(time.perf_counter() - start, 1), round(time.process_time() - cpu, 1)]
            write_frame(args.out / f"{name}_{key}.exr", fogs[-1], scene)
        # the floor of the frames as stored (half floats), read back as `fit` reads them
        import OpenImageIO as oiio

        stored = [oiio.ImageBuf(str(args.out / f"{name}_{key}.exr")).get_pixels(oiio.FLOAT)[..., :3]
                  for key in ("fog_a", "fog_b")]
        floor = 0.5 * display_mse(*stored)
        index = json.loads(index_path.read_text()) if index_path.exists() else {}  # read late: runs side by side
        index[name] = record(scene, args.spp, seconds, floor, args.variant)
        index_path.write_text(json.dumps(dict(sorted(index.items())), indent=1) + "\n")
        print(f"{name}: {seconds} s, noise floor {floor:.3e} (float32 {0.5 * display_mse(*fogs):.3e})", flush=True)


if __name__ == "__main__":
    main()
