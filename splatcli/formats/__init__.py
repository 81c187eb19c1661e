"""Splat file formats: the Gaussians as files other tools read and write. One module per
format (`ply.py`, the original 3DGS layout; `spz.py`; `sog.py`; `compressed_ply.py`;
`splat.py`), what the compressed ones share (`codec.py`), the table of every format with its
one writer and reader (`registry.py`), and `splatcli export`'s checks and writing
(`export.py`). It takes paths and Gaussians, never a project; the model loader that reads
these is `model.py`."""
