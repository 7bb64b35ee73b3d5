"""How much of the light reaches points of the frame's view space, read from a depth map seen from the light.

A shadow map's test, as engines make it: a point is lit when it lies no
deeper along the light camera's axis than the first surface its pixel of the
map sees (`primitives.light_view.LightView`). Each point is compared with the
four texels around its position on the map and the four results blended by
bilinear weights (percentage-closer filtering), so that a shadow's edge moves
smoothly as the point moves over the map's grid; each comparison is a linear
ramp `RAMP_TEXELS` texels' footprints deep behind the texel's surface, so that
the points' positions (the medium's fields that place a view ray's segments)
have gradients. The volumetric fog takes a segment's shadow from the map at
its points that fall on it (`on_light_view`) and from its screen-space reading
(`shadow_reading`) at the others: the map holds every surface the light sees,
those the frame shows among them, and both readings of one window's edge,
multiplied, would shade its beam twice (benchmarks/README.md, "A sunbeam through
a window in view"). `covers_view` says, on the host, whether a map covers every
point a frame's fog reads within a reach, where the screen's reading has nothing left to shade.
"""

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from godrays_jax.primitives.light_view import LightView
from godrays_jax.primitives.sampling import bilinear_corners

RAMP_TEXELS = 2.0
"""How deep behind a texel's surface a point falls from lit to shadowed, in texels' footprints: a surface that
slants across a texel spans about one footprint in depth when it faces the light at 45 degrees (more when it
faces away), and the four texels around a point blend such spans."""


def light_view_visibility(points: Float[Array, "*S 3"], *, light_view: LightView) -> Float[Array, "*S"]:
    """How much of the light reaches each of `points` (the frame camera's view space, scene units), in [0, 1].

    1 where the point lies off the map (beyond `[0, w] x [0, h]`), behind a
    perspective map's centre, or where its texels see nothing (`+inf`);
    nothing is known there and nothing blocks. Differentiable in the points
    and the map's camera (`from_camera`, `scale`); not in the map's depths'
    positions (the texels are sampled where they are).
    """
    if not isinstance(light_view, LightView):
        raise ValueError(f"light_view must be a LightView, got {type(light_view).__name__}")
    if jnp.shape(points)[-1:] != (3,):
        raise ValueError(f"points must have shape (..., 3), got {jnp.shape(points)}")
    dtype = jnp.result_type(points, jnp.float32)
    height, width = light_view.depth.shape[-2:]
    x, y, z, footprint = light_view.project(jnp.asarray(points, dtype))
    rows, cols, weights = bilinear_corners(x - 0.5, y - 0.5, height, width)
    texels = jnp.asarray(light_view.depth, dtype)[rows, cols]
    ramp = RAMP_TEXELS * footprint
    seen = jnp.isfinite(texels)
    # Lit up to the texel's surface, shadowed a ramp behind it; where the texel sees nothing the difference is
    # replaced by a ramp, so that no infinity reaches a derivative.
    behind = jnp.where(seen, z - texels, -ramp)
    lit = jnp.sum(weights * jnp.clip(1.0 - behind / ramp, 0.0, 1.0), axis=0)
    return jnp.where(_on_map(x, y, z, height, width, light_view.projection), lit, 1.0)


def on_light_view(points: Float[Array, "*S 3"], *, light_view: LightView) -> Bool[Array, "*S"]:
    """Whether each of `points` (the frame camera's view space, scene units) falls on the map, where its test
    decides: within `[0, w] x [0, h]` and, for a perspective map, in front of its centre (its texels that see
    nothing included: they say that nothing blocks). No gradient."""
    if not isinstance(light_view, LightView):
        raise ValueError(f"light_view must be a LightView, got {type(light_view).__name__}")
    if jnp.shape(points)[-1:] != (3,):
        raise ValueError(f"points must have shape (..., 3), got {jnp.shape(points)}")
    height, width = light_view.depth.shape[-2:]
    x, y, z, _ = light_view.project(jnp.asarray(points, jnp.result_type(points, jnp.float32)))
    return _on_map(x, y, z, height, width, light_view.projection)


def covers_view(
    light_view: LightView, *, height: int, width: int, focal: float, reach: float, margin: float
) -> bool:
    """Whether every point of the frame camera's view within `reach` scene units of it, through the frame
    `[-margin, width + margin] x [-margin, height + margin]` (pixels, focal length `focal` pixels), falls on the
    map (`on_light_view`). Where it does (and on points within `reach`) the map alone shades the fog, and no
    reading of the screen is needed.

    The points on a map form a convex region (a prism along an orthographic map's axis, a pyramid from a
    perspective map's centre) and those points lie in the pyramid from the camera to the frame's corners at
    depth `reach`: the map covers them when it covers that pyramid's five corners. Evaluated on the host, for a
    static choice: a map with leading batch axes is taken as not covering.
    """
    if np.ndim(light_view.depth) != 2:
        return False
    corners = [[0.0, 0.0, 0.0]] + [
        [reach * (x - 0.5 * width) / focal, -reach * (y - 0.5 * height) / focal, reach]
        for x in (-margin, width + margin)
        for y in (-margin, height + margin)
    ]  # fmt: skip
    return bool(np.all(np.asarray(on_light_view(np.asarray(corners, np.float32), light_view=light_view))))


def _on_map(x, y, z, height, width, projection):
    on_map = (x >= 0.0) & (x <= width) & (y >= 0.0) & (y <= height)
    return on_map & (z > 0.0) if projection == "perspective" else on_map
