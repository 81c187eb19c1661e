"""Per-pixel part of the forward model: alpha compositing of screen-space Gaussians,
with an analytic backward.

Layout. The image is cut into square pixel blocks of `block` px (4, 8 or 16; a
divisor of the 16 px tile, so each block lies in one tile). Every Gaussian is paired
with the blocks that intersect both its tiles (the 16x16 tiles its 3-sigma square
overlaps: the model's rule) and the bounding box of its alpha >= 1/255 ellipse
(exact culling: contributions below 1/255 are skipped by the model anyway). Pairs are
sorted by (block, depth) with one integer key. Blocks are then processed in chunks
of similar list length K as dense [blocks, K, pixels] tensors:

    log(alpha) = coef @ feats      one small GEMM: the exponent is a quadratic in the
                                   block-local pixel offset, coef [.., 6] per pair
    T          = cumprod(1 - alpha) along K (front to back)
    colour     = (alpha T)^T @ [rgb, z]   one batched GEMM

The backward recomputes alpha and T per chunk (cheaper than storing them: they are
the largest tensors) and uses the 3DGS identity for the colour behind a Gaussian,
suffix_i = C_final - prefix_i, so it needs no back-to-front pass. The per-pair
gradient sums over pixels are again one GEMM against the same six pixel features.

Chunks bound memory to O(chunk elements + pairs); nothing here loops over pixels,
Gaussians or blocks individually.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from .project import TILE

ALPHA_MIN = 1.0 / 255.0  # contributions below this are skipped
ALPHA_MAX = 0.99  # alpha is clamped to this
T_MIN = 1e-4  # a Gaussian that would bring transmittance below this is not blended, nor any after it
CHUNK_ELEMS = 1 << 18  # [blocks, pixels, K] elements per chunk: bounds memory, stays in cache (measured: 2^18 best of 2^16..2^21)
_DEAD = -1e4  # log-opacity of the padding row: exp() is exactly 0
_LOG2E = 1.4426950408889634  # exp(x) = exp2(x log2 e); exp2 is the faster vectorised kernel
SEGMENT = 64  # Gaussians per block processed between early-termination checks


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


def _feats(block: int, dtype: torch.dtype, device: torch.device) -> Tensor:  # [6, P]
    """(1, lx, ly, lx^2, lx ly, ly^2) of each pixel centre relative to the block centre."""
    i = torch.arange(block, dtype=dtype, device=device) + 0.5 - block / 2
    ly, lx = torch.meshgrid(i, i, indexing="ij")
    lx, ly = lx.reshape(-1), ly.reshape(-1)
    return torch.stack([torch.ones_like(lx), lx, ly, lx * lx, lx * ly, ly * ly])


def make_plan(
    means2d: Tensor,  # [N, 2] px
    cov2d: Tensor,  # [N, 3] (a, b, c) px^2, incl. blur
    opacities: Tensor,  # [N]
    depths: Tensor,  # [N]
    rect: Tensor,  # [N, 4] int64 tile rect (tx0, ty0, tx1, ty1), exclusive ends
    active: Tensor,  # [N] bool
    width: int,
    height: int,
    block: int = 8,
    chunk_elems: int | None = None,
    seg: int | None = None,
) -> Plan:
    assert TILE % block == 0
    dev = means2d.device
    nbx, nby = math.ceil(width / block), math.ceil(height / block)
    nblocks = nbx * nby
    with torch.no_grad():
        o = opacities.detach().to(torch.float64)
        # alpha >= 1/255  <=>  d^T Sigma'^-1 d <= 2 ln(255 o). Slightly generous margin:
        # the per-pixel test in the compositor is the exact one.
        t2 = 2.0 * torch.log(torch.clamp_min(o * 255.0, 1e-30)) + 1e-3
        act = active & (t2 > 0)
        idx = torch.nonzero(act).squeeze(1)
        m = means2d.detach()[idx].to(torch.float64)
        cv = cov2d.detach()[idx].to(torch.float64)
        t = torch.sqrt(t2[idx]) * (1 + 1e-6)
        hx, hy = t * torch.sqrt(cv[:, 0]), t * torch.sqrt(cv[:, 2])
        rc = rect[idx]
        # Pixel i is sampled at i + 0.5: inside [lo, hi] iff ceil(lo - .5) <= i <= floor(hi - .5).
        x0 = torch.maximum(torch.ceil(m[:, 0] - hx - 0.5), (rc[:, 0] * TILE).to(torch.float64)).clamp_min(0)
        x1 = torch.minimum(torch.floor(m[:, 0] + hx - 0.5), (rc[:, 2] * TILE - 1).to(torch.float64)).clamp_max(width - 1)
        y0 = torch.maximum(torch.ceil(m[:, 1] - hy - 0.5), (rc[:, 1] * TILE).to(torch.float64)).clamp_min(0)
        y1 = torch.minimum(torch.floor(m[:, 1] + hy - 0.5), (rc[:, 3] * TILE - 1).to(torch.float64)).clamp_max(height - 1)
        keep = (x1 >= x0) & (y1 >= y0)
        idx, x0, x1, y0, y1 = idx[keep], x0[keep], x1[keep], y0[keep], y1[keep]
        bx0 = torch.div(x0.to(torch.int64), block, rounding_mode="floor")
        bx1 = torch.div(x1.to(torch.int64), block, rounding_mode="floor")
        by0 = torch.div(y0.to(torch.int64), block, rounding_mode="floor")
        by1 = torch.div(y1.to(torch.int64), block, rounding_mode="floor")
        # Depth order (stable: ties keep index order, as in the reference).
        order = torch.argsort(depths.detach()[idx], stable=True)
        idx, bx0, bx1, by0, by1 = idx[order], bx0[order], bx1[order], by0[order], by1[order]
        nx, ny = bx1 - bx0 + 1, by1 - by0 + 1
        n = nx * ny
        S = idx.numel()
        rank = torch.repeat_interleave(torch.arange(S, device=dev), n)
        M = rank.numel()
        first = torch.cumsum(n, 0) - n
        local = torch.arange(M, device=dev) - first[rank]
        nxr = nx[rank]
        bid = (by0[rank] + local // nxr) * nbx + bx0[rank] + local % nxr
        key, _ = torch.sort(bid * max(S, 1) + rank)
        blk = key // max(S, 1)
        pair_gid = idx[key % max(S, 1)]
        count = torch.bincount(blk, minlength=nblocks)
        start = torch.cumsum(count, 0) - count
        chunks = _schedule(count, block * block, chunk_elems or CHUNK_ELEMS)
    return Plan(width, height, block, nbx, nby, pair_gid, start, count, chunks, M, seg or SEGMENT)


def _schedule(count: Tensor, P: int, chunk_elems: int) -> list[tuple[Tensor, int]]:
    """Chunks of blocks with similar list lengths (longest first), each about
    `chunk_elems` dense elements, so padding to the chunk's longest list is small."""
    nz = torch.nonzero(count).squeeze(1)
    if nz.numel() == 0:
        return []
    c = count[nz]
    c, o = torch.sort(c, descending=True)
    nz = nz[o]
    cl = c.tolist()
    out, s = [], 0
    while s < len(cl):
        k = cl[s]
        nb = max(1, chunk_elems // (k * P))
        out.append((nz[s : s + nb], k))
        s += nb
    return out


def _coef(
    p: Tensor,  # [nb, K, 6] packed (u, v, A, B, C, log o) per pair
    centre: Tensor,  # [nb, 1, 2] block centre px
):
    """Coefficients of log(o G) as a quadratic in the block-local pixel offset l:
    c0 + gx lx + gy ly + qa lx^2 + qb lx ly + qc ly^2, with d0 = mean - centre.
    Expanding around the block centre keeps the terms small where alpha matters:
    the large part of d0 lies along the ellipse's long axis, where Q d0 is small."""
    d0x = p[..., 0] - centre[..., 0]
    d0y = p[..., 1] - centre[..., 1]
    A, B, C = p[..., 2], p[..., 3], p[..., 4]
    gx = A * d0x + B * d0y
    gy = B * d0x + C * d0y
    c0 = p[..., 5] - 0.5 * (d0x * gx + d0y * gy)
    coef = torch.stack([c0, gx, gy, -0.5 * A, -B, -0.5 * C], 1)  # [nb, 6, K]
    return coef, d0x, d0y, gx, gy


def _below(x: float, dtype: torch.dtype) -> float:
    """The largest value of `dtype` below x, so that `threshold(t > it)` means t >= x."""
    t = torch.tensor(x, dtype=dtype)
    return float(torch.nextafter(t, torch.zeros_like(t)))


class _Consts:
    def __init__(self, dtype: torch.dtype):
        self.a_min = _below(ALPHA_MIN, dtype)
        self.t_min = _below(T_MIN, dtype)


def _alpha(coef2: Tensor, featsT: Tensor, c: _Consts) -> Tensor:  # [nb, P, k]
    """alpha = min(0.99, o G), zeroed below 1/255; coef2 is in log2 units."""
    a = torch.matmul(featsT, coef2)  # [P, 6] @ [nb, 6, k]
    a.exp2_()
    F.threshold_(a, c.a_min, 0.0)
    return a.clamp_max_(ALPHA_MAX)


def _transmittance(alpha: Tensor, Tc: Tensor | None, c: _Consts):
    """om = 1 - alpha; U = T after each Gaussian, zero from the first one that would
    bring T below 1e-4 (that one and all behind it are not blended)."""
    om = torch.rsub(alpha, 1.0)
    U = torch.cumprod(om, 2)
    if Tc is not None:
        U.mul_(Tc[..., None])
    F.threshold_(U, c.t_min, 0.0)
    return om, U


def _segments(K: int, seg: int):
    return [(k0, min(K, k0 + seg)) for k0 in range(0, K, seg)]


def _gather(plan: Plan, bl: Tensor, K: int, nrows: int):
    """Per chunk: Gaussian index of every (block, k) slot ([nb, K], padding -> nrows-1)
    and the block centres [nb, 1, 2]."""
    dev = bl.device
    ar = torch.arange(K, device=dev)
    pos = plan.block_start[bl][:, None] + ar
    ok = ar < plan.block_count[bl][:, None]
    g = torch.where(ok, plan.pair_gid[pos.clamp(max=max(plan.n_pairs - 1, 0))], nrows - 1)
    b = plan.block
    cx = (bl % plan.nbx) * b + b / 2
    cy = torch.div(bl, plan.nbx, rounding_mode="floor") * b + b / 2
    return g, torch.stack([cx, cy], -1)[:, None, :]


def _pack(means2d, conics, opacities, colors, depths):
    """Per-Gaussian rows (u, v, A, B, C, log o) and (r, g, b, z, 1), plus one padding row
    (log o = -1e4: alpha exactly 0). The constant 1 makes the colour GEMM also sum the
    blending weights, which gives T_final = 1 - sum w for free."""
    logo = torch.log(torch.clamp_min(opacities, 1e-38)).masked_fill(opacities <= 0, _DEAD)
    geo = torch.cat([means2d, conics, logo[:, None]], 1)
    pad = geo.new_zeros(1, 6)
    pad[0, 5] = _DEAD
    geo = torch.cat([geo, pad], 0)
    cz = torch.cat([colors, depths[:, None], torch.ones_like(depths)[:, None]], 1)
    cz = torch.cat([cz, cz.new_zeros(1, 5)], 0)
    return geo, cz


def _rows(x: Tensor, act: Tensor | None) -> Tensor:
    return x if act is None else x[act]


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, plan: Plan, means2d, conics, opacities, colors, depths, background):
        geo, cz = _pack(means2d, conics, opacities, colors, depths)
        dt, dev = means2d.dtype, means2d.device
        P = plan.block * plan.block
        nblocks = plan.nbx * plan.nby
        c = _Consts(dt)
        featsT = _feats(plan.block, dt, dev).T.contiguous()  # [P, 6]
        acc = torch.zeros(nblocks, 5, P, dtype=dt, device=dev)  # (r, g, b, depth, sum w)
        for bl, K in plan.chunks:
            g, centre = _gather(plan, bl, K, geo.shape[0])
            coef2 = _coef(geo[g], centre)[0].mul_(_LOG2E)  # [nb, 6, K]
            czt = cz[g].transpose(1, 2)  # [nb, 5, K]
            out = torch.zeros(bl.shape[0], 5, P, dtype=dt, device=dev)
            act, Tc = None, None
            for k0, k1 in _segments(K, plan.seg):
                alpha = _alpha(_rows(coef2, act)[:, :, k0:k1], featsT, c)
                om, U = _transmittance(alpha, Tc, c)
                w = alpha.div_(om).mul_(U)  # alpha T_before, 0 where not blended
                o = torch.bmm(_rows(czt, act)[:, :, k0:k1], w.transpose(1, 2))  # [na, 5, P]
                Tc = U[:, :, -1]
                if act is None:
                    out += o
                else:
                    out.index_add_(0, act, o)
                if k1 < K:  # early termination: drop blocks whose every pixel has stopped
                    alive = Tc.amax(1) > 0
                    if not bool(alive.all()):
                        act = torch.nonzero(alive).squeeze(1) if act is None else act[alive]
                        Tc = Tc[alive]
                        if act.numel() == 0:
                            break
            acc[bl] = out
        ctx.plan = plan
        ctx.save_for_backward(geo, cz, acc, background, opacities)
        return _unblock(plan, acc, background)

    @staticmethod
    def backward(ctx, g_image, g_alpha, g_depth):
        plan: Plan = ctx.plan
        geo, cz, acc, background, opacities = ctx.saved_tensors
        dt, dev = geo.dtype, geo.device
        c = _Consts(dt)
        feats = _feats(plan.block, dt, dev)  # [6, P]
        featsT = feats.T.contiguous()
        g4, gA = _block(plan, g_image, g_alpha, g_depth)  # [nblocks, 4, P], [nblocks, P]
        Tfin = 1.0 - acc[:, 4]
        # Per pixel: the colour+depth total g . acc (suffix sums come from it: 3DGS's
        # trick) plus d loss / d T_final = g . bg - g_alpha times T_final.
        base_all = (g4 * acc[:, :4]).sum(1) + Tfin * ((g4[:, :3] * background[:, None]).sum(1) - gA)
        g4t_all = g4.transpose(1, 2)  # [nblocks, P, 4]
        d_geo = torch.zeros_like(geo)
        d_cz = torch.zeros_like(cz)
        for bl, K in plan.chunks:
            nb = bl.shape[0]
            g, centre = _gather(plan, bl, K, geo.shape[0])
            p = geo[g]
            coef, d0x, d0y, gx, gy = _coef(p, centre)
            coef2 = coef * _LOG2E
            czt = cz[g].transpose(1, 2)[:, :4]  # [nb, 4, K]
            g4b, g4tb, base = g4[bl], g4t_all[bl], base_all[bl]
            R = torch.zeros(nb, 6, K, dtype=dt, device=dev)
            dczt = torch.zeros(nb, 4, K, dtype=dt, device=dev)
            act, Tc, pc = None, None, None
            for k0, k1 in _segments(K, plan.seg):
                alpha = _alpha(_rows(coef2, act)[:, :, k0:k1], featsT, c)
                om, U = _transmittance(alpha, Tc, c)
                r = alpha / om
                w = r * U
                v = torch.bmm(_rows(g4tb, act), _rows(czt, act)[:, :, k0:k1])  # [na, P, k]
                pre = torch.cumsum(w * v, 2)
                if pc is not None:
                    pre += pc[..., None]
                # d loss / d power = alpha d loss / d alpha
                #   = r (U v - (base - pre)), for blended, unclamped alpha; 0 otherwise.
                t = U * v
                t += pre
                t -= _rows(base, act)[..., None]
                mask = torch.sign(U).mul_(torch.sign(torch.rsub(alpha, ALPHA_MAX)))
                dpow = t.mul_(r).mul_(mask)
                Rs = torch.matmul(feats, dpow)  # [na, 6, k]: sums of dpow * pixel features
                ds = torch.bmm(_rows(g4b, act), w)  # [na, 4, k]
                if act is None:
                    R[:, :, k0:k1] = Rs
                    dczt[:, :, k0:k1] = ds
                else:
                    R[act, :, k0:k1] = Rs
                    dczt[act, :, k0:k1] = ds
                Tc, pc = U[:, :, -1], pre[:, :, -1]
                if k1 < K:
                    alive = Tc.amax(1) > 0
                    if not bool(alive.all()):
                        act = torch.nonzero(alive).squeeze(1) if act is None else act[alive]
                        Tc, pc = Tc[alive], pc[alive]
                        if act.numel() == 0:
                            break
            A, B, C = p[..., 2], p[..., 3], p[..., 4]
            R0, R1, R2, R3, R4, R5 = R.unbind(1)
            dgeo = torch.stack(
                [
                    -gx * R0 + A * R1 + B * R2,
                    -gy * R0 + B * R1 + C * R2,
                    -0.5 * (R0 * d0x * d0x - 2 * R1 * d0x + R3),
                    -(R0 * d0x * d0y - R1 * d0y - R2 * d0x + R4),
                    -0.5 * (R0 * d0y * d0y - 2 * R2 * d0y + R5),
                    R0,
                ],
                -1,
            )
            d_geo.index_add_(0, g.reshape(-1), dgeo.reshape(-1, 6))
            d_cz[:, :4].index_add_(0, g.reshape(-1), dczt.transpose(1, 2).reshape(-1, 4))
        d_geo, d_cz = d_geo[:-1], d_cz[:-1]
        d_opac = torch.where(opacities > 0, d_geo[:, 5] / opacities.clamp_min(1e-38), torch.zeros_like(opacities))
        d_bg = None
        if ctx.needs_input_grad[6]:
            d_bg = (g_image * _to_image(plan, Tfin[:, None])[..., 0:1]).sum((0, 1))
        return None, d_geo[:, :2], d_geo[:, 2:5], d_opac, d_cz[:, :3], d_cz[:, 3], d_bg


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
    plan: Plan,
    means2d: Tensor,  # [N, 2] px
    conics: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    colors: Tensor,  # [N, 3]
    depths: Tensor,  # [N]
    background: Tensor,  # [3]
) -> tuple[Tensor, Tensor, Tensor]:  # image [H, W, 3], alpha [H, W], depth [H, W]
    return _Composite.apply(plan, means2d, conics, opacities, colors, depths, background)
