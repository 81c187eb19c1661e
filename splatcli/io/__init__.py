"""File formats: atomic writes, .ply / .splat, checkpoints."""
