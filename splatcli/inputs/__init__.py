"""Capture inputs: the files a capture brings that splatcli reads and never writes. The one
image loader and the input images' checks and staging (`images.py`), EXIF camera facts
(`exif.py`), the one transforms.json reader (`transforms.py`) and the one LLFF
poses_bounds.npy reader (`llff.py`). `process/` turns these into a project; a COLMAP
workspace is read by `sfm/`."""
