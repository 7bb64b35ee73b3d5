"""Every matrix product and convolution the library stages out asks for full float32 precision.

GPUs multiply float32 matrices in TF32 (10-bit mantissas) unless told otherwise: on an H100 that moved
SSIM by 2e-3 against scikit-image and the sun-spot and fog presets' view cosines by 1e-3, and it would
move a 1920-pixel-wide projection by about a pixel. The CPU ignores the setting, so these tests read it
from the traced programs instead of comparing numbers.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.extend.core import ClosedJaxpr, Jaxpr

import godrays_jax as gr
from godrays_jax.primitives.camera import Camera
from godrays_jax.pipeline.fit_programs import forward_mode
from godrays_jax.raster import DirectionalLight, Material, Mesh, Scene, Sphere, render
from frames import LIGHT, make_frame, small

HIGHEST = (jax.lax.Precision.HIGHEST, jax.lax.Precision.HIGHEST)
PRODUCTS = ("dot_general", "conv_general_dilated")


def _equations(jaxpr):
    for equation in jaxpr.eqns:
        yield equation
        for value in equation.params.values():
            for inner in value if isinstance(value, (tuple, list)) else (value,):
                if isinstance(inner, ClosedJaxpr):
                    yield from _equations(inner.jaxpr)
                elif isinstance(inner, Jaxpr):
                    yield from _equations(inner)


def products_below_highest(function, *args):
    """The matrix products and convolutions in `function`'s program (nested ones too) without full precision."""
    products = [e for e in _equations(jax.make_jaxpr(function)(*args).jaxpr) if e.primitive.name in PRODUCTS]
    return len(products), [str(e.params["precision"]) for e in products if e.params["precision"] != HIGHEST]


def test_the_check_sees_a_default_precision_product():
    count, loose = products_below_highest(lambda a: a @ a, jnp.ones((2, 2)))
    assert count == 1 and loose == ["None"]


@pytest.mark.parametrize("name", sorted(gr.PRESETS))
def test_presets_and_their_gradients(name):
    effect = small(gr.preset(name))
    frame = make_frame()
    params, static = eqx.partition(effect, eqx.is_inexact_array)

    def loss(params, light):
        return jnp.sum(eqx.combine(params, static)(frame, light) ** 2)

    for function in (loss, jax.grad(loss, argnums=(0, 1))):
        _, loose = products_below_highest(function, params, LIGHT)
        assert not loose, (name, loose)


def test_losses_camera_rasterizer_and_fit_jacobian():
    image = jnp.asarray(np.random.default_rng(0).uniform(0, 1, (16, 16, 3)), jnp.float32)
    camera = Camera(position=[0, 0, 0], target=[0, 0, -1], up=[0, 1, 0], fov_x_deg=60.0, width=16, height=12)
    scene = Scene(
        objects=(
            Sphere(center=(0.4, 0.2, -4.0), radius=0.8, material=Material(albedo=(0, 0, 0), emission=(3.0, 2.0, 1.0))),
            Mesh(vertices=[[-1.5, -1.0, -6.0], [1.0, -1.2, -6.0], [-0.2, 1.3, -6.0]], faces=[[0, 1, 2]],
                 rotation_deg=(10.0, 20.0, 30.0), material=Material(albedo=(1.0, 0.2, 0.1))),
        ),
        light=DirectionalLight(direction=(0.0, 0.0, 1.0)),
        sun=0,
    )  # fmt: skip
    fitted = forward_mode(lambda y: jnp.sin(y) * y[::-1])
    cases = {
        "ssim loss": (jax.value_and_grad(lambda a: gr.ssim_loss(a, image[::-1])), image),
        "project_point": (lambda p: gr.project_point(camera, p), jnp.asarray([0.3, 0.2, -5.0])),
        "render": (lambda s: render(s, camera, with_glow_pass=False, tile_capacity=4).color, scene),
        "fit's forward-mode Jacobian": (lambda y: jax.jvp(fitted, (y,), (y,)), jnp.arange(3.0)),
    }
    for name, (function, argument) in cases.items():
        count, loose = products_below_highest(function, argument)
        assert count > 0 and not loose, (name, count, loose)
