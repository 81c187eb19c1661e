"""`splatcli export`: a project's model, or any splat file, as .ply, .spz, .sog, .compressed.ply or .splat."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..events import Note
from ..io.export import ExportConfig, check_export_config
from ..io.sog import SogOptions
from ..io.spz import SpzOptions
from ..model import export_project
from .common import DebugOpt, JsonOpt, QuietOpt, Ui

_D = ExportConfig()  # the defaults, written once in the config


def export(
    source: Path = typer.Argument(..., help="A project directory (its latest checkpoint), or a splat file to convert "
                                  "(.ply, .compressed.ply, .spz, .sog, .splat)."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Output file (default PROJECT/exports/scene.<suffix>, "
                                       "or the source file's name with the new suffix)."),
    fmt: str = typer.Option(_D.format, "--format", "-f",
                            help="ply: 3DGS layout, lossless. spz: Niantic SPZ (~10x smaller). sog: PlayCanvas SOG (~15-20x smaller). compressed-ply: "
                                 "SuperSplat/PlayCanvas chunks (~4x smaller). splat: 32-byte web-viewer rows, SH degree 0 "
                                 "only. docs/guide.md says which viewer reads which."),
    spz_sh_bits: str = typer.Option(f"{_D.spz.sh1_bits},{_D.spz.sh_rest_bits}", "--spz-sh-bits",
                                    help="SPZ: bits per SH coefficient of degree 1, and of degrees 2-3 (fewer: smaller, "
                                         "less view-dependent colour)."),
    spz_version: int = typer.Option(_D.spz.version, "--spz-version", help="SPZ: 4 (zstd; Niantic's library, "
                                    "PlayCanvas/SuperSplat, splat-transform 3) or 3 (gzip, right-up-back; Spark 2.2 and "
                                    "other readers of v3 only)."),
    sog_palette: Optional[int] = typer.Option(None, "--sog-palette", help="SOG: entries of the SH palette (k-means of the "
                                              "Gaussians' SH; default a power of two near N/16, 256 to 4096; more: larger, "
                                              "closer view-dependent colour)."),
    quiet: bool = QuietOpt,
    json_out: bool = JsonOpt,
    debug: bool = DebugOpt,
) -> None:
    """Write Gaussians in a format other tools read (also: convert one splat file into another)."""
    ui = Ui(quiet=quiet, json_out=json_out)
    cfg = ExportConfig(format=fmt.strip().lower(), out=out, spz=SpzOptions(*_bits(spz_sh_bits), version=spz_version),
                       sog=SogOptions(palette=sog_palette))
    check_export_config(cfg)
    # notes only: an export takes seconds, and errors must stay the only line
    sink = lambda ev: ui.note(ev.message, ev.level) if isinstance(ev, Note) else None  # noqa: E731
    r = export_project(source, cfg, on_event=sink)
    origin = f"checkpoint step {r.step}" if r.step is not None else str(r.checkpoint)
    ui.summary(
        {"path": r.path, "format": r.format, "num_gaussians": r.num_gaussians, "num_dropped": r.num_dropped,
         "sh_degree": r.sh_degree, "bytes": r.bytes, "step": r.step, "source": r.checkpoint, "lossy": r.lossy},
        title=f"exported {r.num_gaussians} Gaussians to {r.path}",
        lines=[f"{r.format}, SH degree {r.sh_degree}, {r.bytes / 1e6:.2f} MB, from {origin}"],
    )


def _bits(text: str) -> tuple[int, int]:
    from ..errors import SplatError

    try:
        a, b = (int(x) for x in text.split(","))
    except ValueError:
        raise SplatError(f"--spz-sh-bits {text!r}: expected two whole numbers, e.g. 5,4") from None
    return a, b
