"""SuperSplat's compressed PLY (`.compressed.ply`), read by the PlayCanvas viewers.

Written from the layout SuperSplat and splat-transform publish. A binary little-endian
PLY with three elements:

    chunk   one per 256 Gaussians: float min/max of x, y, z, of the log scales, and of
            the DC colours (SH_C0 * dc + 0.5), 18 floats
    vertex  uint packed_position  x, y, z in 11, 10, 11 bits, within the chunk's box
            uint packed_rotation  smallest three of (w, x, y, z): the index of the
                                  largest in the top 2 bits, then 3 x 10 bits of
                                  c / sqrt 2 + 0.5 (the largest made positive)
            uint packed_scale     log scales in 11, 10, 11 bits within the chunk's range
            uint packed_color     R, G, B within the chunk's range and sigmoid(opacity), 8 bits each
    sh      optional, uchar f_rest_0 ... (channel-major as in the 3DGS .ply):
            byte = trunc((c / 8 + 0.5) * 256)

Gaussians are written in Morton (Z-curve) order, so each chunk covers a small box.
The frame is the .ply's (OpenCV), so nothing is flipped.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import torch

from ..files.atomic import atomic_write_bytes
from ..gaussians import SH_C0, Gaussians, morton_order
from .codec import Arrays, blocks, logit, pack_smallest_three, refuse, sigmoid, unpack_smallest_three

CHUNK = 256
CHUNK_PROPS = ["min_x", "min_y", "min_z", "max_x", "max_y", "max_z",
               "min_scale_x", "min_scale_y", "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z",
               "min_r", "min_g", "min_b", "max_r", "max_g", "max_b"]
VERTEX_PROPS = ["packed_position", "packed_rotation", "packed_scale", "packed_color"]
MAX_HEADER = 64 * 1024


def _unorm(x: np.ndarray, bits: int) -> np.ndarray:
    t = (1 << bits) - 1
    return np.clip(np.floor(x * t + 0.5), 0, t).astype(np.uint32)


def _chunked(v: np.ndarray, n_chunks: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """v [C*256, D] -> each chunk's range lo, hi [C, D], and v within it in [0, 1] (0 where the range is empty)."""
    c = v.reshape(n_chunks, CHUNK, -1)
    lo, hi = c.min(1), c.max(1)
    span = (hi - lo)[:, None]
    out = np.where(span < 1e-5, 0.0, (c - lo[:, None]) / np.where(span < 1e-5, 1.0, span))
    return lo, hi, np.clip(out, 0.0, 1.0).reshape(v.shape)


def encode_compressed_ply(g: Gaussians) -> tuple[bytes, int]:
    """The .compressed.ply bytes of the finite rows of `g`, and the number dropped."""
    a, dropped = Arrays.of(g)
    n = len(a)
    order = morton_order(torch.from_numpy(a.means)).numpy() if n else np.zeros(0, np.int64)
    n_chunks = (n + CHUNK - 1) // CHUNK
    pad = np.concatenate([order, np.full(n_chunks * CHUNK - n, order[-1] if n else 0, np.int64)])  # repeat the last
    means, ls = a.means[pad], np.clip(a.log_scales[pad], -20.0, 20.0)
    rgb = a.sh[pad, 0] * SH_C0 + 0.5
    alpha = sigmoid(a.opacity_logits[pad])
    pmin, pmax, p = _chunked(means, n_chunks)
    smin, smax, s = _chunked(ls, n_chunks)
    cmin, cmax, c = _chunked(rgb, n_chunks)
    position = _unorm(p[:, 0], 11) << 21 | _unorm(p[:, 1], 10) << 11 | _unorm(p[:, 2], 11)
    scale = _unorm(s[:, 0], 11) << 21 | _unorm(s[:, 1], 10) << 11 | _unorm(s[:, 2], 11)
    color = _unorm(c[:, 0], 8) << 24 | _unorm(c[:, 1], 8) << 16 | _unorm(c[:, 2], 8) << 8 | _unorm(alpha, 8)
    big, rest = pack_smallest_three(a.quats[pad])
    rotation = big.astype(np.uint32)
    for j in range(3):
        rotation = (rotation << 10) | _unorm(rest[:, j] / np.sqrt(2.0) + 0.5, 10)
    vertex = np.stack([position, rotation, scale, color], axis=1)[:n].astype("<u4")
    chunks = np.concatenate([pmin, pmax, smin, smax, cmin, cmax], axis=1).astype("<f4")
    k = a.sh.shape[1]
    header = ["ply", "format binary_little_endian 1.0", "comment splatcli compressed ply",
              f"element chunk {n_chunks}", *[f"property float {x}" for x in CHUNK_PROPS],
              f"element vertex {n}", *[f"property uint {x}" for x in VERTEX_PROPS]]
    parts = [chunks.tobytes(), vertex.tobytes()]
    if k > 1:
        header += [f"element sh {n}", *[f"property uchar f_rest_{i}" for i in range((k - 1) * 3)]]
        packed = np.empty((n, (k - 1) * 3), np.uint8)
        for b in blocks(n):
            rest_sh = a.sh[order[b], 1:].transpose(0, 2, 1).reshape(-1, (k - 1) * 3)  # channel-major, as f_rest
            packed[b] = np.clip(np.trunc((rest_sh / 8.0 + 0.5) * 256.0), 0, 255)
        parts.append(packed.tobytes())
    head = ("\n".join(header + ["end_header"]) + "\n").encode("ascii")
    return head + b"".join(parts), dropped


def write_compressed_ply(path: str | os.PathLike, g: Gaussians) -> tuple[int, int, int]:
    """Write `g` as .compressed.ply (atomically): (rows written, rows dropped, bytes)."""
    data, dropped = encode_compressed_ply(g)
    atomic_write_bytes(path, data)
    return len(g) - dropped, dropped, len(data)


def is_compressed_ply(path: str | os.PathLike) -> bool:
    """Whether a .ply file is the compressed layout (its header names a chunk element)."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return False
    end = head.find(b"end_header")
    return head.startswith(b"ply") and b"element chunk" in head[:end if end > 0 else None]


def _header(raw: bytes, path: Path) -> tuple[list[tuple[str, int, list[tuple[str, str]]]], int]:
    end = raw.find(b"end_header\n", 0, MAX_HEADER)
    if not raw.startswith(b"ply\n") or end < 0:
        raise refuse(path, "not a PLY file (no header)")
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    for line in raw[:end].decode("ascii", "replace").splitlines()[1:]:
        parts = line.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "format":
            if parts[1:2] != ["binary_little_endian"]:
                raise refuse(path, f"compressed PLY must be binary_little_endian, not {' '.join(parts[1:])}")
        elif parts[0] == "element" and len(parts) == 3 and re.fullmatch(r"\d{1,10}", parts[2]):
            elements.append((parts[1], int(parts[2]), []))
        elif parts[0] == "property" and len(parts) == 3 and elements:
            elements[-1][2].append((parts[1], parts[2]))
        else:
            raise refuse(path, f"unexpected PLY header line {line.strip()[:60]!r}")
    return elements, end + len(b"end_header\n")


def read_compressed_ply(path: str | os.PathLike, device: torch.device | str = "cpu") -> Gaussians:
    """A compressed .ply as Gaussians. A truncated, garbled or lying file is refused
    in one line before anything is allocated beyond its real size."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise refuse(path, f"cannot read ({exc.strerror or exc})") from None
    elements, offset = _header(raw, path)
    by = {name: (count, props) for name, count, props in elements}
    if [e[0] for e in elements][:2] != ["chunk", "vertex"] or set(by) - {"chunk", "vertex", "sh"}:
        raise refuse(path, f"expected elements chunk, vertex[, sh], found {', '.join(e[0] for e in elements)}")
    n_chunks, cprops = by["chunk"]
    n, vprops = by["vertex"]
    cnames = [p[1] for p in cprops]
    if cnames not in (CHUNK_PROPS, CHUNK_PROPS[:12]) or any(t != "float" for t, _ in cprops):
        raise refuse(path, "chunk properties are not the compressed-PLY layout")
    if [p[1] for p in vprops] != VERTEX_PROPS or any(t != "uint" for t, _ in vprops):
        raise refuse(path, "vertex properties are not packed_position/rotation/scale/color (uint)")
    if n_chunks != (n + CHUNK - 1) // CHUNK:
        raise refuse(path, f"{n_chunks} chunks cannot hold {n} Gaussians in chunks of {CHUNK}")
    n_sh, sh_props = by.get("sh", (0, []))
    if "sh" in by and (n_sh != n or len(sh_props) not in (9, 24, 45) or any(t != "uchar" for t, _ in sh_props)):
        raise refuse(path, f"sh element of {n_sh} rows x {len(sh_props)} properties does not fit {n} Gaussians")
    sizes = [n_chunks * len(cnames) * 4, n * 16, n_sh * len(sh_props)]
    if len(raw) - offset < sum(sizes):
        raise refuse(path, f"truncated: {len(raw) - offset:,} bytes of data, the header promises {sum(sizes):,}")
    chunks = np.frombuffer(raw, "<f4", n_chunks * len(cnames), offset).reshape(n_chunks, -1).astype(np.float64)
    v = np.frombuffer(raw, "<u4", n * 4, offset + sizes[0]).reshape(n, 4)
    ci = np.arange(n) // CHUNK
    unorm = lambda x, bits: (x & ((1 << bits) - 1)).astype(np.float64) / ((1 << bits) - 1)  # noqa: E731
    lerp = lambda lo, hi, t: lo[ci] + (hi[ci] - lo[ci]) * t  # noqa: E731

    def three(packed: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        t = np.stack([unorm(packed >> 21, 11), unorm(packed >> 11, 10), unorm(packed, 11)], axis=1)
        return lerp(lo, hi, t)

    means = three(v[:, 0], chunks[:, 0:3], chunks[:, 3:6])
    log_scales = three(v[:, 2], chunks[:, 6:9], chunks[:, 9:12])
    rest = np.stack([unorm(v[:, 1] >> 20, 10), unorm(v[:, 1] >> 10, 10), unorm(v[:, 1], 10)], axis=1)
    quats = unpack_smallest_three((v[:, 1] >> 30).astype(np.int64), (rest - 0.5) * np.sqrt(2.0))
    c = v[:, 3]
    rgb = np.stack([unorm(c >> 24, 8), unorm(c >> 16, 8), unorm(c >> 8, 8)], axis=1)
    if len(cnames) == 18:
        rgb = lerp(chunks[:, 12:15], chunks[:, 15:18], rgb)
    k = 1 + len(sh_props) // 3
    sh = np.zeros((n, k, 3), np.float32)
    sh[:, 0] = (rgb - 0.5) / SH_C0
    if k > 1:
        raw_sh = np.frombuffer(raw, np.uint8, n * len(sh_props), offset + sizes[0] + sizes[1]).reshape(n, -1)
        for blk in blocks(n):
            b = raw_sh[blk]
            t = np.where(b == 0, 0.0, np.where(b == 255, 1.0, (b.astype(np.float32) + 0.5) / 256.0)).astype(np.float32)
            sh[blk, 1:] = ((t - 0.5) * 8.0).reshape(-1, 3, k - 1).transpose(0, 2, 1)
    opac = logit(unorm(c, 8), 0.5 / 255.0)
    return Arrays(means, quats, log_scales, opac, sh).gaussians(device)
