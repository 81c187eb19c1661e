"""The one model loader, and where `export` reads and writes: a project (its latest
checkpoint) or a splat file.

render, eval (`--model`), view, export and `train --init-ply` all load through
`load_model`, so they accept the same sources and refuse bad ones the same way.
This module sits above project.py (it opens projects) and formats/ and files/ (it reads
files): those read and write files and know no project.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch

from .errors import SplatError
from .events import EventSink
from .files.checkpoint import load_checkpoint
from .formats.compressed_ply import is_compressed_ply
from .formats.export import (
    EXPORT_FORMATS,
    ExportConfig,
    ExportResult,
    check_export_config,
    export_gaussians,
    path_beside,
)
from .formats.registry import SUFFIXES, check_format, format_of, read_format
from .gaussians import Gaussians
from .project import Project, is_project, writer_lock


@dataclass
class LoadedModel:
    gaussians: Gaussians  # truncated to the active SH degree
    kind: str  # "checkpoint", or the file's format (formats/registry.py)
    path: Path  # the checkpoint or file read
    project: Project | None  # the project, when the source is one
    step: int | None = None  # training step of the checkpoint
    notes: list[str] = field(default_factory=list)  # what the reader had to do (dropped rows, ...)
    antialiased: bool | None = None  # trained with the 2D filter (checkpoint of train --mip-filter); None: unknown
    light: torch.Tensor | None = None  # [3, 4] the training photo's colour transform baked in (--appearance-of)

    def lit(self, background: tuple[float, float, float]) -> tuple[float, float, float]:
        """A background as this model shows it: through its light (--appearance-of), as the
        colours baked into it went (Gaussians.recoloured); unchanged without one."""
        if self.light is None:
            return background
        t = self.light.cpu()
        bg = (torch.tensor(background, dtype=t.dtype) @ t[:, :3].T + t[:, 3]).clamp(0, 1)
        return (float(bg[0]), float(bg[1]), float(bg[2]))

    @property
    def name(self) -> str:
        """What was loaded, in words: "checkpoint step 7000" or the file's path."""
        return f"checkpoint step {self.step}" if self.kind == "checkpoint" else str(self.path)


def load_model(source: str | os.PathLike, device: torch.device, appearance_of: str | None = None) -> LoadedModel:
    """A project directory (its latest checkpoint) or a splat file of any format
    formats/registry.py reads (.ply, .compressed.ply, .spz, .splat). The model has the scene's
    reference light (what training's per-photo transforms average to); `appearance_of`: a
    training photo's instead (a project trained with --appearance exposure), baked into its SH."""
    source = Path(source)
    fmt = format_of(source) if not source.is_dir() else None
    if source.is_dir() and source.suffix.lower() == ".ply" and not is_project(source):
        raise SplatError(f"{source}: is a directory, not a .ply file")
    if source.is_dir() or is_project(source):
        project = Project.open(source)
        ck_path = project.require_trained()
        ck = load_checkpoint(ck_path, device)
        light = _light_of(project, ck.appearance, appearance_of) if appearance_of is not None else None
        g = ck.model() if light is None else ck.model().recoloured(light)
        return LoadedModel(gaussians=g, kind="checkpoint", path=ck_path, project=project, step=ck.step,
                           antialiased=ck.antialiased, light=light)
    if appearance_of is not None:
        raise SplatError(f"--appearance-of {appearance_of}: {source} is a splat file; only a project's checkpoint "
                         "holds each training photo's light")
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


def _light_of(project: Project, appearance: dict, name: str) -> torch.Tensor:  # -> [3, 4]
    """Training photo `name`'s learnt colour transform, from a checkpoint's appearance state."""
    t = appearance.get("transforms")
    if not isinstance(t, torch.Tensor):
        raise SplatError(f"--appearance-of {name}: {project.root} was trained without --appearance exposure, so every "
                         "photo has the scene's one light")
    train = project.splits()["train"]  # the order training numbered the photos in
    if name not in train:
        shown = ", ".join(train[:5]) + (", ..." if len(train) > 5 else "")
        raise SplatError(f"--appearance-of {name}: not a training photo of {project.root} ({shown})")
    if len(train) != t.shape[0]:
        raise SplatError(f"--appearance-of {name}: the checkpoint holds {t.shape[0]} photos' transforms but the "
                         f"project's train split has {len(train)}; train again")
    return t[train.index(name)].detach().to(torch.float32)


def _starts_like_ply(path: Path) -> bool:
    try:
        with open(path, "rb") as f:
            return f.read(5).startswith((b"ply\n", b"ply\r\n"))
    except OSError:
        return True  # let the .ply reader name the problem


Writer = Callable[[LoadedModel, Path, ExportConfig, EventSink | None], ExportResult]


def export_project(root: str | os.PathLike, config: ExportConfig, *, on_event: EventSink | None = None,
                   write: Writer | None = None, appearance_of: str | None = None) -> ExportResult:
    """Write the latest checkpoint of the project at `root`, or the splat file `root`,
    in `config.format` (formats/export.py): a project's to PROJECT/exports/ under its lock
    (shared), a file's beside it. `write`: what writes the loaded model instead of
    formats/export.py (--format web: viewer/site.py's export_site, a layer above this one);
    `appearance_of`: a training photo's light instead of the scene's (load_model)."""
    config = ExportConfig(check_format(config.format, allowed=EXPORT_FORMATS), config.out, config.spz, config.sog)
    check_export_config(config)
    root = Path(root)
    if root.is_dir() or is_project(root) or not root.exists():
        project = Project.open(root)
        with writer_lock(project.root, "export", shared=True):
            out = Path(config.out) if config.out is not None else project.export_path(config.format)
            return _export(project.root, out, config, on_event, write, appearance_of)
    out = Path(config.out) if config.out is not None else path_beside(root, config.format)
    if out.resolve() == root.resolve():
        raise SplatError(f"-o {out}: is the source file itself; give another name")
    return _export(root, out, config, on_event, write, appearance_of)


def _export(source: Path, out: Path, config: ExportConfig, on_event: EventSink | None,
            write: Writer | None, appearance_of: str | None) -> ExportResult:
    m = load_model(source, torch.device("cpu"), appearance_of)
    if write is not None:
        return write(m, out, config, on_event)
    return export_gaussians(m.gaussians, out, config, source=m.path, step=m.step, notes=m.notes, on_event=on_event)
