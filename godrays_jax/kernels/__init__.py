"""Kernels layer: pure functions on images (image first, options keyword-only), differentiable under jit and vmap."""
