"""Meshes from trained Gaussians: depth fusion and marching cubes (fuse.py), and their
distance to a reference surface (measure.py)."""
