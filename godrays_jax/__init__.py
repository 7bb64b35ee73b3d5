"""godrays_jax: differentiable screen-space light scattering in JAX."""

from godrays_jax.blur import POISSON_OFFSETS as POISSON_OFFSETS
from godrays_jax.blur import gaussian_blur as gaussian_blur
from godrays_jax.blur import poisson_blur as poisson_blur
from godrays_jax.buffers import Buffers as Buffers
from godrays_jax.composite import BLEND_MODES as BLEND_MODES
from godrays_jax.composite import add as add
from godrays_jax.composite import alpha_over as alpha_over
from godrays_jax.composite import blend as blend
from godrays_jax.composite import multiply as multiply
from godrays_jax.composite import screen as screen
from godrays_jax.effects import PRESETS as PRESETS
from godrays_jax.effects import Effect as Effect
from godrays_jax.effects import FlareOuts as FlareOuts
from godrays_jax.effects import GodRays as GodRays
from godrays_jax.effects import SunOvercast as SunOvercast
from godrays_jax.effects import effect_from_dict as effect_from_dict
from godrays_jax.effects import effect_to_dict as effect_to_dict
from godrays_jax.effects import load_effect as load_effect
from godrays_jax.effects import preset as preset
from godrays_jax.effects import save_effect as save_effect
from godrays_jax.masks import bright_pass as bright_pass
from godrays_jax.masks import coverage_mask as coverage_mask
from godrays_jax.masks import depth_test_mask as depth_test_mask
from godrays_jax.masks import flare_mask as flare_mask
from godrays_jax.masks import light_source_mask as light_source_mask
from godrays_jax.masks import sky_mask as sky_mask
from godrays_jax.rays import radial_rays as radial_rays
from godrays_jax.rays import scale_iterated_flares as scale_iterated_flares
from godrays_jax.sampling import sample_bilinear as sample_bilinear

__version__ = "0.1.0"

from godrays_jax.io import check_buffers as check_buffers
from godrays_jax.io import read_buffers as read_buffers
from godrays_jax.io import read_image as read_image
from godrays_jax.io import read_light as read_light
from godrays_jax.io import write_buffers as write_buffers
from godrays_jax.io import write_image as write_image

from godrays_jax.blur import bloom as bloom
from godrays_jax.blur import downsample_box as downsample_box
from godrays_jax.effects import Bloom as Bloom
from godrays_jax.effects import LensDirt as LensDirt
from godrays_jax.effects import SunSpot as SunSpot
from godrays_jax.effects import light_visibility as light_visibility
from godrays_jax.effects import parameter_bounds as parameter_bounds
from godrays_jax.lens import dirt_texture as dirt_texture
from godrays_jax.lens import lens_dirt as lens_dirt
from godrays_jax.lens import lens_dirt_intensity as lens_dirt_intensity
from godrays_jax.lens import light_direction as light_direction
from godrays_jax.lens import sun_spot as sun_spot
from godrays_jax.lens import view_directions as view_directions
from godrays_jax.masks import dilate as dilate
from godrays_jax.masks import erode as erode
from godrays_jax.fit import FitResult as FitResult
from godrays_jax.fit import fit as fit
from godrays_jax.fit import fit_report_image as fit_report_image
from godrays_jax.losses import LOSSES as LOSSES
from godrays_jax.losses import charbonnier_loss as charbonnier_loss
from godrays_jax.losses import l1_loss as l1_loss
from godrays_jax.losses import mse_loss as mse_loss
from godrays_jax.losses import ssim as ssim
from godrays_jax.losses import ssim_loss as ssim_loss
from godrays_jax.tune import Tuner as Tuner
from godrays_jax.tune import TuneServer as TuneServer

from godrays_jax.camera import Camera as Camera, project_point as project_point
from godrays_jax.raster import (
    DirectionalLight as DirectionalLight,
    Material as Material,
    Mesh as Mesh,
    PointLight as PointLight,
    Scene as Scene,
    Sky as Sky,
    Sphere as Sphere,
    light_pixel as light_pixel,
    load_obj as load_obj,
    load_scene as load_scene,
    plan_tile_capacity as plan_tile_capacity,
    render as render,
    scene_from_dict as scene_from_dict,
    uv_sphere as uv_sphere,
)
from godrays_jax.effects import ScatteringFog as ScatteringFog
from godrays_jax.media import apply_fog as apply_fog
from godrays_jax.media import henyey_greenstein as henyey_greenstein
from godrays_jax.media import in_scattering as in_scattering
from godrays_jax.media import transmittance as transmittance
from godrays_jax.batch import expand_frames as expand_frames
from godrays_jax.batch import plan_batch as plan_batch
from godrays_jax.batch import read_light_track as read_light_track
from godrays_jax.batch import run_batch as run_batch
from godrays_jax.io import read_frame as read_frame
from godrays_jax.io import write_frame_like as write_frame_like

from godrays_jax.fast import at_reduced_resolution as at_reduced_resolution
from godrays_jax.fast import fast_radial_rays as fast_radial_rays
from godrays_jax.fast import interleaved_gradient_noise as interleaved_gradient_noise
from godrays_jax.fast import radial_rays_jittered as radial_rays_jittered
from godrays_jax.fast import radial_rays_multipass as radial_rays_multipass
from godrays_jax.fast import upsample_bilinear as upsample_bilinear
from godrays_jax.rays import scaled_copies as scaled_copies
