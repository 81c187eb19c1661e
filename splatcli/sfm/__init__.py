"""Structure from motion and dataset import. The only package that imports pycolmap,
because its API changes between versions."""
