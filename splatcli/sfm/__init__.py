"""Structure from motion and the COLMAP model: the only package that imports pycolmap,
because its API changes between versions."""
