"""godrays_jax: differentiable screen-space light scattering in JAX.

Kernels are pure functions (image first, options keyword-only); effects are
`equinox.Module` parameter sets with presets; `fit`, `render`, `run_batch` and
the I/O functions build on them. This is the library: the command line and
the tuner's server live in `godrays_jax.app` and are not imported here.
"""

import importlib as _importlib
import types as _types
from importlib import metadata as _metadata


# Image primitives: sampling, resampling, colour, buffers, camera (files load on first use, below).
from godrays_jax.primitives.buffers import Buffers as Buffers
from godrays_jax.primitives.camera import Camera as Camera
from godrays_jax.primitives.camera import planar_to_ray_depth as planar_to_ray_depth
from godrays_jax.primitives.camera import project_point as project_point
from godrays_jax.primitives.color import display_map as display_map
from godrays_jax.primitives.color import srgb_decode as srgb_decode
from godrays_jax.primitives.color import srgb_encode as srgb_encode
from godrays_jax.primitives.derivatives import values_only as values_only
from godrays_jax.primitives.light_view import LightView as LightView
from godrays_jax.primitives.resample import box_pool as box_pool
from godrays_jax.primitives.resample import downsample_box as downsample_box
from godrays_jax.primitives.resample import upsample_bilinear as upsample_bilinear
from godrays_jax.primitives.sampling import sample_bilinear as sample_bilinear

# Kernels: pure functions, image first, options keyword-only.
from godrays_jax.kernels.blur import POISSON_OFFSETS as POISSON_OFFSETS
from godrays_jax.kernels.blur import bloom as bloom
from godrays_jax.kernels.blur import gaussian_blur as gaussian_blur
from godrays_jax.kernels.blur import poisson_blur as poisson_blur
from godrays_jax.kernels.bounded_medium import BoundedMedium as BoundedMedium
from godrays_jax.kernels.bounded_medium import light_transmittance as light_transmittance
from godrays_jax.kernels.bounded_medium import optical_depth as optical_depth
from godrays_jax.kernels.composite import BLEND_MODES as BLEND_MODES
from godrays_jax.kernels.composite import add as add
from godrays_jax.kernels.composite import alpha_over as alpha_over
from godrays_jax.kernels.composite import blend as blend
from godrays_jax.kernels.composite import multiply as multiply
from godrays_jax.kernels.composite import screen as screen
from godrays_jax.kernels.fast import at_reduced_resolution as at_reduced_resolution
from godrays_jax.kernels.fast import fast_radial_rays as fast_radial_rays
from godrays_jax.kernels.fast import radial_rays_jittered as radial_rays_jittered
from godrays_jax.kernels.fast import radial_rays_multipass as radial_rays_multipass
from godrays_jax.kernels.lens import dirt_texture as dirt_texture
from godrays_jax.kernels.lens import lens_dirt as lens_dirt
from godrays_jax.kernels.lens import lens_dirt_intensity as lens_dirt_intensity
from godrays_jax.kernels.lens import light_direction as light_direction
from godrays_jax.kernels.lens import sun_spot as sun_spot
from godrays_jax.kernels.lens import view_directions as view_directions
from godrays_jax.kernels.light_view_shadows import light_view_visibility as light_view_visibility
from godrays_jax.kernels.losses import LOSSES as LOSSES
from godrays_jax.kernels.losses import charbonnier_loss as charbonnier_loss
from godrays_jax.kernels.losses import l1_loss as l1_loss
from godrays_jax.kernels.losses import mse_loss as mse_loss
from godrays_jax.kernels.losses import ssim as ssim
from godrays_jax.kernels.losses import ssim_loss as ssim_loss
from godrays_jax.kernels.masks import bright_pass as bright_pass
from godrays_jax.kernels.masks import bright_sky as bright_sky
from godrays_jax.kernels.masks import clip_space_depth as clip_space_depth
from godrays_jax.kernels.masks import coverage_mask as coverage_mask
from godrays_jax.kernels.masks import depth_test_mask as depth_test_mask
from godrays_jax.kernels.masks import dilate as dilate
from godrays_jax.kernels.masks import erode as erode
from godrays_jax.kernels.masks import flare_image as flare_image
from godrays_jax.kernels.masks import flare_mask as flare_mask
from godrays_jax.kernels.masks import hardware_depth as hardware_depth
from godrays_jax.kernels.masks import light_source_mask as light_source_mask
from godrays_jax.kernels.masks import procedural_flare as procedural_flare
from godrays_jax.kernels.masks import sky_mask as sky_mask
from godrays_jax.kernels.media import apply_fog as apply_fog
from godrays_jax.kernels.media import henyey_greenstein as henyey_greenstein
from godrays_jax.kernels.media import in_scattering as in_scattering
from godrays_jax.kernels.media import transmittance as transmittance
from godrays_jax.kernels.rays import radial_rays as radial_rays
from godrays_jax.kernels.rays import scale_iterated_flares as scale_iterated_flares
from godrays_jax.kernels.rays import scaled_copies as scaled_copies
from godrays_jax.kernels.shadow_lines import segment_visibility_by_lines as segment_visibility_by_lines
from godrays_jax.kernels.shadow_reading import ShadowLines as ShadowLines
from godrays_jax.kernels.shadow_reading import ShadowSamples as ShadowSamples
from godrays_jax.kernels.shadow_reading import Slabs as Slabs
from godrays_jax.kernels.volumetric import apply_volumetric_fog as apply_volumetric_fog
from godrays_jax.kernels.shadow_samples import segment_visibility as segment_visibility
from godrays_jax.kernels.volumetric import composite_fog as composite_fog
from godrays_jax.kernels.volumetric import fog_light as fog_light
from godrays_jax.kernels.volumetric import scattered_again as scattered_again
from godrays_jax.kernels.volumetric import scattered_aside as scattered_aside
from godrays_jax.kernels.volumetric import volumetric_fog_terms as volumetric_fog_terms

# Effects: parameter sets (equinox Modules), presets, serialisation.
from godrays_jax.effects.base import Effect as Effect
from godrays_jax.effects.base import light_visibility as light_visibility
from godrays_jax.effects.base import needs_depth as needs_depth
from godrays_jax.effects.fields import FieldInfo as FieldInfo
from godrays_jax.effects.fields import field_metadata as field_metadata
from godrays_jax.effects.fields import field_value as field_value
from godrays_jax.effects.fields import parameter_bounds as parameter_bounds
from godrays_jax.effects.fields import replace_fields as replace_fields
from godrays_jax.effects.fields import size_fields as size_fields
from godrays_jax.effects.fog import ScatteringFog as ScatteringFog
from godrays_jax.effects.lights import Light as Light
from godrays_jax.effects.lights import lit_by as lit_by
from godrays_jax.effects.medium import Medium as Medium
from godrays_jax.effects.volumetric import VolumetricFog as VolumetricFog
from godrays_jax.effects.glow import Bloom as Bloom
from godrays_jax.effects.glow import BloomBlur as BloomBlur
from godrays_jax.effects.glow import LensDirt as LensDirt
from godrays_jax.effects.glow import SunOvercast as SunOvercast
from godrays_jax.effects.glow import SunSpot as SunSpot
from godrays_jax.effects.presets import PRESETS as PRESETS
from godrays_jax.effects.plates import buffers_without_depth as buffers_without_depth
from godrays_jax.effects.presets import preset as preset
from godrays_jax.effects.presets import presets_without_depth as presets_without_depth
from godrays_jax.effects.serialization import effect_from_dict as effect_from_dict
from godrays_jax.effects.serialization import effect_to_dict as effect_to_dict
from godrays_jax.effects.serialization import load_effect as load_effect
from godrays_jax.effects.serialization import MAX_EFFECT_FILE_BYTES as MAX_EFFECT_FILE_BYTES
from godrays_jax.effects.serialization import save_effect as save_effect
from godrays_jax.effects.shafts import FlareOuts as FlareOuts
from godrays_jax.effects.shafts import GodRays as GodRays
from godrays_jax.effects.shafts import step_clamp as step_clamp
from godrays_jax.effects.shafts import XNA_FAR_PLANE as XNA_FAR_PLANE
from godrays_jax.effects.shafts import XNA_NEAR_PLANE as XNA_NEAR_PLANE

# Load on first use: files (OpenImageIO), batches (tqdm), fitting (optimistix) and the rasterizer, so that
# importing the kernels or effects loads none of them, and `godrays-jax apply` neither the solver nor the rasterizer.
_ON_FIRST_USE = {
    "read_frame": "godrays_jax.primitives.frame_files",
    "write_buffers": "godrays_jax.primitives.frame_files",
    "write_frame_like": "godrays_jax.primitives.frame_files",
    "check_buffers": "godrays_jax.primitives.frame_reading",
    "read_buffers": "godrays_jax.primitives.frame_reading",
    "encode_png": "godrays_jax.primitives.images",
    "read_image": "godrays_jax.primitives.images",
    "write_image": "godrays_jax.primitives.images",
    "read_light": "godrays_jax.primitives.light_metadata",
    "read_light_depth": "godrays_jax.primitives.light_metadata",
    "read_lights": "godrays_jax.primitives.light_metadata",
    "lights_metadata": "godrays_jax.primitives.light_metadata",
    "read_light_view": "godrays_jax.primitives.light_view_files",
    "write_light_view": "godrays_jax.primitives.light_view_files",
    "StoredLight": "godrays_jax.primitives.light_metadata",
    "plan_batch": "godrays_jax.pipeline.batch",
    "run_batch": "godrays_jax.pipeline.batch",
    "expand_frames": "godrays_jax.pipeline.sequences",
    "read_light_track": "godrays_jax.pipeline.sequences",
    "maps_by_frame": "godrays_jax.pipeline.sequences",
    "determination": "godrays_jax.pipeline.determination",
    "Determination": "godrays_jax.pipeline.determination",
    "fit": "godrays_jax.pipeline.fit",
    "FitResult": "godrays_jax.pipeline.fit",
    "fit_report_image": "godrays_jax.pipeline.report",
    "find_light": "godrays_jax.pipeline.light_search",
    "halo_starts": "godrays_jax.pipeline.light_search",
    "LightSearch": "godrays_jax.pipeline.light_search",
    "seen_lights": "godrays_jax.pipeline.light_seen",
    "SeenLight": "godrays_jax.pipeline.light_seen",
    "profile_light": "godrays_jax.pipeline.light_profile",
    "LightProfile": "godrays_jax.pipeline.light_profile",
    "DirectionalLight": "godrays_jax.raster",
    "light_distance": "godrays_jax.raster",
    "light_pixel": "godrays_jax.raster",
    "light_view": "godrays_jax.raster",
    "load_obj": "godrays_jax.raster",
    "load_scene": "godrays_jax.raster",
    "Material": "godrays_jax.raster",
    "Mesh": "godrays_jax.raster",
    "plan_tile_capacity": "godrays_jax.raster",
    "PointLight": "godrays_jax.raster",
    "render": "godrays_jax.raster",
    "Scene": "godrays_jax.raster",
    "scene_from_dict": "godrays_jax.raster",
    "Sky": "godrays_jax.raster",
    "Sphere": "godrays_jax.raster",
    "uv_sphere": "godrays_jax.raster",
}


__all__ = sorted([
    *(name for name, value in globals().items() if not name.startswith("_") and not isinstance(value, _types.ModuleType)),
    *_ON_FIRST_USE,
])  # fmt: skip
"""Every public name: those imported above and those loaded on first use (subpackages are not names of the API)."""


def __getattr__(name: str):
    if name not in _ON_FIRST_USE:
        raise AttributeError(f"module 'godrays_jax' has no attribute {name!r}")
    value = getattr(_importlib.import_module(_ON_FIRST_USE[name]), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_ON_FIRST_USE})


__version__ = _metadata.version("godrays_jax")
