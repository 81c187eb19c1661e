"""`splatcli export`: the trained model as a 3DGS .ply or a web-viewer .splat."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..events import Note
from ..io.export import ExportConfig, check_export_config, export_project
from .common import DebugOpt, JsonOpt, QuietOpt, Ui

_D = ExportConfig()  # the defaults, written once in the config


def export(
    project: Path = typer.Argument(..., help="The project directory (its latest checkpoint is exported)."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Output file (default PROJECT/exports/scene.<format>)."),
    fmt: str = typer.Option(_D.format, "--format", "-f",
                            help="ply: 3DGS layout, lossless. splat: 32-byte web-viewer rows, SH degree 0 only."),
    quiet: bool = QuietOpt,
    json_out: bool = JsonOpt,
    debug: bool = DebugOpt,
) -> None:
    """Write the trained Gaussians in a format other tools read."""
    ui = Ui(quiet=quiet, json_out=json_out)
    cfg = ExportConfig(format=fmt.strip().lower(), out=out)
    check_export_config(cfg)
    # notes only: an export takes seconds, and errors must stay the only line
    sink = lambda ev: ui.note(ev.message, ev.level) if isinstance(ev, Note) else None  # noqa: E731
    r = export_project(project, cfg, on_event=sink)
    ui.summary(
        {"path": r.path, "format": r.format, "num_gaussians": r.num_gaussians, "num_dropped": r.num_dropped,
         "sh_degree": r.sh_degree, "bytes": r.bytes, "step": r.step, "lossy": r.lossy},
        title=f"exported {r.num_gaussians} Gaussians to {r.path}",
        lines=[f"{r.format}, SH degree {r.sh_degree}, {r.bytes / 1e6:.2f} MB, from checkpoint step {r.step}"],
    )
