"""Image primitives: sampling, resampling, colour encodings, buffers, camera, files and I/O, argument checks."""
