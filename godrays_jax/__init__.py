"""godrays_jax: differentiable screen-space light scattering in JAX."""

from godrays_jax.buffers import Buffers as Buffers

__version__ = "0.1.0"
from godrays_jax.io import check_buffers as check_buffers
from godrays_jax.io import read_buffers as read_buffers
from godrays_jax.io import read_image as read_image
from godrays_jax.io import read_light as read_light
from godrays_jax.io import write_buffers as write_buffers
from godrays_jax.io import write_image as write_image
