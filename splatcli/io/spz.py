"""Niantic's SPZ (`.spz`), versions 2 and 3 read, version 3 written.

Written from the published specification (nianticlabs/spz, docs): one gzip stream
holding a 16-byte header and then attribute arrays, each for every Gaussian in turn:

    header     <u32 magic 0x5053474e ("NGSP"), u32 version, u32 count, u8 SH degree,
               u8 fractional bits, u8 flags (bit 0: antialiased), u8 reserved 0
    positions  3 x 24-bit signed fixed point, value = int / 2^fractional_bits
    alphas     u8 sigmoid(opacity) * 255
    colours    3 x u8 (SH DC * 0.15 + 0.5) * 255
    scales     3 x u8 (log scale + 10) * 16
    rotations  v3: u32 smallest three of (x, y, z, w): top 2 bits the index of the
               largest (dropped, made positive), then per kept component (in x, y, z, w
               order, highest bits first) a sign bit and 9 bits of |c| * 511 * sqrt 2;
               v2: 3 x u8 of (x, y, z) * 127.5 + 127.5 with w >= 0
    SH         per Gaussian, per coefficient (degrees 1-3, 3DGS order), R, G, B:
               u8 round(c * 128 + 128), rounded to multiples of 2^(8 - bits)
               (SpzOptions: 6 bits for degree 1 and 5 above by default; the reference
               encoder's 5 and 4 lose twice as much; any readers decode either)

SPZ stores the right-up-back frame; splatcli's is OpenCV's right-down-front, so
y and z change sign (positions, rotations and the SH bands they flip). Version 4
(per-attribute zstd streams) is refused with a one-line reason.
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

from ..gaussians import Gaussians
from .atomic import atomic_write_bytes
from .codec import (
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
HEADER = struct.Struct("<IIIBBBB")
COLOR_SCALE = 0.15
XYZW = (1, 2, 3, 0)  # positions of x, y, z, w in (w, x, y, z)
COMPRESS_LEVEL = 6  # zlib default; 9 is many times slower on quantised SH runs for <1% smaller files
MAX_RATIO = 1100  # deflate expands at most ~1032x: a larger claimed payload is a lie


@dataclass(frozen=True)
class SpzOptions:
    # Bits per SH coefficient of degree 1, and of degrees 2-3. The reference encoder's 5 and 4
    # cost 0.54 dB on the demo scene (12.4x smaller than .ply); 6 and 5 cost 0.23 dB (9.9x),
    # 7 and 6 0.11 dB (8.0x), 8 and 8 0.01 dB (6.3x): docs/benchmarks.md, "formats".
    sh1_bits: int = 6
    sh_rest_bits: int = 5
    fractional_bits: int | None = None  # None: the most the scene's extent allows (at most 16; the reference uses 12)


def _quantise_sh(v: np.ndarray, bits: int) -> np.ndarray:
    q = np.round(v * 128.0 + 128.0)
    step = 2 ** (8 - bits)
    return np.clip(np.floor((q + step / 2) / step) * step, 0, 255).astype(np.uint8)


def encode_spz(g: Gaussians, options: SpzOptions = SpzOptions()) -> tuple[bytes, int]:
    """The .spz bytes of the finite rows of `g`, and the number of rows dropped."""
    a, dropped = Arrays.of(g)
    a = a.flip_yz(sh=False)  # the SH bands are flipped block by block below
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
    rotations = comp.astype("<u4")
    parts = [HEADER.pack(MAGIC, 3, n, deg, fb, 0, 0), positions.tobytes(), alphas.tobytes(), colors.tobytes(),
             scales.tobytes(), rotations.tobytes()]
    if deg > 0:
        sh = np.empty((n, a.sh.shape[1] - 1, 3), np.uint8)
        for b in blocks(n):
            v = flip_sh(a.sh[b].copy())
            sh[b, :3] = _quantise_sh(v[:, 1:4], options.sh1_bits)
            sh[b, 3:] = _quantise_sh(v[:, 4:], options.sh_rest_bits)
        parts.append(sh.tobytes())
    return gzip.compress(b"".join(parts), compresslevel=COMPRESS_LEVEL, mtime=0), dropped


def write_spz(path: str | os.PathLike, g: Gaussians, options: SpzOptions = SpzOptions()) -> tuple[int, int, int]:
    """Write `g` as .spz (atomically): (rows written, rows dropped, bytes)."""
    data, dropped = encode_spz(g, options)
    atomic_write_bytes(path, data)
    return len(g) - dropped, dropped, len(data)


def read_spz(path: str | os.PathLike, device: torch.device | str = "cpu") -> Gaussians:
    """A .spz file (versions 2 and 3) as Gaussians in splatcli's frame. A truncated,
    garbled or lying file is a one-line SplatError; memory stays within the payload
    the file can really hold."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise refuse(path, f"cannot read ({exc.strerror or exc})") from None
    if raw[:4] == b"NGSP":
        raise refuse(path, "SPZ version 4 (zstd streams) is not supported; "
                     "convert it with `splat-transform --spz-version 3 IN OUT.spz`")
    if raw[:2] != b"\x1f\x8b":
        raise refuse(path, "not an SPZ file (no gzip stream)")
    d = zlib.decompressobj(wbits=31)
    try:
        head = d.decompress(raw, HEADER.size)
    except zlib.error as exc:
        raise refuse(path, f"damaged SPZ stream ({exc})") from None
    if len(head) < HEADER.size:
        raise refuse(path, "truncated SPZ header")
    magic, version, n, deg, fb, _flags, _ = HEADER.unpack(head)
    if magic != MAGIC:
        raise refuse(path, f"not an SPZ file (magic {magic:#x})")
    if version not in (2, 3):
        raise refuse(path, f"SPZ version {version} is not supported (2 and 3 are)")
    k = check_sh_degree(deg, path)
    rot_bytes = 4 if version == 3 else 3
    per = 9 + 1 + 3 + 3 + rot_bytes + (k - 1) * 3
    need = n * per
    if need > MAX_RATIO * len(raw) + 1024:
        raise refuse(path, f"claims {n:,} Gaussians, more than its {len(raw):,} bytes can hold")
    try:
        body = d.decompress(d.unconsumed_tail, need + 1)
    except zlib.error as exc:
        raise refuse(path, f"damaged SPZ stream ({exc})") from None
    if len(body) < need:
        raise refuse(path, f"truncated: {len(body):,} of {need:,} bytes of Gaussian data for {n:,} Gaussians")
    buf = np.frombuffer(body, np.uint8, need)
    o = 0

    def take(size: int) -> np.ndarray:
        nonlocal o
        out = buf[o:o + n * size].reshape(n, size)
        o += n * size
        return out

    pos = take(9).reshape(n, 3, 3).astype(np.int32)
    fixed = pos[..., 0] | (pos[..., 1] << 8) | (pos[..., 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    means = fixed.astype(np.float64) / 2.0 ** fb
    alphas = take(1)[:, 0].astype(np.float64) / 255.0
    colors = take(3).astype(np.float64)
    log_scales = take(3).astype(np.float64) / 16.0 - 10.0
    rot = take(rot_bytes)
    if version == 3:
        comp = rot.astype(np.uint32)
        comp = comp[:, 0] | (comp[:, 1] << 8) | (comp[:, 2] << 16) | (comp[:, 3] << 24)
        rest = np.zeros((n, 3))
        for j in (2, 1, 0):  # lowest bits hold the last kept component
            v = (comp & 511).astype(np.float64) / 511.0 / np.sqrt(2.0)
            rest[:, j] = np.where((comp >> 9) & 1, -v, v)
            comp = comp >> 10
        quats = unpack_smallest_three((comp & 3).astype(np.int64), rest, XYZW)
    else:
        xyz = rot.astype(np.float64) / 127.5 - 1.0
        w = np.sqrt(np.clip(1.0 - (xyz ** 2).sum(1), 0.0, None))
        quats = np.concatenate([w[:, None], xyz], axis=1)
    sh = np.zeros((n, k, 3), np.float32)
    sh[:, 0] = (colors / 255.0 - 0.5) / COLOR_SCALE
    if k > 1:
        raw_sh = take((k - 1) * 3).reshape(n, k - 1, 3)
        for b in blocks(n):
            sh[b, 1:] = (raw_sh[b].astype(np.float32) - 128.0) / 128.0
            flip_sh(sh[b])
    a = Arrays(means, quats, log_scales, logit(alphas, 0.5 / 255.0), sh).flip_yz(sh=False)
    return a.gaussians(device)
