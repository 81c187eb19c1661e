"""`splatcli export`: a project's model, or any splat file, as .ply, .spz, .sog, .compressed.ply or .splat,
or as a folder a static web server serves (web)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..errors import SplatError
from ..events import Note
from ..formats.export import ExportConfig
from ..formats.sog import SogOptions
from ..formats.spz import SpzOptions
from ..mesh.fuse import MeshConfig, export_mesh
from ..model import export_project
from ..viewer.site import export_site
from .common import DebugOpt, JsonOpt, QuietOpt, Ui

_D = ExportConfig()  # the defaults, written once in the config
_M = MeshConfig()


def export(
    source: Path = typer.Argument(..., help="A project directory (its latest checkpoint), or a splat file to convert "
                                  "(.ply, .compressed.ply, .spz, .sog, .splat)."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Output file (default PROJECT/exports/scene.<suffix>, "
                                       "or the source file's name with the new suffix); for web a folder "
                                       "(default PROJECT/exports/web/); for mesh the .ply, the .obj beside it "
                                       "(default PROJECT/exports/mesh.ply)."),
    fmt: str = typer.Option(_D.format, "--format", "-f",
                            help="ply: 3DGS layout, lossless. spz: Niantic SPZ (~10x smaller). sog: PlayCanvas SOG (~15-20x smaller). compressed-ply: "
                                 "SuperSplat/PlayCanvas chunks (~4x smaller). splat: 32-byte web-viewer rows, SH degree 0 "
                                 "only. web: a folder with the viewer's page and the scene as .sog, to share: any static web "
                                 "server shows it, offline too. mesh: triangles (PROJECT/exports/mesh.ply and .obj, vertex "
                                 "colours) fused from the training views' depth. docs/guide.md says which viewer reads which."),
    spz_sh_bits: str = typer.Option(f"{_D.spz.sh1_bits},{_D.spz.sh_rest_bits}", "--spz-sh-bits",
                                    help="SPZ: bits per SH coefficient of degree 1, and of degrees 2-3 (fewer: smaller, "
                                         "less view-dependent colour)."),
    spz_version: int = typer.Option(_D.spz.version, "--spz-version", help="SPZ: 3 (gzip; Spark 2.2, Niantic's "
                                    "library, PlayCanvas/SuperSplat) or 4 (zstd, a little smaller; Niantic's library, PlayCanvas/SuperSplat, "
                                    "splat-transform 3, not Spark 2.2). Both in the .ply's frame, declared."),
    sog_palette: Optional[int] = typer.Option(None, "--sog-palette", help="SOG: entries of the SH palette (k-means of the "
                                              "Gaussians' SH; default a power of two near N/16, 256 to 4096; more: larger, "
                                              "closer view-dependent colour)."),
    appearance_of: Optional[str] = typer.Option(None, "--appearance-of", help="A training photo's name: export with "
                                                "its light (what --appearance exposure learnt for it) baked into the "
                                                "colours, instead of the scene's, the average of the training photos'."),
    voxel_size: Optional[float] = typer.Option(_M.voxel_size, "--voxel-size", help="mesh: voxel size in world units "
                                               "(default: 1/256 of the scene's longest side)."),
    depth_trunc: Optional[float] = typer.Option(_M.depth_trunc, "--depth-trunc", help="mesh: fuse no depth beyond "
                                                "this (world units; default: all), e.g. to leave out a far background."),
    views: str = typer.Option(_M.views, "--views", help="mesh: the views fused: train, test, all, or image names "
                              "separated by commas."),
    quiet: bool = QuietOpt,
    json_out: bool = JsonOpt,
    debug: bool = DebugOpt,
) -> None:
    """Write Gaussians in a format other tools read (also: convert one splat file into another)."""
    ui = Ui(quiet=quiet, json_out=json_out)
    if fmt.strip().lower() == "mesh":
        with ui.progress() as sink:
            m = export_mesh(source, MeshConfig(voxel_size, depth_trunc, views.strip()), out, on_event=sink)
        return ui.summary({"path": m.path, "obj": m.obj, "format": "mesh", "vertices": m.num_vertices,
                           "faces": m.num_faces, "voxel_size": m.voxel_size, "grid": m.grid, "views": m.views,
                           "seconds": m.seconds, "step": m.step},
                          title=f"exported a mesh of {m.num_faces:,} triangles to {m.path}",
                          lines=[f"also {m.obj}; {m.views} views fused into a {'x'.join(map(str, m.grid))} volume "
                                 f"(voxel {m.voxel_size:.4g}) in {m.seconds:.1f} s"])
    cfg = ExportConfig(format=fmt.strip().lower(), out=out, spz=SpzOptions(*_bits(spz_sh_bits), version=spz_version),
                       sog=SogOptions(palette=sog_palette))
    # notes only: an export takes seconds, and errors must stay the only line
    sink = lambda ev: ui.note(ev.message, ev.level) if isinstance(ev, Note) else None  # noqa: E731
    r = export_project(source, cfg, on_event=sink, write=export_site if cfg.format == "web" else None,
                       appearance_of=appearance_of)
    origin = f"checkpoint step {r.step}" if r.step is not None else str(r.checkpoint)
    ui.summary(
        {"path": r.path, "format": r.format, "num_gaussians": r.num_gaussians, "num_dropped": r.num_dropped,
         "sh_degree": r.sh_degree, "bytes": r.bytes, "step": r.step, "source": r.checkpoint, "lossy": r.lossy},
        title=f"exported {r.num_gaussians} Gaussians to {r.path}",
        lines=[f"{r.format}, SH degree {r.sh_degree}, {r.bytes / 1e6:.2f} MB, from {origin}"],
    )


def _bits(text: str) -> tuple[int, int]:
    try:
        a, b = (int(x) for x in text.split(","))
    except ValueError:
        raise SplatError(f"--spz-sh-bits {text!r}: expected two whole numbers, e.g. 5,4") from None
    return a, b
