"""Every splat file format splatcli writes and reads, in one table.

    ply             the original 3DGS layout, lossless (formats/ply.py)
    compressed-ply  SuperSplat's chunked 8-11-bit layout, PlayCanvas viewers (formats/compressed_ply.py)
    spz             Niantic's fixed-point layout, zstd (v4) or gzip (v3) packed (formats/spz.py)
    sog             PlayCanvas's WebP images with codebooks, zipped (formats/sog.py)
    splat           the 32-byte rows of the antimatter15 web viewers, SH degree 0 (formats/splat.py)

`format_of` names a file's format from its name (and, for `.ply`, its header);
`write_format` / `read_format` are the one writer and reader per format that
export, eval --formats and the model loader use.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import torch

from ..errors import SplatError
from ..gaussians import Gaussians
from .compressed_ply import is_compressed_ply, read_compressed_ply, write_compressed_ply
from .ply import read_ply, write_ply
from .sog import SogOptions, read_sog, write_sog
from .splat import read_splat, splat_gaussians, write_splat
from .spz import SpzOptions, read_spz, write_spz

SUFFIXES = {"ply": ".ply", "compressed-ply": ".compressed.ply", "spz": ".spz", "sog": ".sog", "splat": ".splat"}
FORMATS = tuple(SUFFIXES)
LOSSLESS = ("ply",)


@dataclass(frozen=True)
class WriteResult:
    num_written: int
    num_dropped: int  # rows with NaN/Inf values (or a zero quaternion)
    bytes: int
    sh_degree: int  # of the file


@dataclass(frozen=True)
class ReadResult:
    gaussians: Gaussians
    format: str
    notes: list[str]


def check_format(fmt: str, option: str = "--format", allowed: tuple[str, ...] = FORMATS) -> str:
    f = fmt.strip().lower()
    if f not in allowed:
        raise SplatError(f"{option} {fmt!r} is not known; allowed values: {', '.join(allowed)}")
    return f


def format_of(path: str | os.PathLike) -> str | None:
    """The format a file name says (".compressed.ply" before ".ply"; a ".ply" whose
    header has the compressed layout's chunk element is compressed-ply)."""
    name = Path(path).name.lower()
    if name.endswith(".compressed.ply"):
        return "compressed-ply"
    if name.endswith(".ply"):
        return "compressed-ply" if is_compressed_ply(path) else "ply"
    if name == "meta.json":  # an unbundled SOG
        return "sog"
    for fmt, suffix in SUFFIXES.items():
        if name.endswith(suffix):
            return fmt
    return None


def default_name(stem: str, fmt: str) -> str:
    return stem + SUFFIXES[fmt]


def write_format(fmt: str, path: str | os.PathLike, g: Gaussians, spz: SpzOptions = SpzOptions(),
                 sog: SogOptions = SogOptions()) -> WriteResult:
    """Write `g` as `fmt` (atomically, as every export)."""
    if fmt == "ply":
        r = write_ply(path, g)
        return WriteResult(r.num_written, r.num_dropped, r.bytes, r.sh_degree)
    if fmt == "splat":
        s = write_splat(path, g)
        return WriteResult(s.num_written, s.num_dropped, s.bytes, 0)
    if fmt == "spz":
        return WriteResult(*write_spz(path, g, spz), g.sh_degree)
    if fmt == "compressed-ply":
        return WriteResult(*write_compressed_ply(path, g), g.sh_degree)
    if fmt == "sog":
        return WriteResult(*write_sog(path, g, sog), g.sh_degree)
    raise SplatError(f"--format {fmt!r} is not known; allowed values: {', '.join(FORMATS)}")


def read_format(path: str | os.PathLike, device: torch.device | str = "cpu", fmt: str | None = None) -> ReadResult:
    """A splat file of any format above as Gaussians (one-line SplatError when it is
    not what it claims)."""
    path = Path(path)
    fmt = fmt or format_of(path)
    if fmt == "ply":
        r = read_ply(path, device)
        return ReadResult(r.gaussians, fmt, list(r.notes))
    read = {"compressed-ply": read_compressed_ply, "spz": read_spz, "sog": read_sog,
            "splat": lambda p, d: splat_gaussians(read_splat(p), d)}.get(fmt)
    if read is None:
        raise SplatError(f"{path}: not a splat file splatcli reads ({', '.join(SUFFIXES.values())})")
    return ReadResult(read(path, device), fmt, [])
