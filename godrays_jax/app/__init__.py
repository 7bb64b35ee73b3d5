"""Application layer: the `godrays-jax` command line and the live tuner (its state, HTTP server and page)."""
