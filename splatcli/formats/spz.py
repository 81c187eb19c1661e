"""Niantic's SPZ (`.spz`): versions 2, 3 and 4 read, 3 written (4 on request).

Written from the published specification (nianticlabs/spz, README). Versions 2 and 3 are
one gzip stream holding a 16-byte header, the attribute arrays and then, where flag 2 is
set, extension records (Niantic's library's legacy layout); version 4 is a 32-byte
plaintext header, extension records, a table of contents and one zstd stream per array
(the SH stream absent at degree 0):

    header v2/3  <u32 magic 0x5053474e ("NGSP"), u32 version, u32 count, u8 SH degree,
                 u8 fractional bits, u8 flags (1: antialiased, 2: extensions), u8 0
    header v4    the same to the flags, then u8 streams, u32 TOC offset, 12 zero bytes;
                 extension records <u32 type, u32 bytes, payload> up to the TOC; the TOC
                 <u64 compressed, u64 uncompressed> per stream
    extensions   v2/3: the same records, after the SH array, to the end of the stream
    positions    3 x 24-bit signed fixed point, value = int / 2^fractional_bits
    alphas       u8 sigmoid(opacity) * 255
    colours      3 x u8 (SH DC * 0.15 + 0.5) * 255
    scales       3 x u8 (log scale + 10) * 16
    rotations    v3, v4: u32 smallest three of (x, y, z, w): top 2 bits the index of the
                 largest (dropped, made positive), then per kept component (in x, y, z, w
                 order, highest bits first) a sign bit and 9 bits of |c| * 511 * sqrt 2;
                 v2: 3 x u8 of (x, y, z) * 127.5 + 127.5 with w >= 0
    SH           per Gaussian, per coefficient (degrees 1-3, 3DGS order), R, G, B:
                 u8 round(c * 128 + 128), rounded to multiples of 2^(8 - bits)
                 (SpzOptions: 6 bits for degree 1 and 5 above by default; the reference
                 encoder's 5 and 4 lose more; any readers decode either)

The frame. Niantic's README says SPZ stores right-up-back (RUB) unless a writer says
otherwise, but the tools that write it today store the .ply's right-down-front (RDF)
values unchanged: Niantic's own ply_to_spz (default, unspecified frames) and PlayCanvas
splat-transform 3.x, whose reader also takes every file as it is (2.x converted to RUB
both ways, as splatcli did), and so does Spark 2.2 (docs/benchmarks.md, "formats"). So both versions are
written in RDF, splatcli's frame, and say so with the SPZ_ADOBE_coordinate_system
extension (0xADBE0003, CoordinateSystem RDF = 6; in version 3 after the arrays, flag 2,
as Niantic's library writes it there, and which splat-transform 3.7 reads past): raw
readers and readers of the extension both get it right. Version 3 is the default because
Spark 2.2, the renderer of splatcli's viewer, reads no version 4; version 4 is a little
smaller. Read: that extension's frame where a file has it (the axis-sign frames, 1-8;
the z-up ones are refused), else RDF for version 4 (what its writers store, and how
splat-transform 3.x and Niantic's tools read it) and RUB for versions 2 and 3 (the
specification's frame, which Scaniverse, splat-transform 2.x and splatcli before the
extension wrote). Files that break the rule read upside down, here as in splat-transform
3.x: splat-transform 3.x's version 3 (raw RDF, no extension) and 2.x's version 4 (RUB,
no extension; May-July 2026).
"""

from __future__ import annotations

import gzip
import os
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import zstandard

from ..files.atomic import atomic_write_bytes
from ..gaussians import Gaussians
from .codec import (
    MAX_RATIO,
    Arrays,
    blocks,
    check_sh_degree,
    flip_sh,
    logit,
    pack_smallest_three,
    refuse,
    sigmoid,
    unpack_smallest_three,
)

MAGIC = 0x5053474E
HEADER = struct.Struct("<IIIBBBB")  # versions 2 and 3, inside the gzip stream
HEADER4 = struct.Struct("<IIIBBBBI12x")  # version 4, plaintext: ... u8 streams, u32 TOC offset
RECORD = struct.Struct("<II")  # an extension's type and payload bytes
HAS_EXTENSIONS = 0x2
COORDINATE_SYSTEM = 0xADBE0003  # SPZ_ADOBE_coordinate_system: one u32 of Niantic's CoordinateSystem
RUB, RDF = 4, 6  # CoordinateSystem (spz src/cc/splat-types.h): 1-8 are LDB, RDB, LUB, RUB, LDF, RDF, LUF, RUF
ZSTD_LEVEL = 12  # the reference encoder's
COLOR_SCALE = 0.15
XYZW = (1, 2, 3, 0)  # positions of x, y, z, w in (w, x, y, z)
COMPRESS_LEVEL = 6  # zlib default; 9 is many times slower on quantised SH runs for barely smaller files


@dataclass(frozen=True)
class SpzOptions:
    # Bits per SH coefficient of degree 1, and of degrees 2-3: 6 and 5 lose much less than the
    # reference encoder's 5 and 4 for a somewhat larger file; more bits cost size for little
    # gain (docs/benchmarks.md, "formats").
    sh1_bits: int = 6
    sh_rest_bits: int = 5
    fractional_bits: int | None = None  # None: the most the scene's extent allows (at most 16; the reference uses 12)
    version: int = 3  # 3: one gzip stream (Spark 2.2 reads no 4); 4: zstd streams, smaller. Both RDF, declared


def _quantise_sh(v: np.ndarray, bits: int) -> np.ndarray:
    q = np.round(v * 128.0 + 128.0)
    step = 2 ** (8 - bits)
    return np.clip(np.floor((q + step / 2) / step) * step, 0, 255).astype(np.uint8)


def encode_spz(g: Gaussians, options: SpzOptions = SpzOptions()) -> tuple[bytes, int]:
    """The .spz bytes of the finite rows of `g`, and the number of rows dropped."""
    a, dropped = Arrays.of(g)
    n, deg = len(a), a.sh_degree
    span = float(np.abs(a.means).max()) if n else 1.0
    fb = options.fractional_bits
    if fb is None:
        fb = int(np.clip(np.floor(np.log2((2 ** 23 - 1) / max(span, 1e-9))), 0, 16))
    fixed = np.clip(np.round(a.means * 2.0 ** fb), -(2 ** 23 - 1), 2 ** 23 - 1).astype("<i4")
    positions = fixed.view(np.uint8).reshape(n, 3, 4)[:, :, :3]
    alphas = np.round(sigmoid(a.opacity_logits) * 255.0).astype(np.uint8)
    colors = np.clip(np.round((a.sh[:, 0] * COLOR_SCALE + 0.5) * 255.0), 0, 255).astype(np.uint8)
    scales = np.clip(np.round((a.log_scales + 10.0) * 16.0), 0, 255).astype(np.uint8)
    big, rest = pack_smallest_three(a.quats, XYZW)
    mag = np.clip(np.round(np.abs(rest) * np.sqrt(2.0) * 511.0), 0, 511).astype(np.uint32)
    comp = big.astype(np.uint32)
    for j in range(3):
        comp = (comp << 10) | ((rest[:, j] < 0).astype(np.uint32) << 9) | mag[:, j]
    parts = [positions.tobytes(), alphas.tobytes(), colors.tobytes(), scales.tobytes(), comp.astype("<u4").tobytes()]
    if deg > 0:
        sh = np.empty((n, a.sh.shape[1] - 1, 3), np.uint8)
        for b in blocks(n):
            sh[b, :3] = _quantise_sh(a.sh[b, 1:4], options.sh1_bits)
            sh[b, 3:] = _quantise_sh(a.sh[b, 4:], options.sh_rest_bits)
        parts.append(sh.tobytes())
    ext = RECORD.pack(COORDINATE_SYSTEM, 4) + struct.pack("<I", RDF)  # the frame: ours, unchanged
    if options.version == 3:  # Niantic's legacy layout: the extension records after the arrays, flag 2
        body = HEADER.pack(MAGIC, 3, n, deg, fb, HAS_EXTENSIONS, 0) + b"".join(parts) + ext
        return gzip.compress(body, compresslevel=COMPRESS_LEVEL, mtime=0), dropped
    zc = zstandard.ZstdCompressor(level=ZSTD_LEVEL)
    streams = [(zc.compress(p), len(p)) for p in parts if p]  # none empty unless n == 0
    toc = b"".join(struct.pack("<QQ", len(z), size) for z, size in streams)
    head = HEADER4.pack(MAGIC, 4, n, deg, fb, HAS_EXTENSIONS, len(streams), HEADER4.size + len(ext))
    return b"".join([head, ext, toc] + [z for z, _ in streams]), dropped


def write_spz(path: str | os.PathLike, g: Gaussians, options: SpzOptions = SpzOptions()) -> tuple[int, int, int]:
    """Write `g` as .spz (atomically): (rows written, rows dropped, bytes)."""
    data, dropped = encode_spz(g, options)
    atomic_write_bytes(path, data)
    return len(g) - dropped, dropped, len(data)


def read_spz(path: str | os.PathLike, device: torch.device | str = "cpu") -> Gaussians:
    """A .spz file (versions 2-4) as Gaussians in splatcli's frame. A truncated,
    garbled or lying file is a one-line SplatError; memory stays within the payload
    the file can really hold."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise refuse(path, f"cannot read ({exc.strerror or exc})") from None
    if raw[:4] == b"NGSP":
        version, n, fb, arrays, system = _unpack_v4(path, raw)
    elif raw[:2] == b"\x1f\x8b":
        version, n, fb, arrays, system = _unpack_gzip(path, raw)
    else:
        raise refuse(path, "not an SPZ file (no gzip stream or NGSP header)")
    s = _signs(path, system)
    pos, alpha, color, scale, rot, sh_bytes = arrays
    pos = pos.reshape(n, 3, 3).astype(np.int32)
    fixed = pos[..., 0] | (pos[..., 1] << 8) | (pos[..., 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    means = fixed.astype(np.float64) / 2.0 ** fb
    alphas = alpha.astype(np.float64) / 255.0
    log_scales = scale.reshape(n, 3).astype(np.float64) / 16.0 - 10.0
    if version >= 3:
        comp = rot.view("<u4").astype(np.uint32)
        rest = np.zeros((n, 3))
        for j in (2, 1, 0):  # lowest bits hold the last kept component
            v = (comp & 511).astype(np.float64) / 511.0 / np.sqrt(2.0)
            rest[:, j] = np.where((comp >> 9) & 1, -v, v)
            comp = comp >> 10
        quats = unpack_smallest_three((comp & 3).astype(np.int64), rest, XYZW)
    else:
        xyz = rot.reshape(n, 3).astype(np.float64) / 127.5 - 1.0
        w = np.sqrt(np.clip(1.0 - (xyz ** 2).sum(1), 0.0, None))
        quats = np.concatenate([w[:, None], xyz], axis=1)
    k = 1 + len(sh_bytes) // (3 * n) if n else 1
    sh = np.zeros((n, k, 3), np.float32)
    sh[:, 0] = (color.reshape(n, 3).astype(np.float64) / 255.0 - 0.5) / COLOR_SCALE
    if k > 1:
        raw_sh = sh_bytes.reshape(n, k - 1, 3)
        for b in blocks(n):
            sh[b, 1:] = (raw_sh[b].astype(np.float32) - 128.0) / 128.0
            flip_sh(sh[b], s)
    a = Arrays(means, quats, log_scales, logit(alphas, 0.5 / 255.0), sh).flip(s, sh=False)
    return a.gaussians(device)


def _sizes(version: int, n: int, k: int) -> list[int]:
    """Bytes of positions, alphas, colours, scales, rotations and SH for `n` Gaussians of `k` SH bases."""
    return [9 * n, n, 3 * n, 3 * n, (4 if version >= 3 else 3) * n, (k - 1) * 3 * n]


def _unpack_gzip(path: Path, raw: bytes) -> tuple[int, int, int, list[np.ndarray], int | None]:
    """Versions 2 and 3: (version, count, fractional bits, the six arrays, the frame an extension declares)."""
    d = zlib.decompressobj(wbits=31)
    try:
        head = d.decompress(raw, HEADER.size)
    except zlib.error as exc:
        raise refuse(path, f"damaged SPZ stream ({exc})") from None
    if len(head) < HEADER.size:
        raise refuse(path, "truncated SPZ header")
    magic, version, n, deg, fb, flags, _ = HEADER.unpack(head)
    if magic != MAGIC:
        raise refuse(path, f"not an SPZ file (magic {magic:#x})")
    if version not in (2, 3):
        raise refuse(path, f"SPZ version {version} is not supported (2, 3 and 4 are)")
    sizes = _sizes(version, n, check_sh_degree(deg, path))
    need = sum(sizes)
    if need > MAX_RATIO * len(raw) + 1024:
        raise refuse(path, f"claims {n:,} Gaussians, more than its {len(raw):,} bytes can hold")
    try:
        body = d.decompress(d.unconsumed_tail, need)
        # Niantic's library puts extension records after the arrays (flag 2)
        tail = d.decompress(d.unconsumed_tail, 1 << 16) if flags & HAS_EXTENSIONS else b""
    except zlib.error as exc:
        raise refuse(path, f"damaged SPZ stream ({exc})") from None
    if len(body) < need:
        raise refuse(path, f"truncated: {len(body):,} of {need:,} bytes of Gaussian data for {n:,} Gaussians")
    buf = np.frombuffer(body, np.uint8)
    arrays = np.split(buf, np.cumsum(sizes)[:-1])
    return version, n, fb, arrays, _declared(path, tail)


def _unpack_v4(path: Path, raw: bytes) -> tuple[int, int, int, list[np.ndarray], int | None]:
    """Version 4: as _unpack_gzip; each zstd stream is read to at most the size its count allows."""
    if len(raw) < HEADER4.size:
        raise refuse(path, "truncated SPZ header")
    _, version, n, deg, fb, flags, count, toc_at = HEADER4.unpack_from(raw)
    if version != 4:
        raise refuse(path, f"SPZ version {version} with an NGSP header is not supported (4 is)")
    sizes = _sizes(4, n, check_sh_degree(deg, path))
    if 9 * n > MAX_RATIO * len(raw):
        raise refuse(path, f"claims {n:,} Gaussians, more than its {len(raw):,} bytes can hold")
    want = [size for size in sizes if size]  # a writer leaves out empty streams (SH at degree 0)
    if count != len(want):
        raise refuse(path, f"{count} attribute streams, not the {len(want)} of SH degree {deg}")
    start = toc_at + 16 * count
    if toc_at < HEADER4.size or start > len(raw):
        raise refuse(path, f"truncated or damaged table of contents (at byte {toc_at:,} of {len(raw):,})")
    toc = struct.unpack_from(f"<{2 * count}Q", raw, toc_at)
    packed, unpacked = toc[0::2], list(toc[1::2])
    if unpacked != want:
        raise refuse(path, f"stream sizes {unpacked} do not fit {n:,} Gaussians of SH degree {deg} ({want})")
    if sum(packed) != len(raw) - start:
        raise refuse(path, f"truncated: its streams claim {sum(packed):,} bytes, {len(raw) - start:,} follow the table")
    streams, o, view = [], start, memoryview(raw)
    for c, size in zip(packed, want):
        try:  # read to one byte past the size: a frame claiming more is never allocated
            out = zstandard.ZstdDecompressor().stream_reader(view[o:o + c], read_across_frames=True).read(size + 1)
        except zstandard.ZstdError as exc:
            raise refuse(path, f"damaged SPZ stream ({exc})") from None
        if len(out) != size:
            raise refuse(path, f"damaged SPZ stream ({len(out):,} bytes where its table says {size:,})")
        streams.append(np.frombuffer(out, np.uint8))
        o += c
    it = iter(streams)
    arrays = [next(it) if size else np.zeros(0, np.uint8) for size in sizes]
    return 4, n, fb, arrays, _declared(path, raw[HEADER4.size:toc_at] if flags & HAS_EXTENSIONS else b"", RDF)


def _declared(path: Path, zone: bytes, default: int = RUB) -> int:
    """The CoordinateSystem the extension records in `zone` declare (others are skipped), else `default`."""
    o, system = 0, default
    while o < len(zone):
        if o + RECORD.size > len(zone) or o + RECORD.size + RECORD.unpack_from(zone, o)[1] > len(zone):
            raise refuse(path, f"damaged extension records (one runs past byte {len(zone):,} of their zone)")
        kind, size = RECORD.unpack_from(zone, o)
        if kind == COORDINATE_SYSTEM and size >= 4:
            system = struct.unpack_from("<I", zone, o + RECORD.size)[0]
        o += RECORD.size + size
    return system


def _signs(path: Path, system: int) -> tuple[float, float, float]:
    """The axis signs from Niantic's CoordinateSystem `system` to splatcli's RDF (0, unspecified, is RUB)."""
    i = (system or RUB) - 1
    if not 0 <= i < 8:
        raise refuse(path, f"coordinate system {system} (z up, or unknown) is not supported; "
                     "convert the file to a right-up-back or right-down-front one")
    return (1.0 if i & 1 else -1.0, -1.0 if i & 2 else 1.0, 1.0 if i & 4 else -1.0)
