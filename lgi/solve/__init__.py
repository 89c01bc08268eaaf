"""Per-frame reconstruction: the global fit, the indexing solver, the jaw rig, temporal treatment."""
