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
order, float or double, either endianness, other elements before or after the
vertices, extra properties (ignored, with a note) and unnormalised quaternions.
It refuses, in one line, anything that is not a Gaussian splat: a plain point
cloud, a truncated file, a header claiming more vertices than the file holds.
It never allocates more than the file's actual size implies.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..errors import SplatError
from ..gaussians import Gaussians, num_sh_bases
from .atomic import atomic_write_with

MAX_SH_DEGREE = 3
MAX_HEADER_BYTES = 1 << 20  # a 3DGS header is ~1.5 KB; anything past 1 MiB is not a splat
MAX_PROPERTIES = 4096

# PLY scalar type names (both spellings) -> numpy type codes, without byte order.
_PLY_TYPES = {
    "char": "i1", "int8": "i1",
    "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4",
    "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}
_FLOAT_CODES = ("f4", "f8")
_FORMATS = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": None}
_F_REST_RE = re.compile(r"^f_rest_(\d+)$")
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
    rows = torch.cat(
        [cpu(g.means), torch.zeros(n, 3), dc, rest, cpu(g.opacity_logits), cpu(g.log_scales), cpu(g.quats)],
        dim=1,
    )
    return rows.numpy()


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

    def _write(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            f.write(header)
            rows.tofile(f)

    atomic_write_with(path, _write)
    return PlyWriteResult(path=path, num_written=int(rows.shape[0]), num_dropped=dropped, sh_degree=d,
                          bytes=len(header) + rows.nbytes)


# ---------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class PlyProperty:
    name: str
    code: str  # numpy type code without byte order: "f4", "u1", ...; "list" for list properties
    ply_type: str  # as written in the header


@dataclass(frozen=True)
class PlyElement:
    name: str
    count: int
    properties: tuple[PlyProperty, ...]

    def has_list(self) -> bool:
        return any(p.code == "list" for p in self.properties)

    def dtype(self, order: str) -> np.dtype:
        return np.dtype([(p.name, order + p.code) for p in self.properties])


@dataclass(frozen=True)
class PlyHeader:
    path: Path
    format: str  # binary_little_endian | binary_big_endian | ascii
    elements: tuple[PlyElement, ...]
    header_bytes: int  # offset of the body
    file_bytes: int

    def element(self, name: str) -> PlyElement | None:
        for e in self.elements:
            if e.name == name:
                return e
        return None


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


def read_ply_header(path: str | os.PathLike) -> PlyHeader:
    """Parse and check the header; reads at most MAX_HEADER_BYTES."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if path.is_dir():
            raise PlyError(f"{path}: is a directory, not a .ply file")
        with open(path, "rb") as f:
            head = f.read(min(size, MAX_HEADER_BYTES) if size else MAX_HEADER_BYTES)
    except FileNotFoundError:
        raise PlyError(f"{path}: no such file") from None
    except PlyError:
        raise
    except OSError as exc:
        raise PlyError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if not head.startswith(b"ply\n") and not head.startswith(b"ply\r\n"):
        raise PlyError(f"{path}: not a PLY file (it does not start with 'ply')")
    m = re.search(rb"(?:^|\n)end_header\r?\n", head)
    if m is None:
        raise PlyError(f"{path}: PLY header has no end_header within {len(head)} bytes (truncated or not a PLY file)")
    header_bytes = m.end()
    try:
        text = head[:header_bytes].decode("ascii")
    except UnicodeDecodeError:
        raise PlyError(f"{path}: PLY header contains non-ASCII bytes") from None

    fmt: str | None = None
    elements: list[tuple[str, int, list[PlyProperty]]] = []
    n_props = 0
    for lineno, raw in enumerate(text.splitlines()[1:], start=2):
        words = raw.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        key = words[0]
        if key == "end_header":
            break
        if key == "format":
            if len(words) != 3 or words[1] not in _FORMATS:
                raise PlyError(f"{path}: unknown PLY format line {raw.strip()!r} (line {lineno})")
            if fmt is not None:
                raise PlyError(f"{path}: PLY header has two format lines")
            fmt = words[1]
        elif key == "element":
            if len(words) != 3 or not words[2].isdigit() or len(words[2]) > 18:
                raise PlyError(f"{path}: bad PLY element line {raw.strip()!r} (line {lineno})")
            elements.append((words[1], int(words[2]), []))
        elif key == "property":
            if not elements:
                raise PlyError(f"{path}: PLY property before any element (line {lineno})")
            n_props += 1
            if n_props > MAX_PROPERTIES:
                raise PlyError(f"{path}: PLY header declares more than {MAX_PROPERTIES} properties")
            if len(words) == 5 and words[1] == "list":
                if words[2] not in _PLY_TYPES or words[3] not in _PLY_TYPES:
                    raise PlyError(f"{path}: unknown PLY type in {raw.strip()!r} (line {lineno})")
                elements[-1][2].append(PlyProperty(words[4], "list", " ".join(words[1:4])))
            elif len(words) == 3 and words[1] in _PLY_TYPES:
                elements[-1][2].append(PlyProperty(words[2], _PLY_TYPES[words[1]], words[1]))
            else:
                raise PlyError(f"{path}: bad PLY property line {raw.strip()!r} (line {lineno})")
        else:
            raise PlyError(f"{path}: unknown PLY header line {raw.strip()!r} (line {lineno})")
    if fmt is None:
        raise PlyError(f"{path}: PLY header has no format line")
    els = []
    for name, count, props in elements:
        names = [p.name for p in props]
        if len(set(names)) != len(names):
            dup = sorted({n for n in names if names.count(n) > 1})
            raise PlyError(f"{path}: PLY element {name!r} declares property {dup[0]!r} twice")
        els.append(PlyElement(name, count, tuple(props)))
    return PlyHeader(path=path, format=fmt, elements=tuple(els), header_bytes=header_bytes, file_bytes=size)


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
    raise PlyError(
        f"{path}: {m} f_rest_* properties match no SH degree 0..{MAX_SH_DEGREE} "
        f"(expected 0, 9, 24 or 45)"
    )


def _check_vertex(path: Path, header: PlyHeader) -> tuple[PlyElement, int]:
    """The vertex element and its SH degree, or a one-line refusal."""
    vertex = header.element("vertex")
    if vertex is None:
        names = ", ".join(e.name for e in header.elements) or "none"
        raise PlyError(f"{path}: PLY file has no 'vertex' element (elements: {names}); not a Gaussian splat")
    names = [p.name for p in vertex.properties]
    if not any(n in names for n in _SPLAT_MARKERS):
        raise PlyError(
            f"{path}: a plain point cloud, not a Gaussian splat "
            f"(no f_dc_0, opacity, scale_0 or rot_0 properties; it has {', '.join(names[:8]) or 'none'})"
        )
    missing = [n for n in _REQUIRED if n not in names]
    if missing:
        raise PlyError(f"{path}: not a 3DGS splat: vertex properties missing: {', '.join(missing)}")
    d = _sh_layout(path, names)
    by_name = {p.name: p for p in vertex.properties}
    for n in _REQUIRED + [f"f_rest_{i}" for i in range(3 * (num_sh_bases(d) - 1))]:
        p = by_name[n]
        if p.code not in _FLOAT_CODES:
            raise PlyError(f"{path}: property {n!r} is {p.ply_type}; Gaussian parameters must be float or double")
    if vertex.count == 0:
        raise PlyError(f"{path}: the vertex element holds zero Gaussians")
    return vertex, d


def _load_vertex_table(header: PlyHeader, vertex: PlyElement) -> np.ndarray:
    """The vertex rows as a structured array, reading only what the file holds."""
    path = header.path
    if header.format == "ascii":
        raise PlyError(f"{path}: ASCII PLY is not supported for splats; write binary_little_endian")
    order = "<" if header.format == "binary_little_endian" else ">"
    offset = header.header_bytes
    for e in header.elements:
        if e is vertex:
            break
        if e.count and e.has_list():
            raise PlyError(f"{path}: element {e.name!r} before the vertices has list properties; cannot locate the vertices")
        offset += e.count * e.dtype(order).itemsize
    if vertex.has_list():
        bad = next(p.name for p in vertex.properties if p.code == "list")
        raise PlyError(f"{path}: vertex property {bad!r} is a list; Gaussian splats have scalar properties only")
    dtype = vertex.dtype(order)
    need = vertex.count * dtype.itemsize
    have = header.file_bytes - offset
    if need > have:
        raise PlyError(
            f"{path}: header claims {vertex.count} vertices ({need} bytes) but the file holds only "
            f"{max(have, 0)} bytes after the header (truncated file or lying header)"
        )
    try:
        with open(path, "rb") as f:
            f.seek(offset)
            table = np.fromfile(f, dtype=dtype, count=vertex.count)
    except OSError as exc:
        raise PlyError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if table.shape[0] != vertex.count:  # the file shrank under us
        raise PlyError(f"{path}: file ended after {table.shape[0]} of {vertex.count} vertices")
    return table


def read_ply(path: str | os.PathLike, device: torch.device | str = "cpu") -> PlyRead:
    """Read a 3DGS .ply as raw Gaussians (float32 on `device`).

    Rows with NaN/Inf or an all-zero quaternion are dropped and counted in
    `num_dropped` (with a note); a file in which no valid row remains is refused.
    Raises PlyError (a SplatError and a ValueError) for anything else.
    """
    path = Path(path)
    header = read_ply_header(path)
    vertex, d = _check_vertex(path, header)
    table = _load_vertex_table(header, vertex)
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
    ignored_elements = [e.name for e in header.elements if e is not vertex and e.count]
    if ignored_elements:
        notes.append(f"{path.name}: ignored PLY elements: {', '.join(ignored_elements)}")

    dev = torch.device(device)
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)).to(dev)  # noqa: E731
    g = Gaussians(means=t(means), quats=t(quats), log_scales=t(scales), opacity_logits=t(opac), sh=t(sh))
    return PlyRead(
        gaussians=g,
        sh_degree=d,
        num_vertices=int(len(table)),
        num_dropped=n_bad,
        has_normals=all(n in names for n in _NORMALS),
        extra_properties=extra,
        notes=notes,
    )
