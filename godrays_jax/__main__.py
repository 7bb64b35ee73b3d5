"""`python -m godrays_jax`: the command line, as the `godrays-jax` script."""

import sys

from godrays_jax.app.cli import console_main

sys.exit(console_main())
