"""`splatcli export`: the trained model as an interchange file.

* `ply`: the original 3DGS layout, byte-compatible with its writer (see
  io/ply.py); every 3DGS viewer and tool reads it. Lossless.
* `splat`: the 32-byte-per-Gaussian web-viewer format (see io/splat.py).
  Lossy: SH bands above degree 0 are dropped (no view-dependent colour) and
  colour, opacity and rotation are quantised to 8 bits.

Rows with NaN/Inf values are dropped and counted.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import torch

from ..errors import SplatError
from ..events import EventSink, Note, Stage, StageDone, emit
from ..project import Project, writer_lock
from .model import load_model
from .ply import write_ply
from .splat import write_splat

EXPORT_FORMATS = ("ply", "splat")


@dataclass(frozen=True)
class ExportConfig:
    format: str = "ply"  # ply | splat
    out: Path | None = None  # default PROJECT/exports/scene.<format>


@dataclass
class ExportResult:
    path: Path
    format: str
    num_gaussians: int  # rows written
    num_dropped: int  # rows dropped for NaN/Inf
    sh_degree: int  # of the file (0 for .splat)
    bytes: int
    checkpoint: Path
    step: int
    lossy: bool


def check_export_config(config: ExportConfig) -> None:
    if config.format not in EXPORT_FORMATS:
        raise SplatError(f"--format {config.format!r} is not known; allowed values: {', '.join(EXPORT_FORMATS)}")
    if config.out is not None:
        out = Path(config.out)
        if out.is_dir():
            raise SplatError(f"-o {out}: is a directory; give a file name such as {out / ('scene.' + config.format)}")


def export_project(root: str | os.PathLike, config: ExportConfig, *, on_event: EventSink | None = None) -> ExportResult:
    """Write the latest checkpoint of the project at `root` as .ply or .splat."""
    check_export_config(config)
    project = Project.open(root)
    with writer_lock(project.root, "export", shared=True):
        return _export(project, config, on_event)


def _export(project: Project, config: ExportConfig, on_event: EventSink | None) -> ExportResult:
    m = load_model(project.root, torch.device("cpu"))
    g, ck_path, step = m.gaussians, m.path, m.step
    out = Path(config.out) if config.out is not None else project.export_path(config.format)
    emit(on_event, Stage(f"export {config.format}"))
    if config.format == "ply":
        r = write_ply(out, g)
        result = ExportResult(path=out, format="ply", num_gaussians=r.num_written, num_dropped=r.num_dropped,
                              sh_degree=r.sh_degree, bytes=r.bytes, checkpoint=ck_path, step=step, lossy=False)
    else:
        s = write_splat(out, g)
        result = ExportResult(path=out, format="splat", num_gaussians=s.num_written, num_dropped=s.num_dropped,
                              sh_degree=0, bytes=s.bytes, checkpoint=ck_path, step=step, lossy=True)
        if g.sh_degree > 0:
            emit(on_event, Note(f".splat keeps only SH degree 0: view-dependent colour (degree {g.sh_degree}) is dropped; "
                                "colour, opacity and rotation are 8-bit"))
    if result.num_dropped:
        emit(on_event, Note(f"dropped {result.num_dropped} Gaussians with NaN/Inf values", "warning"))
    emit(on_event, StageDone(f"export {config.format}", 0.0))
    return result
