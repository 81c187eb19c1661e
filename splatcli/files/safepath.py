"""Joining paths that come from files we did not write (transforms.json, COLMAP
models): they must not reach outside the folder they describe."""

from __future__ import annotations

import os
from pathlib import Path, PurePosixPath

from ..errors import SplatError


def safe_join(root: Path, rel: str, src: Path, what: str) -> Path:
    """root / rel, refusing paths that leave `root` (`..` or absolute) with a
    one-line SplatError naming `src` (the file that held the path). The check is
    lexical: symlinks inside the input folder are the user's business."""
    p = PurePosixPath(rel.replace("\\", "/"))
    if p.is_absolute():
        full = Path(os.path.normpath(str(p)))
    else:
        full = Path(os.path.normpath(str(root / p)))
    root_n = Path(os.path.normpath(str(root.absolute())))
    full_abs = Path(os.path.normpath(str(full.absolute())))
    if full_abs != root_n and root_n not in full_abs.parents:
        raise SplatError(f"{src}: {what} {rel!r} points outside the input folder {root}")
    return full
