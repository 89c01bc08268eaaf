"""File formats and safe writing: atomic outputs, CSV, deterministic npz, OBJ."""
