"""What `render` looks from and writes: camera sources, generated paths, and the
views rendered to PNGs and videos."""
