"""The one model loader: a project (its latest checkpoint) or a splat file.

render, eval (`--model`), export and `train --init-ply` all load through
`load_model`, so they accept the same sources and refuse bad ones the same way.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import torch

from ..errors import SplatError
from ..gaussians import Gaussians
from ..project import Project, is_project
from .checkpoint import load_checkpoint
from .compressed_ply import is_compressed_ply
from .formats import SUFFIXES, format_of, read_format


@dataclass
class LoadedModel:
    gaussians: Gaussians  # truncated to the active SH degree
    kind: str  # "checkpoint", or the file's format (io/formats.py)
    path: Path  # the checkpoint or file read
    project: Project | None  # the project, when the source is one
    step: int | None = None  # training step of the checkpoint
    notes: list[str] = field(default_factory=list)  # what the reader had to do (dropped rows, ...)
    antialiased: bool | None = None  # trained with the 2D filter (checkpoint of train --mip-filter); None: unknown

    @property
    def name(self) -> str:
        """What was loaded, in words: "checkpoint step 7000" or the file's path."""
        return f"checkpoint step {self.step}" if self.kind == "checkpoint" else str(self.path)


def load_model(source: str | os.PathLike, device: torch.device) -> LoadedModel:
    """A project directory (its latest checkpoint) or a splat file of any format
    io/formats.py reads (.ply, .compressed.ply, .spz, .splat)."""
    source = Path(source)
    fmt = format_of(source) if not source.is_dir() else None
    if source.is_dir() and source.suffix.lower() == ".ply" and not is_project(source):
        raise SplatError(f"{source}: is a directory, not a .ply file")
    if source.is_dir() or is_project(source):
        project = Project.open(source)
        ck_path = project.require_trained()
        ck = load_checkpoint(ck_path, device)
        return LoadedModel(gaussians=ck.model(), kind="checkpoint", path=ck_path, project=project, step=ck.step,
                           antialiased=ck.antialiased)
    if not source.exists():
        if fmt is not None:
            raise SplatError(f"{source}: no such {SUFFIXES[fmt]} file")
        Project.open(source)  # raises: no such project, run `splatcli process` first
    if fmt is None:
        if not _starts_like_ply(source):
            raise SplatError(f"{source}: neither a splatcli project directory nor a splat file "
                             f"({', '.join(SUFFIXES.values())})")
        fmt = "compressed-ply" if is_compressed_ply(source) else "ply"
    r = read_format(source, device, fmt)
    return LoadedModel(gaussians=r.gaussians, kind=fmt, path=source, project=None, notes=list(r.notes))


def _starts_like_ply(path: Path) -> bool:
    try:
        with open(path, "rb") as f:
            return f.read(5).startswith((b"ply\n", b"ply\r\n"))
    except OSError:
        return True  # let the .ply reader name the problem
