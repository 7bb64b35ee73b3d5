"""`python -m godrays_jax`: the command line, as the `godrays-jax` script."""

from godrays_jax.app.cli import script

script()
