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
from .ply import read_ply


@dataclass
class LoadedModel:
    gaussians: Gaussians  # truncated to the active SH degree
    kind: str  # "checkpoint" | "ply"
    path: Path  # the checkpoint or file read
    project: Project | None  # the project, when the source is one
    step: int | None = None  # training step of the checkpoint
    notes: list[str] = field(default_factory=list)  # what the reader had to do (dropped rows, ...)

    @property
    def name(self) -> str:
        """What was loaded, in words: "checkpoint step 7000" or the file's path."""
        return f"checkpoint step {self.step}" if self.kind == "checkpoint" else str(self.path)


def load_model(source: str | os.PathLike, device: torch.device) -> LoadedModel:
    """A project directory (its latest checkpoint) or a 3DGS .ply file."""
    source = Path(source)
    if source.is_dir() and source.suffix.lower() == ".ply" and not is_project(source):
        raise SplatError(f"{source}: is a directory, not a .ply file")
    if source.is_dir() or is_project(source):
        project = Project.open(source)
        ck_path = project.require_trained()
        ck = load_checkpoint(ck_path, device)
        return LoadedModel(gaussians=ck.model(), kind="checkpoint", path=ck_path, project=project, step=ck.step)
    if not source.exists():
        if source.suffix.lower() == ".ply":
            raise SplatError(f"{source}: no such .ply file")
        Project.open(source)  # raises: no such project, run `splatcli process` first
    if source.suffix.lower() != ".ply" and not _starts_like_ply(source):
        raise SplatError(f"{source}: neither a splatcli project directory nor a 3DGS .ply file")
    r = read_ply(source, device)
    return LoadedModel(gaussians=r.gaussians, kind="ply", path=source, project=None, notes=list(r.notes))


def _starts_like_ply(path: Path) -> bool:
    try:
        with open(path, "rb") as f:
            return f.read(5).startswith((b"ply\n", b"ply\r\n"))
    except OSError:
        return True  # let the .ply reader name the problem
