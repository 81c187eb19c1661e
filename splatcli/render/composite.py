"""Per-pixel part of the forward model: alpha compositing of screen-space Gaussians,
with an analytic backward.

Layout. The image is cut into square pixel blocks of `block` px (4, 8 or 16; a
divisor of the 16 px tile, so each block lies in one tile). Every Gaussian is paired
with the blocks that hold a pixel centre inside both its tiles (the 16x16 tiles its
3-sigma square overlaps: the model's rule) and its alpha >= 1/255 ellipse (exact
culling: the model skips contributions below 1/255 anyway). Pairs are generated in
depth order and stably sorted by block. Blocks are processed in chunks of similar
list length K as dense [blocks, pixels, K] tensors (K last, so scans run along
contiguous memory):

    log2(alpha) = feats^T @ coef   one small GEMM: the exponent is a quadratic in the
                                   block-local pixel offset, coef [.., 6, K] per slot
    T           = cumprod(1 - alpha) along K (front to back), zeroed from the first
                  Gaussian that would take it below 1e-4
    colour      = [rgb, z, 1] @ (alpha T_before)^T   one batched GEMM; the row of
                  ones sums the weights, so T_final = 1 - sum w

Lists are cut into segments (`SEGMENT` long, longer when few blocks remain); after
each (every few on CUDA), blocks whose every pixel has stopped blending are dropped:
early termination.
Per-slot work (coefficients, gradient scatter) happens per segment for active blocks
only, so pairs behind saturated pixels cost only their planning.

The backward takes alpha and T of each segment from the forward (with its per-slot terms and
gathered rows), which keeps them up to KEEP_BYTES, and computes the rest again. It uses the 3DGS
identity for the colour behind a Gaussian, suffix_i = C_final - prefix_i, so it needs no
back-to-front pass. The per-slot gradient sums over pixels are again one GEMM
against the same six pixel features.

Chunks bound memory to O(chunk elements + pairs) plus what is kept; nothing here loops over pixels,
Gaussians or blocks individually (the Python loops run over chunks and segments).

The slots below 1/255 are evaluated, not skipped: compacting a segment to its surviving slots (a
nonzero, gathers, a segmented scan per pixel, one scatter into the pixels) took 10-16x the time of
the dense tail it would replace on trained fox and lego views (a Zen 4 EPYC; the nonzero alone cost
more than that whole tail), so every CPU runs the dense form.
"""

from __future__ import annotations

import collections
import math
import time
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from . import kernels, timing
from .blocks import CHUNKS, Meter
from .projection import TILE, Footprint

ALPHA_MIN = 1.0 / 255.0  # contributions below this are skipped
ALPHA_MAX = 0.99  # alpha is clamped to this
T_MIN = 1e-4  # a Gaussian that would bring transmittance below this is not blended, nor any after it
# [blocks, pixels, K] elements per chunk: bounds memory; the default where nothing measures it: the largest a
# tuner tries, its measured pick on most workloads of bench/peers.py on a Zen 3 EPYC (docs/benchmarks.md).
CHUNK_ELEMS = CHUNKS[-1]
_DEAD = -1e4  # log-opacity of the padding row: exp() is exactly 0
_LOG2E = 1.4426950408889634  # exp(x) = exp2(x log2 e); exp2 is the faster vectorised kernel
SEGMENT = 64  # Gaussians per block processed between early-termination checks
# ... with 4 px blocks: 16 pixels a block, so 64 slots made segments too short for their fixed cost
# (about 40 tensor ops); 256 measured 8-14% faster on lego and fox (Zen 3 EPYC), where 8 px blocks
# gained nothing from longer ones.
SEGMENT_4PX = 256
# The forward keeps alpha and transmittance [blocks, pixels, K] of its segments, up to this many bytes,
# so that the backward need not compute them again (the rest it does compute again). A training view at
# 480 px holds about 128 MB of them at most (fox at 8 px blocks); larger renders gain from more where recomputing is dear: on a
# 2-core Zen 1 EPYC (AVX2), one thread, taking turns, 512 MB against 128 MB took garden at 8 px blocks
# from 1,432 to 1,281 ms forward + backward and 100k Gaussians at 800x600 from 2,392 to 1,973 ms (the
# forward alone a few percent slower for what it writes). train/memory.py counts it (WORK_BYTES).
KEEP_BYTES = 512 << 20
# The backward adds its per-slot gradients into the per-Gaussian sums in one call once this many
# slots are pending, not segment by segment: between segments the dense work evicts the sums from
# the cache, and each call paid for it again (fox at 4 px blocks: 38-50 ms a backward, 13 ms batched).
SCATTER_SLOTS = 1 << 19
# What a render holds for and during its backward, at most, beyond its inputs (train/memory.py counts
# it): the kept segments, and the pending slots twice (each 10 gradients and an id, then concatenated).
WORK_BYTES = KEEP_BYTES + 2 * 48 * SCATTER_SLOTS
# On CUDA every early-termination test is a host sync (and every op a kernel launch): chunks 16x
# larger, segments 4x longer, and the test after every 4th segment only (skipping it is exact: a
# terminated or finished block only adds zeros). Not tuned on a GPU yet (docs/benchmarks.md).
CUDA_CHUNK_ELEMS = 1 << 22
CUDA_SEGMENT = 256
CUDA_TERMINATE_EVERY = 4


@dataclass
class Plan:
    """Which Gaussian touches which block, sorted by (block, depth). No gradients."""

    width: int
    height: int
    block: int  # block side, px
    nbx: int  # blocks per row
    nby: int  # blocks per column
    pair_gid: Tensor  # [M] int64 Gaussian index of each pair, sorted by (block, depth)
    block_start: Tensor  # [nblocks] int64 offset of each block's list in pair_gid
    block_count: Tensor  # [nblocks] int64 list length
    chunks: list[tuple[Tensor, int]]  # (block ids [nb], K) per chunk
    n_pairs: int  # M
    seg: int = SEGMENT  # K-segment length between early-termination checks
    chunk_elems: int = CHUNK_ELEMS  # dense elements per segment (segments grow as blocks terminate)
    terminate_every: int = 1  # segments between early-termination tests (each a host sync on CUDA)
    meter: Meter | None = None  # told the compositing backward's seconds (a BlockTuner's measurement)
    slots: tuple[int, list[Tensor]] | None = None  # (padding id, each chunk's slot ids): _slot_ids' cache


def _feats(block: int, dtype: torch.dtype, device: torch.device) -> Tensor:  # [6, P]
    """(1, lx, ly, lx^2, lx ly, ly^2) of each pixel centre relative to the block centre."""
    i = torch.arange(block, dtype=dtype, device=device) + 0.5 - block / 2
    ly, lx = torch.meshgrid(i, i, indexing="ij")
    lx, ly = lx.reshape(-1), ly.reshape(-1)
    return torch.stack([torch.ones_like(lx), lx, ly, lx * lx, lx * ly, ly * ly])


def make_plan(
    fp: Footprint,
    width: int,
    height: int,
    block: int = 8,
    rows: tuple[int, int] | None = None,
    chunk_elems: int | None = None,
    seg: int | None = None,
) -> Plan:
    """Pairs (Gaussian, block) for every block that holds a pixel centre inside both the
    Gaussian's tiles and its alpha >= 1/255 ellipse, sorted by (block, depth). `rows`
    (y0, y1), y0 a multiple of 16: the plan of that band of image rows alone, in the
    band's own pixel coordinates (rows y0.. become 0..).

    Enumeration is exact per block row: over a row band, the ellipse's x-extent is an
    interval whose ends are found in closed form (x given y is a 1D Gaussian with mean
    (b / c) dy and variance 1 / A), so corner blocks outside the ellipse never appear."""
    assert TILE % block == 0
    y0, y1 = rows or (0, height)
    assert y0 % TILE == 0
    nbx, nby = math.ceil(width / block), math.ceil((y1 - y0) / block)
    with torch.no_grad():
        by, bx0, ncol, rg = _block_rows_fast(fp.means2d, fp.cov2d, fp.vx, fp.opacities, fp.rect, width, y0, y1,
                                             block)
        M = int(ncol.sum())  # the pair count sizes what follows: between two compiled graphs
        pair_gid, start, count = _expand_fast(by, bx0, ncol, fp.gid.index_select(0, rg), nbx, nbx * nby, M)
        dseg, dchunk, every = device_settings(fp.gid.device, block)
        seg, chunk_elems = seg or dseg, chunk_elems or dchunk
        chunks = _schedule(count, block * block, chunk_elems, seg)
    return Plan(width, y1 - y0, block, nbx, nby, pair_gid, start, count, chunks, M, seg, chunk_elems, every)


def _block_rows(means2d: Tensor, cov2d: Tensor, vx: Tensor, opacities: Tensor, rect: Tensor, width: int, y0: int,
                y1: int, block: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """One entry per (Gaussian, block row) that the Gaussian reaches, from a footprint's columns:
    the block row, the first block column, the number of block columns, and the Gaussian's
    index in the footprint (each [R])."""
    dev = means2d.device
    f64, i64 = torch.float64, torch.int64
    # alpha >= 1/255  <=>  d^T Sigma'^-1 d <= 2 ln(255 o). Slightly generous margin:
    # the per-pixel test in the compositor is the exact one. The footprint holds the
    # rows where this is positive, in depth order.
    t2 = (2.0 * torch.log(torch.clamp_min(opacities * 255.0, 1e-30)) + 1e-3) * (1 + 1e-6)
    u, v = means2d.unbind(1)
    a, b, c = cov2d.unbind(1)
    rc = rect * TILE
    hy = torch.sqrt(t2 * c)
    # Pixel i is sampled at i + 0.5: inside [lo, hi] iff ceil(lo - .5) <= i <= floor(hi - .5).
    py0 = torch.maximum(torch.ceil(v - hy - 0.5), rc[:, 1].to(f64)).clamp_min(y0).to(i64) - y0
    py1 = torch.minimum(torch.floor(v + hy - 0.5), (rc[:, 3] - 1).to(f64)).clamp_max(y1 - 1).to(i64) - y0
    by0 = torch.div(py0, block, rounding_mode="floor")
    nrow = (torch.div(py1, block, rounding_mode="floor") - by0 + 1).clamp_min(0)
    nrow = torch.where(py1 >= py0, nrow, torch.zeros_like(nrow))
    # What each row of a Gaussian needs, one column per Gaussian (gathered once per row):
    # the mean (v in band coordinates), x | y's slope b / c and variance, the dy of the
    # ellipse's rightmost point, t2, c, the pixel rows and the tile columns.
    per = [u, v - y0, b / c, vx, torch.sqrt(t2 / a) * b, t2, c, py0.to(f64), py1.to(f64), rc[:, 0].to(f64),
           (rc[:, 2] - 1).to(f64)]
    rg = torch.repeat_interleave(torch.arange(u.numel(), device=dev), nrow)
    R = rg.numel()
    by = (by0 - (torch.cumsum(nrow, 0) - nrow)).index_select(0, rg) + torch.arange(R, device=dev)
    # (gathered column by column: one gather along dim 1 of an [11, N] tensor took 3x longer)
    ur, vr, kr, vxr, dys, t2r, cr, py0r, py1r, rx0, rx1 = (x.index_select(0, rg) for x in per)
    top = (by * block).to(f64)
    ylo = torch.maximum(top, py0r) + 0.5 - vr
    yhi = torch.minimum(top + (block - 1), py1r) + 0.5 - vr
    dmax = torch.minimum(torch.maximum(dys, ylo), yhi)
    dmin = torch.minimum(torch.maximum(-dys, ylo), yhi)
    xhi = ur + kr * dmax + torch.sqrt((vxr * (t2r - dmax * dmax / cr)).clamp_min(0))
    xlo = ur + kr * dmin - torch.sqrt((vxr * (t2r - dmin * dmin / cr)).clamp_min(0))
    px0 = torch.maximum(torch.ceil(xlo - 0.5), rx0).clamp_min(0).to(i64)
    px1 = torch.minimum(torch.floor(xhi - 0.5), rx1).clamp_max(width - 1).to(i64)
    bx0 = torch.div(px0, block, rounding_mode="floor")
    ncol = (torch.div(px1, block, rounding_mode="floor") - bx0 + 1).clamp_min(0)
    ncol = torch.where(px1 >= px0, ncol, torch.zeros_like(ncol))
    return by, bx0, ncol, rg


def _expand(by: Tensor, bx0: Tensor, ncol: Tensor, row_gid: Tensor, nbx: int, nblocks: int,
            M: int) -> tuple[Tensor, Tensor, Tensor]:
    """The block rows expanded to their M (Gaussian, block) pairs: pair_gid [M] sorted by (block,
    depth), and each block's start [nblocks] and count [nblocks] in it."""
    row = torch.repeat_interleave(ncol, output_size=M)  # [M] each pair's block row (built once, gathered twice)
    bid = (by * nbx + bx0 - (torch.cumsum(ncol, 0) - ncol)).index_select(0, row)
    bid += torch.arange(M, device=bid.device)
    # Pairs were generated in depth order: a stable sort by block alone gives
    # (block, depth) order; small integer keys sort fastest.
    kdt = torch.int16 if nblocks < 2**15 else (torch.int32 if nblocks < 2**31 else torch.int64)
    perm = torch.sort(bid.to(kdt), stable=True).indices
    pair_gid = row_gid.index_select(0, row).index_select(0, perm)
    count = torch.bincount(bid, minlength=nblocks)
    return pair_gid, torch.cumsum(count, 0) - count, count


# Compiled on the CPU when compiling is on: the same pairs (the integer bounds come from the same
# float64 arithmetic, and the planner's 1e-6 margin dwarfs any reordering of it). One Gaussian, one
# row or one pair stays eager: a size of 1 would compile a graph of its own.
_block_rows_fast = kernels.fast(_block_rows, lambda m, *_: m.device, lambda m, *_: m.shape[0] < 2)
_expand_fast = kernels.fast(_expand, lambda by, *_: by.device, lambda by, *a: by.numel() < 2 or a[-1] < 2)


def device_settings(device: torch.device, block: int = 8) -> tuple[int, int, int]:
    """(segment length, chunk elements, segments between early-termination tests) on `device`, for
    `block` px blocks."""
    if device.type == "cuda":
        return CUDA_SEGMENT, CUDA_CHUNK_ELEMS, CUDA_TERMINATE_EVERY
    return SEGMENT_4PX if block <= 4 else SEGMENT, CHUNK_ELEMS, 1


def _schedule(count: Tensor, P: int, chunk_elems: int, seg: int) -> list[tuple[Tensor, int]]:
    """Chunks of blocks with similar list lengths (longest first). A chunk's dense
    tensors are [blocks, P, min(K, seg)]; each holds about `chunk_elems` elements, and
    padding every list to the chunk's longest stays small."""
    nz = torch.nonzero(count).squeeze(1)
    if nz.numel() == 0:
        return []
    c, o = torch.sort(count[nz], descending=True)
    nz = nz[o]
    cl = c.tolist()
    out, s = [], 0
    while s < len(cl):
        k = cl[s]
        nb = max(1, chunk_elems // (min(k, seg) * P))
        out.append((nz[s : s + nb], k))
        s += nb
    return out


def _below(x: float, dtype: torch.dtype) -> float:
    """The largest value of `dtype` below x, so that `threshold(t > it)` means t >= x."""
    t = torch.tensor(x, dtype=dtype)
    return float(torch.nextafter(t, torch.zeros_like(t)))


class _Consts:
    def __init__(self, dtype: torch.dtype):
        self.a_min = _below(ALPHA_MIN, dtype)
        self.t_min = _below(T_MIN, dtype)
        # r = alpha / (1 - alpha) is r_max exactly where alpha was clamped to 0.99, and below it
        # elsewhere (1 - alpha is exact there, and the quotient grows with alpha).
        self.r_max = _ratio(ALPHA_MAX, dtype)


def _ratio(alpha: float, dtype: torch.dtype) -> float:
    """alpha / (1 - alpha) as the compositor computes it in `dtype`."""
    a = torch.tensor(alpha, dtype=dtype)
    return float(a / torch.rsub(a, 1.0))


class _Gauss:
    """Per-Gaussian rows (u, v, A, B, C, log o, r, g, b, z, 1), plus one padding row at index N
    (log o = -1e4: alpha exactly 0). A, B, C and log o are in log2 units (times log2 e), so that
    the exponent's coefficients need no scaling per slot (the backward divides the mean's
    gradient by log2 e once per Gaussian). The constant 1 makes the colour GEMM also sum the blending
    weights, which gives T_final = 1 - sum w for free. One table, so that a segment gathers its
    slots' rows once (one 11-wide gather costs about half of a 6-wide and a 5-wide one)."""

    def __init__(self, means2d, conics, opacities, colors, depths):
        logo = torch.log(torch.clamp_min(opacities, 1e-38)).masked_fill(opacities <= 0, _DEAD)
        ones = torch.ones_like(depths)[:, None]
        rows = torch.cat([means2d, conics * _LOG2E, logo[:, None] * _LOG2E, colors, depths[:, None], ones], 1)
        pad = rows.new_zeros(1, 11)
        pad[0, 5] = _DEAD
        self.rows = torch.cat([rows, pad], 0)  # [N + 1, 11]


def _gather(rows: Tensor, gid: Tensor) -> tuple[Tensor, Tensor]:  # -> [na, k, 6], [na, k, 5]
    """The slots' rows of a `_Gauss` table: (u, v, A, B, C, log o) and (r, g, b, z, 1)."""
    g = rows.index_select(0, gid.reshape(-1)).view(*gid.shape, 11)
    return g[..., :6], g[..., 6:]


def _coef(p: Tensor, centre: Tensor):  # p [na, k, 6] gathered rows; centre [na, 2]
    """The exponent's coefficients of one segment's slots.

    log(o G) is a quadratic in the block-local pixel offset l,
    c0 + gx lx + gy ly + qa lx^2 + qb lx ly + qc ly^2, with d0 = mean - block centre.
    Expanding around the block centre keeps the terms small where alpha matters: the
    large part of d0 lies along the ellipse's long axis, where Q d0 is small.
    Returns coef2 [na, 6, k] and (d0x, d0y, A, B, C, gx, gy), each [na, k]; all but d0 in log2
    units, as the table holds A, B, C and log o."""
    d0x = p[..., 0] - centre[:, 0:1]
    d0y = p[..., 1] - centre[:, 1:2]
    A, B, C = p[..., 2], p[..., 3], p[..., 4]
    coef2 = p.new_empty(d0x.shape[0], 6, d0x.shape[1])
    gx = torch.mul(A, d0x, out=coef2[:, 1]).addcmul_(B, d0y)
    gy = torch.mul(B, d0x, out=coef2[:, 2]).addcmul_(C, d0y)
    torch.mul(d0x, gx, out=coef2[:, 0]).addcmul_(d0y, gy).mul_(-0.5).add_(p[..., 5])
    torch.mul(A, -0.5, out=coef2[:, 3])
    torch.neg(B, out=coef2[:, 4])
    torch.mul(C, -0.5, out=coef2[:, 5])
    return coef2, (d0x, d0y, A, B, C, gx, gy)


def _slot_grads(q, R: Tensor, dcz: Tensor, out: Tensor) -> Tensor:  # R [na, 6, k], dcz [na, 4, k] -> out [10, na, k]
    """Chain rule from the per-slot pixel sums to (mean, conic, log o, colour, z), written into one
    [10, na, k] tensor with fused multiply-adds: these tensors are small, so the op count is the cost.
    A, B, C, gx and gy come in log2 units, so the mean's rows come log2 e times too large (the
    caller divides once per Gaussian).

        d mean = (A R1 + B R2 - gx R0,  B R1 + C R2 - gy R0)
        d A    = d0x (R1 - R0 d0x / 2) - R3 / 2
        d B    = d0y (R1 - R0 d0x) + d0x R2 - R4
        d C    = d0y (R2 - R0 d0y / 2) - R5 / 2
        d log o = R0"""
    d0x, d0y, A, B, C, gx, gy = q
    R0, R1, R2, R3, R4, R5 = R.unbind(1)
    torch.mul(A, R1, out=out[0]).addcmul_(B, R2).addcmul_(gx, R0, value=-1.0)
    torch.mul(B, R1, out=out[1]).addcmul_(C, R2).addcmul_(gy, R0, value=-1.0)
    hx = R0 * d0x
    torch.mul(d0x, torch.add(R1, hx, alpha=-0.5), out=out[2]).add_(R3, alpha=-0.5)
    torch.mul(d0y, R1 - hx, out=out[3]).addcmul_(d0x, R2).sub_(R4)
    torch.mul(d0y, torch.add(R2, R0 * d0y, alpha=-0.5), out=out[4]).add_(R5, alpha=-0.5)
    out[5].copy_(R0)
    out[6:].copy_(dcz.transpose(0, 1))
    return out


def _alpha(coef2: Tensor, featsT: Tensor, a_min: float) -> Tensor:  # [nb, P, k]
    """alpha = min(0.99, o G), zeroed below 1/255; coef2 [nb, 6, k] is in log2 units."""
    a = torch.matmul(featsT, coef2)  # [P, 6] @ [nb, 6, k]
    a.exp2_()
    F.threshold_(a, a_min, 0.0)
    return a.clamp_max_(ALPHA_MAX)


def _transmittance(alpha: Tensor, Tc: Tensor | None, t_min: float) -> tuple[Tensor, Tensor]:  # [na, P, k] each
    """r = alpha / (1 - alpha), and U = T after each Gaussian (Tc [na, P] the T entering, None: 1),
    zero from the first one that would bring T below 1e-4 (that one and all behind it are not
    blended). T entering is carried in the scan's first factor, which saves a pass over U. alpha
    becomes r (in place: a dense tensor written where it was read costs far less than a new one)."""
    om = torch.rsub(alpha, 1.0)
    r = alpha.div_(om)
    if Tc is not None:
        om[:, :, 0] *= Tc
    U = om.cumprod_(2)
    F.threshold_(U, t_min, 0.0)
    return r, U


def _median_weight(r: Tensor, U: Tensor) -> Tensor:  # [na, P, k] each
    """1 at the slot where transmittance crosses 0.5 (T_before = U (1 + r) > 0.5 >= T_after), else 0."""
    return ((torch.addcmul(U, U, r) > 0.5) & (U <= 0.5)).to(U.dtype)


def _seg_forward(rows: Tensor, gid: Tensor, centre: Tensor, featsT: Tensor, Tc: Tensor | None,
                 a_min: float, t_min: float, weight=None, kept: list | None = None,
                 sums: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor]:
    """One segment of the forward pass: rows [N + 1, 11] (`_Gauss`), gid [na, k]
    slot ids, centre [na, 2], featsT [P, 6], Tc [na, P] transmittance entering (None: 1). Returns
    the sums of a weight times (r, g, b, z, 1) per pixel [na, 5, P] and T after [na, P]: the blending
    weight alpha T_before (weight None: the picture), or weight(alpha / (1 - alpha), T after)
    (`_median_weight`: the median depth). `sums` (totals [N + 1], inside [na, P] 1 for the pixels
    in the image, 0 for a block's pixels past its edge): each slot's blending weight summed over its
    pixels is added into its Gaussian's total (`weight_sums`).
    `kept`: a list that r = alpha / (1 - alpha) and T after [na, P, k], the exponent terms (`_coef`)
    and the gathered (r, g, b, z, 1) rows are appended to, for the backward (blending weights only)."""
    p, czg = _gather(rows, gid)  # [na, k, 6], [na, k, 5]
    coef2, q = _coef(p, centre)
    r, U = _transmittance(_alpha(coef2, featsT, a_min), Tc, t_min)
    if timing.active():
        _count_slots(r, U, gid, rows.shape[0] - 1)
    if weight is not None:
        w = weight(r, U)
    else:
        w = r.mul_(U) if kept is None else r * U  # alpha T_before; 0 where not blended
        if kept is not None:
            kept.append((r, U, q, czg))
        if sums is not None:
            sums[0].index_add_(0, gid.reshape(-1), torch.bmm(sums[1].unsqueeze(1), w).reshape(-1))
    return torch.bmm(czg.transpose(1, 2), w.transpose(1, 2)), U[:, :, -1]


def _count_slots(r: Tensor, U: Tensor, gid: Tensor, pad: int) -> None:  # r, U [na, P, k], gid [na, k]
    """`train --profile`'s slot counts (render/timing.py) of one forward segment."""
    padding = int((gid == pad).sum()) * r.shape[1]
    zero = r == 0
    timing.add("slots", r.numel())
    timing.add("slots padding", padding)
    timing.add("slots below", int(zero.sum()) - padding)
    timing.add("slots ended", int(((U == 0) & ~zero).sum()))


def _seg_backward(rows: Tensor, gid: Tensor, centre: Tensor, feats: Tensor, featsT: Tensor,
                  Tc: Tensor | None, g4: Tensor, g4t: Tensor, base: Tensor, pc: Tensor | None, c: _Consts,
                  out: Tensor, saved: tuple | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """One segment of the backward pass, alpha and T recomputed: g4 [na, 4, P] and g4t [na, P, 4]
    the image gradient of (r, g, b, z), base [na, P] (see backward), pc [na, P] the prefix sum of
    w v over the earlier segments (None in the first). Writes d(u, v, A, B, C, log o, r, g, b, z) per slot into
    `out` [10, na, k] and returns it, T after [na, P] and the prefix sum after [na, P]. `saved`: the forward's alpha / (1 - alpha), T
    after, exponent terms and gathered (r, g, b, z, 1) rows for this segment (used up here), instead
    of computing them again."""
    if saved is not None:
        r, U, q, czg = saved
    else:
        p, czg = _gather(rows, gid)
        coef2, q = _coef(p, centre)
        r, U = _transmittance(_alpha(coef2, featsT, c.a_min), Tc, c.t_min)
    w = r * U
    czt = czg[..., :4].transpose(1, 2)  # [na, 4, k]
    v = torch.bmm(g4t, czt)  # [na, P, k]: g . (rgb, z) per slot
    ds = torch.bmm(g4, w)  # [na, 4, k]
    t = w.mul_(v)  # (w is not needed again)
    t[:, :, 0] += -base if pc is None else pc - base  # earlier segments' prefix - base, carried by the sums:
    t.cumsum_(2)  # (earlier segments' prefix + this one's prefix sums of w v) - base
    pc = t[:, :, -1] + base  # the prefix after this segment (t is edited in place below)
    # d loss / d power = alpha d loss / d alpha = r (U v - (base - prefix)) for
    # blended, unclamped alpha; 0 otherwise (indicators built without branches).
    t.addcmul_(U, v)
    Tlast = U[:, :, -1].clone()
    # -r where alpha was not clamped (r < r_max, r_max exactly where it was), else 0: one pass, where a
    # product of indicators took three; the sign is undone on the small sums below (exactly).
    t.mul_(F.threshold_(r.neg_(), -c.r_max, 0.0))
    dneg = t.mul_(U.sign_())  # -dpow: 0 where the slot was not blended (U is 0 from there on, else >= 1e-4)
    Rs = torch.matmul(feats, dneg).neg_()  # [na, 6, k]: sums of dpow * pixel features
    return _slot_grads(q, Rs, ds, out), Tlast, pc


def _seg_end(plan: Plan, k0: int, K: int, rows: int) -> int:
    """End of the segment starting at k0: `seg` long, or longer when so few blocks are
    still active that a segment's fixed cost (~40 tensor ops) would dominate. Longer
    segments check for early termination less often, hence only chunk_elems / 8."""
    P = plan.block * plan.block
    return min(K, k0 + max(plan.seg, plan.chunk_elems // max(8 * rows * P, 1)))


def _slot_ids(plan: Plan, n: int) -> list[Tensor]:
    """Gaussian id of every (block, k) slot of each chunk ([nb, K] per chunk, padding -> n), built
    once for the forward and the backward: one scatter of the pairs into the chunks' dense slots."""
    if plan.slots is not None and plan.slots[0] == n:
        return plan.slots[1]
    dev = plan.pair_gid.device
    nbs = [len(bl) for bl, _ in plan.chunks]
    if not nbs:
        return []
    ks = torch.tensor([K for _, K in plan.chunks], device=dev)
    nb_t = torch.tensor(nbs, device=dev)
    sizes = nb_t * ks
    offs = torch.cumsum(sizes, 0) - sizes  # each chunk's first slot
    row = torch.arange(sum(nbs), device=dev) - torch.repeat_interleave(torch.cumsum(nb_t, 0) - nb_t, nb_t)
    first = torch.repeat_interleave(offs, nb_t) + row * torch.repeat_interleave(ks, nb_t)  # each block's first slot
    shift = torch.zeros_like(plan.block_start)
    shift[torch.cat([bl for bl, _ in plan.chunks])] = first
    shift -= plan.block_start  # pair j of a block goes to slot j + shift
    pos = torch.repeat_interleave(shift, plan.block_count, output_size=plan.n_pairs)
    pos += torch.arange(plan.n_pairs, device=dev)
    dense = torch.full((int(sizes.sum()),), n, dtype=plan.pair_gid.dtype, device=dev)
    dense.index_copy_(0, pos, plan.pair_gid)
    out = [x.view(nb, K) for x, nb, (_, K) in zip(dense.split(sizes.tolist()), nbs, plan.chunks)]
    plan.slots = (n, out)
    return out


def _centres(plan: Plan, bl: Tensor, dtype: torch.dtype) -> Tensor:  # [nb, 2]
    """The pixel centres of blocks `bl`."""
    b = plan.block
    cx = (bl % plan.nbx) * b + b / 2
    cy = torch.div(bl, plan.nbx, rounding_mode="floor") * b + b / 2
    return torch.stack([cx, cy], -1).to(dtype)


def _rowsel(x: Tensor, act: Tensor | None) -> Tensor:
    return x if act is None else x.index_select(0, act)


def _terminate(act: Tensor | None, Tc: Tensor, more: Tensor, *carry: Tensor):
    """Early termination: drop the blocks whose every pixel has stopped blending, and
    those whose list has ended (`more` false): the rest of their slots are padding."""
    alive = (Tc.amax(1) > 0) & more
    if bool(alive.all()):
        return act, Tc, carry
    act = torch.nonzero(alive).squeeze(1) if act is None else act[alive]
    return act, Tc[alive], tuple(x[alive] for x in carry)


def _blend(plan: Plan, means2d: Tensor, conics: Tensor, opacities: Tensor, colors: Tensor, depths: Tensor,
           weight=None, kept: list | None = None, sums: Tensor | None = None) -> Tensor:  # [nblocks, 5, P]: sums of weight times (r, g, b, z, 1) per pixel
    """The forward pass over the plan's chunks and segments, each slot weighted by its blending
    weight (weight None: the picture) or `weight(alpha / (1 - alpha), T_after)` (the 0.5 crossing
    for the median depth). `kept`: a list that each segment's alpha / (1 - alpha), T after, exponent
    terms and gathered rows are appended to, in order, until they hold KEEP_BYTES (the backward computes
    the rest again). `sums` [N + 1]: each Gaussian's blending weight over the image's pixels is added
    into it."""
    dt, dev = means2d.dtype, means2d.device
    N = means2d.shape[0]
    P = plan.block * plan.block
    c = _Consts(dt)
    gs = _Gauss(means2d, conics, opacities, colors, depths)
    featsT = _feats(plan.block, dt, dev).T.contiguous()  # [P, 6]
    acc = torch.zeros(plan.nbx * plan.nby, 5, P, dtype=dt, device=dev)  # (r, g, b, depth, sum w)
    kept_bytes = 0
    inside = None if sums is None else _to_blocks(plan, means2d.new_ones(plan.height, plan.width, 1))[:, 0]  # [nblocks, P]
    for (bl, K), gid in zip(plan.chunks, _slot_ids(plan, N)):
        centre = _centres(plan, bl, dt)
        inside_bl = None if inside is None else inside.index_select(0, bl)
        cnt = plan.block_count.index_select(0, bl)  # [nb] list lengths
        out = None
        act, Tc = None, None
        k0 = nseg = 0
        while k0 < K:
            k1 = _seg_end(plan, k0, K, len(bl) if act is None else len(act))
            keep = kept if kept is not None and kept_bytes < KEEP_BYTES else None
            o, Tc = _seg_forward(gs.rows, _rowsel(gid, act)[:, k0:k1].contiguous(), _rowsel(centre, act), featsT,
                                 Tc, c.a_min, c.t_min, weight, keep,
                                 None if sums is None else (sums, _rowsel(inside_bl, act)))
            if keep is not None:
                kept_bytes += sum(x.numel() * x.element_size() for x in (*kept[-1][:2], *kept[-1][2], kept[-1][3]))
            if out is None:
                out = o
            elif act is None:
                out += o
            else:
                out.index_add_(0, act, o)
            nseg += 1
            if k1 < K and nseg % plan.terminate_every == 0:
                act, Tc, _ = _terminate(act, Tc, _rowsel(cnt, act) > k1)
                if act is not None and act.numel() == 0:
                    break
            k0 = k1
        acc[bl] = out
    return acc


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, planner, means2d, conics, opacities, colors, depths, background):
        # planner: a Plan, or a function that builds one. A function is called again in
        # backward instead of keeping the plan alive (memory-bounded banded renders).
        plan = planner() if callable(planner) else planner
        ctx.kept = [] if any(ctx.needs_input_grad[1:6]) and not callable(planner) else None  # (banded: memory first)
        acc = _blend(plan, means2d, conics, opacities, colors, depths, kept=ctx.kept)
        ctx.planner = planner
        ctx.save_for_backward(means2d, conics, opacities, colors, depths, background, acc)
        return _unblock(plan, acc, background)

    @staticmethod
    def backward(ctx, g_image, g_alpha, g_depth):
        t0 = time.perf_counter()
        plan: Plan = ctx.planner() if callable(ctx.planner) else ctx.planner
        means2d, conics, opacities, colors, depths, background, acc = ctx.saved_tensors
        dt, dev = means2d.dtype, means2d.device
        N = means2d.shape[0]
        c = _Consts(dt)
        gs = _Gauss(means2d, conics, opacities, colors, depths)
        feats = _feats(plan.block, dt, dev)  # [6, P]
        featsT = feats.T.contiguous()
        g4, gA = _block(plan, g_image, g_alpha, g_depth)  # [nblocks, 4, P], [nblocks, P]
        Tfin = 1.0 - acc[:, 4]
        # Per pixel: the colour+depth total g . acc (suffix sums come from it: 3DGS's
        # trick) plus d loss / d T_final = g . bg - g_alpha times T_final.
        base_all = (g4 * acc[:, :4]).sum(1) + Tfin * ((g4[:, :3] * background[:, None]).sum(1) - gA)
        g4t_all = g4.transpose(1, 2)  # [nblocks, P, 4]
        # d(u, v, A, B, C, log o, r, g, b, z), one row per quantity: index_add_ along dim 1 of [10, N + 1]
        # measured a little faster in place than accumulating rows of [N + 1, 10] (fox: 21 -> 20 ms a backward).
        dg = torch.zeros(10, N + 1, dtype=dt, device=dev)
        slots = _slot_ids(plan, N)
        pend = _Pending(dg, sum(x.numel() for x in slots))
        kept, ctx.kept = collections.deque(ctx.kept or ()), None  # used up (edited in place): a second backward computes them again
        for (bl, K), gid in zip(plan.chunks, slots):
            centre = _centres(plan, bl, dt)
            g4b, g4tb = g4.index_select(0, bl), g4t_all.index_select(0, bl).contiguous()  # [nb, 4, P], [nb, P, 4]
            base = base_all.index_select(0, bl)  # [nb, P]
            cnt = plan.block_count.index_select(0, bl)  # [nb] list lengths
            act, Tc, pc = None, None, None
            k0 = nseg = 0
            while k0 < K:
                k1 = _seg_end(plan, k0, K, len(bl) if act is None else len(act))
                gid_s = _rowsel(gid, act)[:, k0:k1].contiguous()
                _, Tc, pc = _seg_backward(gs.rows, gid_s, _rowsel(centre, act), feats, featsT, Tc, _rowsel(g4b, act),
                                          _rowsel(g4tb, act), _rowsel(base, act), pc, c, pend.take(gid_s),
                                          kept.popleft() if kept else None)  # (freed as the backward goes)
                nseg += 1
                if k1 < K and nseg % plan.terminate_every == 0:
                    act, Tc, (pc,) = _terminate(act, Tc, _rowsel(cnt, act) > k1, pc)
                    if act is not None and act.numel() == 0:
                        break
                k0 = k1
        pend.flush()
        dg = dg[:, :N]
        dg[:2] /= _LOG2E  # (_Gauss: A, B, C in log2 units)
        d_opac = dg[5] / opacities.clamp_min(1e-38)  # d log o -> d o; 0 for pair-less Gaussians
        d_bg = None
        if ctx.needs_input_grad[6]:
            d_bg = (g_image * _to_image(plan, Tfin[:, None])[..., 0:1]).sum((0, 1))
        dt = time.perf_counter() - t0
        timing.add("compositing backward", dt)
        if plan.meter is not None:
            plan.meter.add(dt, last=True)
        return None, dg[:2].T, dg[2:5].T, d_opac, dg[6:9].T, dg[9], d_bg


class _Pending:
    """Per-slot gradients not yet added into dg [10, N + 1]: segments write theirs into one buffer
    of SCATTER_SLOTS slots (no concatenation), added in one call when it is full and at the end. index_add_
    along dim 1 of [10, N + 1] was the fastest form timed (a Xeon, 550,000 random slots into 29,000 Gaussians:
    6.7 ms; scatter_add_ the same; index_add_ on a transposed [N + 1, 10], ten 1-D index_add_ or ten weighted
    bincounts 10-13 ms)."""

    def __init__(self, dg: Tensor, slots: int):  # slots: how many the backward will write, at most
        self.dg, self.n, self.cap = dg, 0, max(1, min(SCATTER_SLOTS, slots))
        self.big: tuple[Tensor, Tensor] | None = None  # a segment larger than the buffer: (ids, gradients)
        self.ids = torch.empty(self.cap, dtype=torch.int64, device=dg.device)
        self.vals = dg.new_empty(10, self.cap)

    def take(self, gid: Tensor) -> Tensor:  # gid [na, k] -> [10, na, k] to write the slots' gradients into
        """Room for one segment's gradients, whose slots hold the Gaussians `gid`."""
        S = gid.numel()
        if self.n + S > self.cap:
            self.flush()
        if S > self.cap:  # added on the next flush, on its own
            self.big = (gid.reshape(-1), self.vals.new_empty(10, S))
            return self.big[1].view(10, *gid.shape)
        self.ids[self.n : self.n + S] = gid.reshape(-1)
        out = self.vals[:, self.n : self.n + S].view(10, *gid.shape)
        self.n += S
        return out

    def flush(self) -> None:
        if self.n:
            self.dg.index_add_(1, self.ids[: self.n], self.vals[:, : self.n])
            self.n = 0
        if self.big is not None:
            self.dg.index_add_(1, *self.big)
            self.big = None


def _to_image(plan: Plan, x: Tensor) -> Tensor:  # [nblocks, C, P] -> [H, W, C]
    b, C = plan.block, x.shape[1]
    img = x.reshape(plan.nby, plan.nbx, C, b, b).permute(0, 3, 1, 4, 2).reshape(plan.nby * b, plan.nbx * b, C)
    return img[: plan.height, : plan.width]


def _to_blocks(plan: Plan, img: Tensor) -> Tensor:  # [H, W, C] -> [nblocks, C, P]
    b, C = plan.block, img.shape[-1]
    Hp, Wp = plan.nby * b, plan.nbx * b
    pad = img.new_zeros(Hp, Wp, C)
    pad[: plan.height, : plan.width] = img
    return pad.reshape(plan.nby, b, plan.nbx, b, C).permute(0, 2, 4, 1, 3).reshape(-1, C, b * b).contiguous()


def _unblock(plan: Plan, acc: Tensor, background: Tensor):
    a = _to_image(plan, acc)
    T = 1.0 - a[..., 4]
    image = a[..., :3] + T[..., None] * background
    return image.contiguous(), (1.0 - T).contiguous(), a[..., 3].contiguous()


def _block(plan: Plan, g_image, g_alpha, g_depth):
    H, W = plan.height, plan.width
    ref = g_image if g_image is not None else (g_alpha if g_alpha is not None else g_depth)
    z = lambda *s: torch.zeros(*s, dtype=ref.dtype, device=ref.device)  # noqa: E731
    gi = g_image if g_image is not None else z(H, W, 3)
    ga = g_alpha if g_alpha is not None else z(H, W)
    gd = g_depth if g_depth is not None else z(H, W)
    g5 = _to_blocks(plan, torch.cat([gi, gd[..., None], ga[..., None]], -1))
    return g5[:, :4].contiguous(), g5[:, 4].contiguous()


def composite(
    plan,  # Plan, or a function returning one (rebuilt in backward instead of kept)
    means2d: Tensor,  # [N, 2] px
    conics: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    colors: Tensor,  # [N, 3]
    depths: Tensor,  # [N]
    background: Tensor,  # [3]
) -> tuple[Tensor, Tensor, Tensor]:  # image [H, W, 3], alpha [H, W], depth [H, W]
    return _Composite.apply(plan, means2d, conics, opacities, colors, depths, background)


@torch.no_grad()
def median_depth(plan: Plan, means2d: Tensor, conics: Tensor, opacities: Tensor, depths: Tensor) -> Tensor:  # [H, W]
    """Per pixel, the depth of the Gaussian at which transmittance falls through 0.5 (0 where
    it never does): a surface depth more stable than the blended mean (2DGS; meshing)."""
    zeros = depths.new_zeros(depths.shape[0], 3)
    return _to_image(plan, _blend(plan, means2d, conics, opacities, zeros, depths, _median_weight))[..., 3]


@torch.no_grad()
def weight_sums(plan: Plan, means2d: Tensor, conics: Tensor, opacities: Tensor) -> Tensor:  # [N]
    """Each Gaussian's blending weight alpha T_before summed over the plan's pixels, from the forward
    pass alone (the gradient of the picture with respect to its colour is the same sum, at the cost
    of a backward)."""
    n = means2d.shape[0]
    sums = means2d.new_zeros(n + 1)  # (the padding slots add into the last)
    zeros = means2d.new_zeros(n, 3)
    _blend(plan, means2d, conics, opacities, zeros, zeros[:, 0], sums=sums)
    return sums[:n]
