"""`Medium`: the participating medium's own fields, one part that `ScatteringFog` and `VolumetricFog` hold."""

from jaxtyping import Array, Float

from godrays_jax.effects.fields import Part, field_metadata, param


class Medium(Part):
    """A homogeneous medium as single scattering sees it (the `medium` part of `ScatteringFog` and `VolumetricFog`).

    `extinction` is the fraction of light the medium removes per scene unit
    (`T(t) = exp(-extinction * t)`); `max_distance` (scene units) is its extent
    along a view ray (the sky sees all of it); `anisotropy` is the
    Henyey-Greenstein `g` of its phase function, in (-1, 1) (positive: forward
    scattering); `light_color` is the RGB albedo times the light's irradiance
    and `ambient_color` the RGB albedo times the sky's radiance. The effects
    name these fields `medium.extinction`, ... (params files, `fit(fixed=...)`).
    """

    extinction: Float[Array, ""] = param(0.01, low=0.0, high=1.0)
    # A room's medium ends within tens of units, an open sky's thousands: the fit also races it by ratios
    # (docs/findings.md, "A medium's reach raced by ratios").
    max_distance: Float[Array, ""] = param(100.0, low=0.0, high=1e4, decades=4.0)
    anisotropy: Float[Array, ""] = param(0.76, low=-0.95, high=0.95)
    light_color: Float[Array, "3"] = param((1.0, 0.9, 0.75), low=0.0, high=100.0)
    ambient_color: Float[Array, "3"] = param((0.05, 0.06, 0.08), low=0.0, high=10.0)


FLAT_NAMES: dict[str, str] = {name: name for name in field_metadata(Medium)}
"""`{old name on the effect: the medium's field}`: the effects held these fields flat before the medium was a part."""
