"""The interchange .ply: byte-compatible with the original 3DGS writer, and a
reader that accepts what real tools write.

Layout written (one `vertex` element, binary little-endian, every property float32):

    x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 f_rest_0 .. f_rest_{3((d+1)^2-1)-1}
    opacity scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3

f_rest is channel-major (all R coefficients of bands 1.., then G, then B);
opacity is a logit, scales are logs, rot is the quaternion w, x, y, z
(unnormalised); positions are in the project's COLMAP world frame; normals are
zero. The header is exactly what `plyfile` writes for that array, so a file
written here and one written by 3DGS's `save_ply` are byte-identical.

The reader takes SH degree 0 to 3, with or without normals, properties in any
order, float or double, either endianness, other scalar elements before or after
the vertices, extra properties (ignored, with a note) and unnormalised quaternions.
It refuses, in one line, anything that is not a Gaussian splat: a plain point
cloud, a truncated file, a header claiming more vertices than the file holds,
ASCII PLY and list properties.

Parsing is plyfile's (`PlyData.read(mmap="r")`): it checks each element's claimed
size against the file before memory-mapping it, so nothing is allocated for a
lying count: a tiny file whose header claims 10^12 vertices is refused at once,
with no growth in max RSS. `_check_head` keeps the cases plyfile does not bound.
"""

from __future__ import annotations

import os
import re
import stat
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import plyfile
import torch

from ..errors import SplatError
from ..files.atomic import atomic_path
from ..gaussians import Gaussians, num_sh_bases

MAX_SH_DEGREE = 3
MAX_HEADER_BYTES = 1 << 20  # a 3DGS header is ~1.5 KB; anything past 1 MiB is not a splat
_F_REST_RE = re.compile(r"^f_rest_(0|[1-9][0-9]*)$")  # no leading zeros: "f_rest_08" is not f_rest_8
_REQUIRED = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
             "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
_SPLAT_MARKERS = ("f_dc_0", "opacity", "scale_0", "rot_0")
_NORMALS = ("nx", "ny", "nz")


class PlyError(SplatError, ValueError):
    """A .ply file that cannot be read as a Gaussian splat (one line, names the file)."""


# ---------------------------------------------------------------------------
# writing
# ---------------------------------------------------------------------------


def ply_property_names(sh_degree: int) -> list[str]:
    """The 3DGS property list, in file order, for SH degree `sh_degree`."""
    if not 0 <= sh_degree <= MAX_SH_DEGREE:
        raise ValueError(f"sh_degree must be 0..{MAX_SH_DEGREE}, got {sh_degree}")
    n_rest = 3 * (num_sh_bases(sh_degree) - 1)
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(n_rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def ply_header(num_gaussians: int, sh_degree: int) -> bytes:
    """The header, byte for byte as plyfile (and so 3DGS's save_ply) writes it."""
    lines = ["ply", "format binary_little_endian 1.0", f"element vertex {int(num_gaussians)}"]
    lines += [f"property float {n}" for n in ply_property_names(sh_degree)]
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


def ply_bytes(num_gaussians: int, sh_degree: int) -> int:
    """Exact size in bytes of the .ply `write_ply` produces for this many
    Gaussians: header + 4 bytes x (14 + 3 (d+1)^2) floats per Gaussian."""
    floats = len(ply_property_names(sh_degree))  # 3 + 3 + 3 + 3((d+1)^2 - 1) + 1 + 3 + 4
    return len(ply_header(num_gaussians, sh_degree)) + 4 * floats * int(num_gaussians)


def gaussians_to_rows(g: Gaussians) -> np.ndarray:
    """The vertex table [N, P] float32 in 3DGS property order (normals zero)."""
    g = g.detach()
    n = len(g)
    k = int(g.sh.shape[1])
    # [N] or [N, C] -> [N, C] float32 on the CPU (works for N = 0 too)
    cpu = lambda t: t.to(device="cpu", dtype=torch.float32).reshape(n, 1 if t.dim() == 1 else t.shape[1])  # noqa: E731
    sh = g.sh.to(device="cpu", dtype=torch.float32)  # [N, K, 3]
    dc = sh[:, 0, :]  # [N, 3]
    # channel-major f_rest: [N, K-1, 3] -> [N, 3, K-1] -> [N, 3(K-1)]
    rest = sh[:, 1:, :].transpose(1, 2).reshape(n, 3 * (k - 1))
    rows = [cpu(g.means), torch.zeros(n, 3), dc, rest, cpu(g.opacity_logits), cpu(g.log_scales), cpu(g.quats)]
    return torch.cat(rows, dim=1).numpy()


@dataclass(frozen=True)
class PlyWriteResult:
    path: Path
    num_written: int  # rows in the file
    num_dropped: int  # rows dropped for NaN/Inf values
    sh_degree: int
    bytes: int  # file size


def write_ply(path: str | os.PathLike, gaussians: Gaussians) -> PlyWriteResult:
    """Write `gaussians` in the 3DGS layout (atomically). Rows with a non-finite
    value are dropped and counted, since viewers choke on NaN."""
    path = Path(path)
    d = gaussians.sh_degree
    if d > MAX_SH_DEGREE:
        raise ValueError(f"SH degree {d} > {MAX_SH_DEGREE} has no 3DGS .ply layout")
    rows = gaussians_to_rows(gaussians)
    finite = np.isfinite(rows).all(axis=1)
    dropped = int((~finite).sum())
    if dropped:
        rows = rows[finite]
    rows = np.ascontiguousarray(rows, dtype="<f4")
    header = ply_header(rows.shape[0], d)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(header)
        rows.tofile(f)
    return PlyWriteResult(path=path, num_written=int(rows.shape[0]), num_dropped=dropped, sh_degree=d,
                          bytes=len(header) + rows.nbytes)


# ---------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------


@dataclass
class PlyRead:
    """A Gaussian splat read from a .ply, plus what the reader had to do."""

    gaussians: Gaussians
    sh_degree: int
    num_vertices: int  # rows in the file
    num_dropped: int  # rows dropped: NaN/Inf or a zero quaternion
    has_normals: bool
    extra_properties: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)  # one line each, for Note events


def _check_head(path: Path, head: bytes) -> None:
    """Refuse, from the file's first MAX_HEADER_BYTES (`head`) only, what plyfile would read unbounded.

    Hand-written because plyfile (1.1.5) does not bound these: it reads the header
    one byte at a time until `end_header`, so a large file without one is read slowly,
    its memory growing, to the end before failing; and it reads ASCII elements and
    elements with list properties with `np.empty(claimed count)` then a Python loop per
    row, so a tiny file's claimed row count alone sets the time and memory spent. Only
    binary files without list properties reach plyfile, which then memory-maps every
    element after checking its size.
    The lines are split and tokenised as plyfile does (on the newline after
    `ply`, with str.split), so the checks see the header plyfile would parse.
    """
    nl = b"\r\n" if head.startswith(b"ply\r\n") else b"\n"
    if not head.startswith(b"ply" + nl):
        raise PlyError(f"{path}: not a PLY file (it does not start with 'ply')")
    end = head.find(nl + b"end_header" + nl)
    if end < 0:
        raise PlyError(f"{path}: PLY header has no end_header within {len(head)} bytes (truncated or not a PLY file)")
    try:
        lines = head[:end].decode("ascii").split(nl.decode())
    except UnicodeDecodeError:
        raise PlyError(f"{path}: PLY header contains non-ASCII bytes") from None
    for words in map(str.split, lines):
        if words[:2] == ["format", "ascii"]:
            raise PlyError(f"{path}: ASCII PLY is not supported for splats; write binary_little_endian")
        if words[:2] == ["property", "list"]:
            raise PlyError(f"{path}: property {words[-1]!r} is {' '.join(words[1:-1]) or 'list'}; "
                           f"Gaussian parameters must be float or double scalars (PLY list properties are refused)")


def _read_plydata(path: Path) -> plyfile.PlyData:
    """The whole file through plyfile, every element memory-mapped (nothing read
    into memory yet), or a one-line PlyError naming the file."""
    try:
        with open(path, "rb") as f:
            st = os.fstat(f.fileno())
            if not stat.S_ISREG(st.st_mode):  # plyfile memory-maps only regular files
                raise PlyError(f"{path}: not a regular file")
            _check_head(path, f.read(min(st.st_size, MAX_HEADER_BYTES)))
            f.seek(0)
            return plyfile.PlyData.read(f, mmap="r")
    except PlyError:
        raise
    except FileNotFoundError:
        raise PlyError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise PlyError(f"{path}: is a directory, not a .ply file") from None
    except OSError as exc:
        raise PlyError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except plyfile.PlyElementParseError as exc:
        e = exc.element
        if exc.message == "early end-of-file" and e is not None and exc.row is not None:
            what = "vertices" if e.name == "vertex" else f"{e.name!r} rows"
            raise PlyError(f"{path}: header claims {e.count} {what} but the file holds only {exc.row} "
                           f"(truncated file or lying header)") from None
        raise PlyError(f"{path}: bad PLY data ({' '.join(str(exc).split())[:200]})") from None
    except Exception as exc:  # plyfile's PlyHeaderParseError, ValueError from numpy, ...
        raise PlyError(f"{path}: bad PLY file ({' '.join(str(exc).split())[:200] or type(exc).__name__})") from None


def _sh_layout(path: Path, names: list[str]) -> int:
    """SH degree from the f_rest_* properties; they must be exactly f_rest_0..M-1."""
    # (an index longer than 6 digits cannot be an SH coefficient; avoid int() of huge strings)
    idx = sorted(int(m.group(1)) if len(m.group(1)) <= 6 else -1 for n in names if (m := _F_REST_RE.match(n)))
    m = len(idx)
    if idx != list(range(m)):
        raise PlyError(f"{path}: f_rest_* properties are not numbered 0..{m - 1} without gaps")
    for d in range(MAX_SH_DEGREE + 1):
        if m == 3 * (num_sh_bases(d) - 1):
            return d
    raise PlyError(f"{path}: {m} f_rest_* properties match no SH degree 0..{MAX_SH_DEGREE} (expected 0, 9, 24 or 45)")


def _check_vertex(path: Path, ply: plyfile.PlyData) -> tuple[plyfile.PlyElement, int]:
    """The vertex element and its SH degree, or a one-line refusal."""
    if "vertex" not in ply:
        names = ", ".join(e.name for e in ply.elements) or "none"
        raise PlyError(f"{path}: PLY file has no 'vertex' element (elements: {names}); not a Gaussian splat")
    vertex = ply["vertex"]
    names = [p.name for p in vertex.properties]
    if not any(n in names for n in _SPLAT_MARKERS):
        raise PlyError(f"{path}: a plain point cloud, not a Gaussian splat (no f_dc_0, opacity, scale_0 or rot_0 "
                       f"properties; it has {', '.join(names[:8]) or 'none'})")
    missing = [n for n in _REQUIRED if n not in names]
    if missing:
        raise PlyError(f"{path}: not a 3DGS splat: vertex properties missing: {', '.join(missing)}")
    d = _sh_layout(path, names)
    for n in _REQUIRED + [f"f_rest_{i}" for i in range(3 * (num_sh_bases(d) - 1))]:
        p = vertex.ply_property(n)
        if p.val_dtype not in ("f4", "f8"):
            ply_type = str(p).split()[1]  # "property uchar opacity" -> "uchar"
            raise PlyError(f"{path}: property {n!r} is {ply_type}; Gaussian parameters must be float or double")
    if vertex.count == 0:
        raise PlyError(f"{path}: the vertex element holds zero Gaussians")
    return vertex, d


def read_ply(path: str | os.PathLike, device: torch.device | str = "cpu") -> PlyRead:
    """Read a 3DGS .ply as raw Gaussians (float32 on `device`).

    Rows with NaN/Inf or an all-zero quaternion are dropped and counted in
    `num_dropped` (with a note); a file in which no valid row remains is refused.
    Raises PlyError (a SplatError and a ValueError) for anything else.
    """
    path = Path(path)
    ply = _read_plydata(path)
    vertex, d = _check_vertex(path, ply)
    table = vertex.data  # memory-mapped; the columns below are the only copies
    names = [p.name for p in vertex.properties]
    k = num_sh_bases(d)

    def cols(ns: list[str]) -> np.ndarray:  # [N, len(ns)] float32
        return np.stack([table[n].astype(np.float32, copy=False) for n in ns], axis=1)

    means = cols(["x", "y", "z"])
    dc = cols(["f_dc_0", "f_dc_1", "f_dc_2"])  # [N, 3]
    rest = cols([f"f_rest_{i}" for i in range(3 * (k - 1))]) if k > 1 else np.zeros((len(table), 0), np.float32)
    # channel-major on disk: [N, 3, K-1] -> [N, K-1, 3]
    rest = rest.reshape(len(table), 3, k - 1).transpose(0, 2, 1)
    sh = np.concatenate([dc[:, None, :], rest], axis=1)  # [N, K, 3]
    opac = table["opacity"].astype(np.float32)
    scales = cols(["scale_0", "scale_1", "scale_2"])
    quats = cols(["rot_0", "rot_1", "rot_2", "rot_3"])

    ok = (
        np.isfinite(means).all(1) & np.isfinite(sh.reshape(len(table), -1)).all(1) & np.isfinite(opac)
        & np.isfinite(scales).all(1) & np.isfinite(quats).all(1) & (np.abs(quats).sum(1) > 0)
    )
    n_bad = int((~ok).sum())
    notes: list[str] = []
    if n_bad == len(table):
        raise PlyError(f"{path}: none of its {len(table)} Gaussians is valid (all have NaN/Inf values or a zero quaternion)")
    if n_bad:
        notes.append(f"{path.name}: dropped {n_bad} of {len(table)} Gaussians with NaN/Inf values or a zero quaternion")
        means, sh, opac, scales, quats = means[ok], sh[ok], opac[ok], scales[ok], quats[ok]
    known = set(_REQUIRED) | set(_NORMALS) | {f"f_rest_{i}" for i in range(3 * (k - 1))}
    extra = [n for n in names if n not in known]
    if extra:
        shown = ", ".join(extra[:6]) + (f" and {len(extra) - 6} more" if len(extra) > 6 else "")
        notes.append(f"{path.name}: ignored extra vertex properties: {shown}")
    ignored_elements = [e.name for e in ply.elements if e is not vertex and e.count]
    if ignored_elements:
        notes.append(f"{path.name}: ignored PLY elements: {', '.join(ignored_elements)}")

    dev = torch.device(device)
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)).to(dev)  # noqa: E731
    g = Gaussians(means=t(means), quats=t(quats), log_scales=t(scales), opacity_logits=t(opac), sh=t(sh))
    return PlyRead(gaussians=g, sh_degree=d, num_vertices=int(len(table)), num_dropped=n_bad,
                   has_normals=all(n in names for n in _NORMALS), extra_properties=extra, notes=notes)
