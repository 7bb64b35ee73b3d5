"""Pipeline layer: sequences and batches of frames, and fitting effects to reference frames."""
