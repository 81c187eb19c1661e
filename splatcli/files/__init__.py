"""The project's own files, at the bottom of every write: atomic writes and bounded JSON
reads (`atomic.py`: temp file, fsync, rename), joining paths that come from files we did
not write (`safepath.py`), and training checkpoints (`checkpoint.py`: tensors and plain
data, read back with weights_only). Where each file lives in a project is `project.py`'s."""
