"""`splatcli export`: a model as an interchange file, or one file converted to another.

splatcli/model.py's export_project picks the source (a project's latest checkpoint, or a
splat file of any format splatcli reads, so `export` also converts between formats) and
the output; this module checks the options and writes. The file formats are registry.py's,
one module each (their sizes and losses: docs/benchmarks.md, "formats"); only `ply`, the
3DGS layout every viewer reads, is lossless. `web` is a folder, not a file: `view`'s page
with the scene as .sog, for any static web server (viewer/site.py, passed to
model.export_project as its writer by the CLI).

Rows with NaN/Inf values are dropped and counted. Every write is atomic.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from ..errors import SplatError
from ..events import EventSink, Note, Stage, StageDone, emit
from ..gaussians import Gaussians
from .registry import FORMATS, LOSSLESS, SUFFIXES, check_format, default_name, write_format
from .sog import SogOptions
from .spz import SpzOptions

EXPORT_FORMATS = (*FORMATS, "web", "mesh")  # mesh: cli/export_cmd hands it to mesh/fuse.py


@dataclass(frozen=True)
class ExportConfig:
    format: str = "ply"  # ply | spz | sog | compressed-ply | splat | web (mesh: mesh/fuse.py)
    out: Path | None = None  # default PROJECT/exports/scene.<suffix> (web: exports/web/), or beside a source file
    spz: SpzOptions = SpzOptions()  # SH bits and version of .spz
    sog: SogOptions = SogOptions()  # SH palette size of .sog


@dataclass
class ExportResult:
    path: Path
    format: str
    num_gaussians: int  # rows written
    num_dropped: int  # rows dropped for NaN/Inf
    sh_degree: int  # of the file (0 for .splat)
    bytes: int
    checkpoint: Path  # the checkpoint or file read
    step: int | None  # of the checkpoint (None for a file)
    lossy: bool


def check_export_config(config: ExportConfig) -> None:
    check_format(config.format, allowed=EXPORT_FORMATS)
    if config.out is not None and config.format == "web":
        check_web_folder(Path(config.out))
    elif config.out is not None:
        out = Path(config.out)
        if out.is_dir():
            raise SplatError(f"-o {out}: is a directory; give a file name such as {out / default_name('scene', config.format)}")
    for name, bits in (("--spz-sh-bits", config.spz.sh1_bits), ("--spz-sh-bits", config.spz.sh_rest_bits)):
        if not 1 <= bits <= 8:
            raise SplatError(f"{name}: {bits} bits is not in 1-8")
    if config.spz.version not in (3, 4):
        raise SplatError(f"--spz-version {config.spz.version}: SPZ versions 3 and 4 are written")
    if config.sog.palette is not None and not 1 <= config.sog.palette <= 65536:
        raise SplatError(f"--sog-palette {config.sog.palette}: must be in 1-65536")


def check_web_folder(out: Path) -> None:
    """`--format web` writes a folder: a new one, an empty one, or a previous web export (replaced)."""
    if out.exists() and not out.is_dir():
        raise SplatError(f"-o {out}: is a file; --format web writes a folder, give a folder name such as {out.parent / 'web'}")
    if out.is_dir() and any(out.iterdir()) and not (out / "api" / "scene").is_file():
        raise SplatError(f"-o {out}: is a folder with other files in it; give a new or empty folder "
                         "(a previous web export is replaced)")


def path_beside(source: Path, fmt: str) -> Path:
    """Where a converted file goes by default: beside `source`, its name with `fmt`'s suffix
    (web: the folder STEM-web)."""
    if fmt == "web":
        return source.with_name(f"{_stem(source)}-web")
    return source.with_name(default_name(_stem(source), fmt))


def _stem(path: Path) -> str:
    name = path.name
    for suffix in sorted(SUFFIXES.values(), key=len, reverse=True):  # ".compressed.ply" before ".ply"
        if name.lower().endswith(suffix):
            return name[: -len(suffix)]
    return path.stem


def export_gaussians(g: Gaussians, out: Path, config: ExportConfig, *, source: Path, step: int | None,
                     notes: Sequence[str] = (), on_event: EventSink | None = None) -> ExportResult:
    """Write `g` to `out` in `config.format`; `source` and `step` say where it was read
    (the checkpoint or file), `notes` what its reader had to do."""
    for n in notes:
        emit(on_event, Note(n))
    emit(on_event, Stage(f"export {config.format}"))
    r = write_format(config.format, out, g, config.spz, config.sog)
    result = ExportResult(path=out, format=config.format, num_gaussians=r.num_written, num_dropped=r.num_dropped,
                          sh_degree=r.sh_degree, bytes=r.bytes, checkpoint=source, step=step,
                          lossy=config.format not in LOSSLESS)
    if config.format == "splat" and g.sh_degree > 0:
        emit(on_event, Note(f".splat keeps only SH degree 0: view-dependent colour (degree {g.sh_degree}) is dropped; "
                            "colour, opacity and rotation are 8-bit"))
    if result.num_dropped:
        emit(on_event, Note(f"dropped {result.num_dropped} Gaussians with NaN/Inf values", "warning"))
    emit(on_event, StageDone(f"export {config.format}", 0.0))
    return result
