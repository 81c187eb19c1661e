"""Per-Gaussian part of the forward model: 3D Gaussians -> screen-space ellipses.

Everything here is O(N); the per-pixel work lives in `composite.py`. The model is the
published 3DGS one:

    Sigma   = R S S^T R^T                      (R from the normalised quaternion)
    Sigma'  = J W Sigma W^T J^T + 0.3 I        (EWA; J at the camera-space mean,
                                                x/z, y/z clamped to +-1.3 tan(fov/2))
    radius  = ceil(3 sqrt(lambda_max(Sigma')))  pixels
    colour  = max(SH(dir) + 0.5, 0), dir = normalise(mean - camera centre)

`project` is one custom autograd Function with a hand-written backward (`_Project`).
Its forward first culls cheaply to the rows that can reach the image (`_cull`: in
front of the near plane, and a bound on the 3-sigma square that can overlap the tile
grid), computes the model on those rows only, in a row layout ([component, Gaussian]
tensors, so each step is one vectorised op over all of them), and scatters the results
back; it also hands the planner the screen footprint of the drawable rows, in depth
order (`Footprint`). `reference.project_autograd` is the same model through autograd,
and the tests hold the two together.

Exactness: culling changes no picture. The transcendental functions and the matrix
product across rows (`exp`, `sigmoid`, the camera transform) run on all N rows before
the cull selects any, and everything after it is elementwise or within a row (the SH
colour's batched 1x16 @ 16x3 products), so a row's numbers do not depend on which other
rows were kept. When few rows are culled they are masked rather than gathered
(`COMPACT_BELOW`): gathering costs more than it saves there.

Robustness: a Gaussian whose screen data is not finite and sane (behind the near plane,
non-finite or huge 2D covariance or mean, ...) is invalid: not drawn, and its inputs are
replaced by benign values before its rows are differentiated, so it gets exactly zero
(never NaN) gradients, as culled rows do.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import torch
from torch import Tensor

from . import timing
from .sh import sh_basis, sh_basis_rows_backward

TILE = 16  # pixels; a Gaussian touches only the 16x16 tiles its 3-sigma square overlaps
BLUR = 0.3  # px^2 added to the 2D covariance diagonal (3DGS low-pass filter)
FOV_CLAMP = 1.3  # x/z, y/z clamped to +-1.3 tan(half fov) when evaluating J
# A screen ellipse larger than this (sigma^2 in px^2) or a mean farther than this from
# the origin (px) is culled: far beyond anything an image can show, and keeping
# float32 squares of these numbers finite in the backward pass needs the headroom.
MAX_VAR_PX2 = 1e16
MAX_MEAN_PX = 1e12
NEAR = 0.2  # Gaussians nearer the camera than this (world units, as 3DGS) are not drawn


def in_frustum(
    points: Tensor,  # [N, 3] world
    viewmat: Tensor,  # [4, 4] world to camera
    K: Tensor,  # [3, 3] pixels
    width: int,
    height: int,
    margin: float = 0.0,  # a fraction of the image size also counted as inside, on every side
) -> tuple[Tensor, Tensor, Tensor]:  # uv [N, 2] pixels, depth [N], inside [N] bool
    """Where each point falls in the image (pixel coordinates of K), its depth, and
    whether it lies in front of the near plane and inside the image grown by `margin`.
    The one frustum test of training's bookkeeping (views that see a point, sampling
    rates, colours of --init-far points); computed in the points' dtype."""
    vm, k = viewmat.to(points), K.to(points)
    cam = points @ vm[:3, :3].T + vm[:3, 3]  # [N, 3]
    z = cam[:, 2]
    front = z > NEAR
    uv = (cam @ k.T)[:, :2] / torch.where(front, z, torch.ones_like(z))[:, None]
    lo_u, lo_v = -margin * width, -margin * height
    inside = (front & (uv[:, 0] >= lo_u) & (uv[:, 0] < width - lo_u)
              & (uv[:, 1] >= lo_v) & (uv[:, 1] < height - lo_v))
    return uv, z, inside


@dataclass
class Footprint:
    """What the planner reads: the screen data of the Gaussians that can be drawn (visible,
    and opaque enough that 2 ln(255 o) + 1e-3 > 0), in stable depth order. float64, from
    the dtype the compositor uses (exact integer pixel bounds)."""

    gid: Tensor  # [S] int64 index of each among the N Gaussians
    means2d: Tensor  # [S, 2] px
    cov2d: Tensor  # [S, 3] (a, b, c) px^2, incl. the blur
    vx: Tensor  # [S] 1 / A (A: the conic's first entry) = var(x | y), px^2
    opacities: Tensor  # [S]
    rect: Tensor  # [S, 4] int64 tile rect (tx0, ty0, tx1, ty1), exclusive ends


@dataclass
class Projection:
    means2d: Tensor  # [N, 2] pixel coordinates of the projected means (0 unless valid)
    conics: Tensor  # [N, 3] (A, B, C): inverse 2D covariance [[A, B], [B, C]], px^-2 (0 unless valid)
    opacities: Tensor  # [N] sigmoid(logit), times the Mip-Splatting compensation if antialiased (0 unless valid)
    colors: Tensor  # [N, 3] SH colour + 0.5 clamped at 0 (0 where culled)
    depths: Tensor  # [N] camera-space z, world units (every row; no gradient where culled)
    radii: Tensor  # [N] int32 ceil(3 sqrt(lambda_max)), 0 unless visible
    visible: Tensor  # [N] bool: valid, and its 3-sigma square overlaps a tile of the image
    footprint: Footprint


def quat_to_rotmat(quats: Tensor) -> Tensor:  # [N, 4] w,x,y,z (any norm) -> [N, 3, 3]
    """Rotation of the normalised quaternion. The zero quaternion maps to the identity
    (its normalised value is taken as 0, and the formula below gives I at q = 0)."""
    w, x, y, z = unit_quat(quats)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(quats.shape[:-1] + (3, 3))


def unit_quat(quats: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:  # [..., 4] any norm -> 4 x [...]
    """The normalised quaternion's w, x, y, z (each 0 for the zero quaternion). Normalising is scale
    invariant, so it divides by a detached max-abs first: keeps |q|^2 finite for huge quaternions
    without changing the value or the gradient."""
    s = quats.detach().abs().amax(dim=-1, keepdim=True).clamp_min(torch.finfo(quats.dtype).tiny)
    q = quats / s
    return (q / torch.linalg.vector_norm(q, dim=-1, keepdim=True).clamp_min(1e-12)).unbind(-1)


def quat_rotate(q: tuple[Tensor, ...], v: tuple[Tensor, ...], inverse: bool = False) -> tuple[Tensor, Tensor, Tensor]:
    """R v, or R^T v when `inverse`, for the rotation of the unit quaternion q = `unit_quat(...)`
    and vectors given by their components v = (vx, vy, vz), each [M]; the same as quat_to_rotmat's R,
    without forming it: with q = (w, u), R v = v + w t + u x t, t = 2 u x v (the conjugate's, -u,
    for R^T). One [M] tensor per component: batched 3x3 products, or transposing [M, 3] rows to
    [3, M], cost 3-4x as much for M in the tens of thousands."""
    w, x, y, z = q
    if inverse:
        x, y, z = -x, -y, -z
    v0, v1, v2 = v
    t0, t1, t2 = 2 * (y * v2 - z * v1), 2 * (z * v0 - x * v2), 2 * (x * v1 - y * v0)
    return (torch.addcmul(v0, w, t0).addcmul_(y, t2).addcmul_(z, t1, value=-1.0),
            torch.addcmul(v1, w, t1).addcmul_(z, t0).addcmul_(x, t2, value=-1.0),
            torch.addcmul(v2, w, t2).addcmul_(x, t1).addcmul_(y, t0, value=-1.0))


def _cross(a: Tensor, b: Tensor) -> Tensor:  # [3, S] x [3, S] -> [3, S]
    """a x b of each column, written out: linalg.cross along the first axis took 3x as long."""
    a0, a1, a2 = a
    b0, b1, b2 = b
    return torch.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def _outer_into(basis: Tensor, g: Tensor, out: Tensor) -> Tensor:  # [S, nk], [S, 3] -> out [S, nk, 3]
    """out[s, k, c] = basis[s, k] g[s, c], one colour channel at a time: a broadcast over the
    3-long last axis runs 2-3x slower (its inner loop is 3 long); the same products, so the same bits."""
    for c in range(out.shape[2]):
        torch.mul(basis, g[:, c:c + 1], out=out[:, :, c])
    return out


def tile_rect(
    means2d: Tensor,  # [N, 2] px
    radii: Tensor,  # [N] int32 px
    width: int,
    height: int,
) -> Tensor:  # [N, 4] int64 (tx0, ty0, tx1, ty1), tiles [tx0, tx1) x [ty0, ty1), clamped
    """The 16x16 tiles that the 3-sigma square [mean - r, mean + r]^2 overlaps."""
    m = means2d.detach().to(torch.float64)  # float64: exact integer tile bounds
    r = radii.to(torch.float64)[:, None]
    g = torch.tensor([math.ceil(width / TILE), math.ceil(height / TILE)], dtype=torch.float64, device=m.device)
    zero = torch.zeros((), dtype=torch.float64, device=m.device)
    lo = torch.clamp(torch.floor((m - r) / TILE), zero, g)
    hi = torch.clamp(torch.ceil((m + r) / TILE), zero, g)
    return torch.cat([lo, hi], 1).to(torch.int64)


def project(
    means: Tensor,  # [N, 3] world
    quats: Tensor,  # [N, 4] w, x, y, z, any norm
    log_scales: Tensor,  # [N, 3]
    opacity_logits: Tensor,  # [N]
    sh: Tensor,  # [N, K, 3] DC first, K >= (sh_degree + 1)^2
    viewmat: Tensor,  # [4, 4] world -> camera
    K: Tensor,  # [3, 3] px
    width: int,
    height: int,
    sh_degree: int,
    near: float = NEAR,
    antialiased: bool = False,
) -> Projection:
    """The screen-space Gaussians of one view, differentiable in every input (the camera
    included) through `_Project`'s hand-written backward."""
    if not 0 <= sh_degree <= 3:
        raise ValueError(f"sh degree {sh_degree} is not supported (0..3)")
    out = _Project.apply(means, quats, log_scales, opacity_logits, sh, viewmat, K, width, height, sh_degree, near,
                         antialiased)
    *dense, radii, visible, gid, m2, cov, vx, opac, rect = out
    return Projection(*dense, radii=radii, visible=visible, footprint=Footprint(gid, m2, cov, vx, opac, rect))


class _Camera:
    """The view in the row layout's terms: W [3, 3] and t [3] of the view matrix, and the
    focal lengths f, principal point c and FOV clamp lim as [2, 1] columns (x, y)."""

    def __init__(self, viewmat: Tensor, K: Tensor, width: int, height: int, dtype: torch.dtype):
        vm, k = viewmat.detach().to(dtype), K.detach().to(dtype)
        self.Rw, self.t = vm[:3, :3], vm[:3, 3]
        self.f = torch.stack([k[0, 0], k[1, 1]])[:, None]
        self.c = torch.stack([k[0, 2], k[1, 2]])[:, None]
        half = torch.tensor([[FOV_CLAMP * 0.5 * width], [FOV_CLAMP * 0.5 * height]], dtype=dtype, device=k.device)
        self.lim = half / self.f
        self.campos = -(self.Rw.T @ self.t)  # [3] camera centre, world


def _mean2d(xy: Tensor, zs: Tensor, cam: _Camera) -> tuple[Tensor, Tensor, Tensor]:
    """xy [2, S] camera x, y and zs [S] depth (> 0) -> r = (x/z, y/z), the pixel mean
    uv = f r + c, and tc: r clamped to the FOV clamp, where J is evaluated (3DGS)."""
    r = xy / zs
    return r, r * cam.f + cam.c, torch.maximum(torch.minimum(r, cam.lim), -cam.lim)


def _cull(
    z: Tensor,  # [N] depth
    near: float,
    zs: Tensor,  # [N] depth, 1 where not beyond the near plane
    uv: Tensor,  # [2, N] px
    scales: Tensor,  # [3, N] exp(log_scales)
    cam: _Camera,
    width: int,
    height: int,
) -> Tensor:  # [N] bool: may be drawn
    """A cheap superset of the Gaussians beyond the near plane whose 3-sigma square can
    overlap the tile grid: lambda_max(Sigma') <= trace(Sigma') = |J W R S|_F^2 + 2 BLUR
    <= |J|_F^2 max(s)^2 + 2 BLUR (W R is a rotation), with |J|_F^2 <= sum f^2 (1 + lim^2) / z^2
    (the FOV clamp bounds x/z, y/z in J), and the radius is ceil(3 sqrt(lambda_max)). Slack
    covers rounding; a bound that is NaN keeps the row (the projection then finds it invalid)."""
    jz = math.sqrt(float((cam.f * cam.f * (1 + cam.lim * cam.lim)).sum())) * scales.amax(0) / zs  # >= |J|_F max(s)
    rad = torch.sqrt(jz * jz + 2 * BLUR) * (3 * (1 + 1e-4)) + 2  # px
    grid = torch.tensor([[TILE * math.ceil(width / TILE)], [TILE * math.ceil(height / TILE)]], dtype=uv.dtype,
                        device=uv.device)
    return (z > near) & ~((uv + rad <= 0) | (uv - rad >= grid)).any(0)


def _rotation_rows(qn: Tensor) -> Tensor:  # [4, S] unit (w, x, y, z) -> R [3, 3, S]
    """quat_to_rotmat's R in the row layout, each entry written in place from the products it needs
    (forming q q^T and gathering its entries cost 4x as much)."""
    w, x, y, z = qn
    q2 = qn[1:] * qn[1:]  # xx, yy, zz
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    R = qn.new_empty(3, 3, qn.shape[1])
    for (i, j), (a, b, sign) in {(0, 1): (xy, wz, -1), (0, 2): (xz, wy, 1), (1, 0): (xy, wz, 1),
                                 (1, 2): (yz, wx, -1), (2, 0): (xz, wy, -1), (2, 1): (yz, wx, 1)}.items():
        torch.add(a, b, alpha=sign, out=R[i, j]).mul_(2)
    for i, (a, b) in enumerate(((1, 2), (0, 2), (0, 1))):  # 1 - 2 (yy + zz), ...
        torch.add(q2[a], q2[b], out=R[i, i]).mul_(-2).add_(1)
    return R


def _cov2d(tc: Tensor, zs: Tensor, quats: Tensor, scales: Tensor, cam: _Camera) -> dict:
    """The screen-space covariance of S Gaussians in the row layout: tc [2, S] (see
    `_mean2d`), zs [S], quats [4, S], scales [3, S]. Sigma' = M M^T + BLUR I with
    M = J W R S [2, 3, S]; returns every intermediate the backward reads."""
    Jd = cam.f / zs  # J's diagonal; its last column is Jz = -Jd tc
    Jz = -(Jd * tc)
    T = Jd[:, None] * cam.Rw[:2, :, None] + Jz[:, None] * cam.Rw[2][None, :, None]  # [2, 3, S] = J W
    # Normalising is scale invariant, so divide by the max-abs first: keeps |q|^2 finite
    # for huge quaternions; the zero quaternion gives qn = 0 and R = I.
    qs = quats.abs().amax(0).clamp_min(torch.finfo(quats.dtype).tiny)
    q = quats / qs
    qnorm = torch.sqrt((q * q).sum(0))
    qn = q / qnorm.clamp_min(1e-12)
    R = _rotation_rows(qn)
    M = (T[:, :, None] * R[None]).sum(1) * scales  # [2, 3, S]
    m1, m2 = M
    a, b, c = (m1 * m1).sum(0), (m1 * m2).sum(0), (m2 * m2).sum(0)
    w = _cross(m1, m2)
    # det(M M^T) = |m1 x m2|^2 (Cauchy-Binet): a sum of squares, so no cancellation for
    # needle-thin Gaussians, where a*c - b^2 would lose every digit in float32.
    det0 = (w * w).sum(0)
    return dict(Jd=Jd, Jz=Jz, T=T, qs=qs, qnorm=qnorm, qn=qn, R=R, M=M, a=a, b=b, c=c, w=w, det0=det0)


def _rotation_grad_matrix() -> list[list[float]]:  # [16, 9]
    """L^T for R (flattened) = I + L vec(q q^T), L split evenly between the (a, b) and
    (b, a) entries: then d loss / d q = 2 (L^T g_R, as [4, 4]) q."""
    w, x, y, z = range(4)
    terms = {0: [(y, y, -2), (z, z, -2)], 1: [(x, y, 2), (w, z, -2)], 2: [(x, z, 2), (w, y, 2)],
             3: [(x, y, 2), (w, z, 2)], 4: [(x, x, -2), (z, z, -2)], 5: [(y, z, 2), (w, x, -2)],
             6: [(x, z, 2), (w, y, -2)], 7: [(y, z, 2), (w, x, 2)], 8: [(x, x, -2), (y, y, -2)]}
    L = [[0.0] * 9 for _ in range(16)]
    for r, ts in terms.items():
        for i, j, v in ts:
            L[4 * i + j][r] += v / 2
            L[4 * j + i][r] += v / 2
    return L


_LT = _rotation_grad_matrix()


def _rows(x: Tensor, idx: Tensor | None) -> Tensor:  # [k, N] or [N] -> [k, S] or [S]
    return x if idx is None else x.index_select(-1, idx)


def _full(x: Tensor, idx: Tensor | None, n: int) -> Tensor:  # [S, ...] -> [N, ...], zero where culled
    if idx is None:
        return x.contiguous()
    return x.new_zeros((n,) + x.shape[1:]).index_copy_(0, idx, x)


def _depth_order(z: Tensor) -> Tensor:  # [S] > 0 -> [S] int64
    """Stable argsort of positive depths. The IEEE bits of positive floats sort as integers,
    and integer sorts are far faster on CPU."""
    bits = {torch.float32: torch.int32, torch.float64: torch.int64}.get(z.dtype)
    return torch.argsort(z if bits is None else z.view(bits), stable=True)


# Below this share of rows kept, the rows are gathered before computing (and scattered
# back after); above it, every row is computed and the culled ones masked like invalid
# ones: gathering and scattering cost about as much as computing a third of the rows.
COMPACT_BELOW = 0.7


class _Project(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, log_scales, opacity_logits, sh, viewmat, K, width, height, sh_degree, near,
                antialiased):
        N, nk = means.shape[0], (sh_degree + 1) ** 2
        cam = _Camera(viewmat, K, width, height, means.dtype)
        # On all N rows (see "Exactness" above): the camera transform, exp, sigmoid and the cull.
        pc = torch.addmm(cam.t[:, None], cam.Rw, means.T)  # [3, N] camera space
        scales = torch.exp(log_scales.T.contiguous())  # [3, N]
        sig = torch.sigmoid(opacity_logits)
        z = pc[2]
        zs = torch.where(z > near, z, torch.ones_like(z))
        r, uv, tc = _mean2d(pc[:2], zs, cam)
        keep = _cull(z, near, zs, uv, scales, cam, width, height)
        front = (z > near) & (uv.abs() < MAX_MEAN_PX).all(0)
        uv_all = uv  # every row's means2d
        idx, nkeep = None, int(keep.sum())
        if nkeep < COMPACT_BELOW * N:  # gather the kept rows
            idx = torch.nonzero(keep).squeeze(1)
            pcr, zs, r, uv, tc, scales = (_rows(t, idx) for t in (pc, zs, r, uv, tc, scales))
            z, sigr, frontr = pcr[2], sig.index_select(0, idx), front.index_select(0, idx)
        else:
            pcr, sigr, frontr = pc, sig, front
        if idx is not None or nkeep == N:
            keep = None  # every computed row is kept
        qr, mr = _rows(quats.T, idx).contiguous(), _rows(means.T, idx).contiguous()  # [4 | 3, S]
        shr = sh[:, :nk] if idx is None else sh[:, :nk].index_select(0, idx)  # [S, nk, 3]

        g = _cov2d(tc, zs, qr, scales, cam)
        # lambda_max(Sigma'), the largest eigenvalue of [[a + BLUR, b], [b, c + BLUR]]
        lam = 0.5 * (g["a"] + g["c"]) + BLUR + torch.sqrt((0.5 * (g["a"] - g["c"])) ** 2 + g["b"] * g["b"])
        # NaN fails every comparison, and lam bounds a, c and |b|: this is "finite and sane".
        sane = lam < MAX_VAR_PX2
        valid = frontr & sane if keep is None else frontr & sane & keep
        if not bool(torch.isfinite(lam + g["det0"]).all()):  # both >= 0 (or NaN)
            # Recompute with benign inputs where the numbers overflowed: the backward multiplies
            # their (zero) gradients by these intermediates, and 0 * inf would be NaN.
            zs = torch.where(valid, z, torch.ones_like(z))
            scales = torch.where(valid, scales, torch.ones_like(scales))
            r, _, tc = _mean2d(pcr[:2], zs, cam)
            g = _cov2d(tc, zs, qr, scales, cam)
        a, b, c, det0 = g["a"], g["b"], g["c"], g["det0"]
        ap, cp = a + BLUR, c + BLUR
        det = det0 + BLUR * (a + c) + BLUR * BLUR  # = ap * cp - b^2, without cancellation
        con = torch.stack([cp, -b, ap]) / det  # [3, S]
        opac = sigr
        if antialiased:
            # Mip-Splatting 2D filter: the blur would brighten small Gaussians; scale the
            # opacity by sqrt(det before / det after) so their integrated mass is kept.
            ratio = det0 / det
            aa = torch.sqrt(torch.clamp_min(ratio, 1e-30))
            opac = opac * aa
        radii = torch.where(valid, torch.ceil(3.0 * torch.sqrt(lam)), torch.zeros_like(lam)).clamp(0, 2**30)
        radii = radii.to(torch.int32)

        # Colour: SH at the view direction from the camera centre to the mean (world frame).
        d = mr - cam.campos[:, None]
        dn = torch.sqrt((d * d).sum(0))
        dirs = d / dn.clamp_min(1e-12)
        basis = sh_basis(dirs.T, sh_degree)  # [S, nk]
        raw = torch.bmm(basis[:, None, :], shr)[:, 0] + 0.5  # [S, 3]
        colors = torch.clamp_min(raw, 0.0)
        if keep is not None:
            colors = torch.where(keep[:, None], colors, torch.zeros_like(colors))

        uvv = torch.where(valid, uv, torch.zeros_like(uv))
        opac = torch.where(valid, opac, torch.zeros_like(opac))
        rect = tile_rect(uvv.T, radii, width, height)
        vis = valid & (rect[:, 2] > rect[:, 0]) & (rect[:, 3] > rect[:, 1])
        radii = torch.where(vis, radii, torch.zeros_like(radii))

        # The planner's footprint: drawable rows in stable depth order (depths > near > 0).
        f64 = torch.float64
        o64 = opac.to(f64)
        fi = torch.nonzero(vis & (2.0 * torch.log(torch.clamp_min(o64 * 255.0, 1e-30)) + 1e-3 > 0)).squeeze(1)
        fi = fi.index_select(0, _depth_order(z.index_select(0, fi)))
        fp = (
            fi if idx is None else idx.index_select(0, fi),
            uvv.index_select(1, fi).T.to(f64),
            torch.stack([ap, b, cp]).index_select(1, fi).T.to(f64),
            1.0 / con[0].index_select(0, fi).to(f64),
            o64.index_select(0, fi),
            rect.index_select(0, fi),
        )

        # The mean of every row in front (culled ones too; the same arithmetic, so the same
        # numbers), but not of those whose covariance was found insane.
        if idx is None:
            mvalid = valid if keep is None else front & (sane | ~keep)
        else:
            mvalid = front.index_copy(0, idx, valid)
        means2d = torch.where(mvalid, uv_all, torch.zeros_like(uv_all)).T
        out = (
            means2d.contiguous(),
            _full(torch.where(valid, con, torch.zeros_like(con)).T, idx, N),
            _full(opac, idx, N),
            _full(colors, idx, N),
            pc[2].clone(),
            _full(radii, idx, N),
            _full(vis, idx, N),
        ) + fp
        ctx.mark_non_differentiable(*out[5:])
        ctx.set_materialize_grads(False)  # no zero-filled gradients for outputs nothing used
        ctx.save_for_backward(sh)
        ctx.idx, ctx.keep, ctx.N, ctx.cam, ctx.deg, ctx.antialiased = idx, keep, N, cam, sh_degree, antialiased
        ctx.camera_dtypes = viewmat.dtype, K.dtype
        ctx.valid, ctx.zs, ctx.r, ctx.tc, ctx.g, ctx.scales = valid, zs, r, tc, g, scales
        ctx.det, ctx.con, ctx.sig, ctx.mr = det, con, sigr, mr
        ctx.dirs, ctx.dn, ctx.basis, ctx.raw = dirs, dn, basis, raw
        if antialiased:
            ctx.ratio, ctx.aa = ratio, aa
        return out

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_opac, g_colors, g_depths, *_):
        t0 = time.perf_counter()
        out = _Project._backward(ctx, g_means2d, g_conics, g_opac, g_colors, g_depths)
        timing.add("projection backward", time.perf_counter() - t0)
        return out

    @staticmethod
    def _backward(ctx, g_means2d, g_conics, g_opac, g_colors, g_depths):
        (sh,) = ctx.saved_tensors
        idx, keep, N, cam, deg, valid = ctx.idx, ctx.keep, ctx.N, ctx.cam, ctx.deg, ctx.valid
        need = ctx.needs_input_grad
        S, nk = valid.shape[0], (deg + 1) ** 2
        zero = ctx.zs.new_zeros(())

        def rows(x, k):  # an output's gradient on the computed rows: [k, S], or [S] for k = 0
            if x is None:
                return ctx.zs.new_zeros((k, S) if k else (S,))
            x = x if idx is None else x.index_select(0, idx)
            return x.T.contiguous() if k else x

        # Outputs are 0 where invalid (means, conics, opacities) or culled (colour; no depth gradient).
        gu = torch.where(valid, rows(g_means2d, 2), zero)
        gcon = torch.where(valid, rows(g_conics, 3), zero)
        gop = torch.where(valid, rows(g_opac, 0), zero)
        gz = rows(g_depths, 0) if keep is None else torch.where(keep, rows(g_depths, 0), zero)
        if g_colors is None:
            gcol = ctx.zs.new_zeros(S, 3)
        else:  # [S, 3], in the outputs' own layout (rows() would transpose it to [3, S])
            gcol = g_colors if idx is None else g_colors.index_select(0, idx)
            gcol = gcol if keep is None else torch.where(keep[:, None], gcol, zero)
        grads = [None] * 7

        # --- opacity ---------------------------------------------------------------------
        sig = ctx.sig
        if need[3]:
            g_sig = gop * ctx.aa if ctx.antialiased else gop
            grads[3] = _full(g_sig * sig * (1 - sig), idx, N)

        # --- SH colour -------------------------------------------------------------------
        g_raw = torch.where(ctx.raw >= 0, gcol, zero)  # [S, 3]; the clamp at 0
        if need[4]:
            if idx is None:  # written in place: [N, K, 3], zero beyond the active degree's nk
                grads[4] = torch.empty_like(sh) if nk == sh.shape[1] else torch.zeros_like(sh)
                _outer_into(ctx.basis, g_raw, grads[4][:, :nk])
            else:
                grads[4] = torch.zeros_like(sh)
                grads[4][:, :nk].index_copy_(0, idx, _outer_into(ctx.basis, g_raw, sh.new_empty(len(idx), nk, 3)))
        if not (need[0] or need[1] or need[2] or need[5] or need[6]):
            return (*grads, None, None, None, None, None)

        # --- screen covariance: conic (A, B, C) and opacity -> a, b, c, det0 --------------
        g = ctx.g
        det, (A, Bc, C) = ctx.det, ctx.con
        gA, gB, gC = gcon
        g_det = -(gA * A + gB * Bc + gC * C) / det
        g_det0 = 0.0
        if ctx.antialiased:  # ratio = det0 / det
            g_ratio = torch.where(ctx.ratio >= 1e-30, gop * sig * 0.5 / ctx.aa, zero)
            g_det0 = g_ratio / det
            g_det = g_det - g_ratio * ctx.ratio / det
        g_det0 = g_det0 + g_det  # det = det0 + BLUR (a + c) + BLUR^2
        g_a = gC / det + BLUR * g_det
        g_c = gA / det + BLUR * g_det
        g_b = -gB / det
        M = g["M"]
        m1, m2 = M
        gw = 2 * g_det0 * g["w"]  # det0 = |w|^2, w = m1 x m2
        g_m1 = 2 * g_a * m1 + g_b * m2 + _cross(m2, gw)
        g_m2 = 2 * g_c * m2 + g_b * m1 + _cross(gw, m1)
        gM = torch.stack([g_m1, g_m2])  # [2, 3, S]

        # --- M = J W R S ------------------------------------------------------------------
        if need[2]:  # d M / d log s_j = column j of M
            grads[2] = _full(torch.where(valid, (gM * M).sum(0), zero).T, idx, N)
        gB_ = gM * ctx.scales  # d / d (J W R)
        if need[1]:
            gR = (g["T"][:, :, None] * gB_[:, None]).sum(0).reshape(9, -1)  # [9, S]
            qn, qnorm = g["qn"], g["qnorm"]
            Gq = torch.mm(torch.tensor(_LT, dtype=gR.dtype, device=gR.device), gR).view(4, 4, -1)
            gqn = 2 * (Gq * qn[None]).sum(1)
            gq = torch.where(qnorm >= 1e-12, (gqn - qn * (qn * gqn).sum(0)) / qnorm, gqn / 1e-12)
            grads[1] = _full((gq / g["qs"]).T, idx, N)
        if not (need[0] or need[5] or need[6]):
            return (*grads, None, None, None, None, None)
        gT = (gB_[:, None] * g["R"][None]).sum(2)  # [2, 3, S]: d / d (J W)

        # --- J = [[fx/z, 0, -fx tx/z], [0, fy/z, -fy ty/z]] and the mean ------------------
        Rw, Jd, Jz, tc, r, zs = cam.Rw, g["Jd"], g["Jz"], ctx.tc, ctx.r, ctx.zs
        g_Jd = (gT * Rw[:2, :, None]).sum(1)  # [2, S]
        g_Jz = (gT * Rw[2][None, :, None]).sum(1)
        g_Jd = g_Jd - g_Jz * tc  # Jz = -Jd tc
        g_tc = -(g_Jz * Jd)
        inside = (r >= -cam.lim) & (r <= cam.lim)
        g_r = gu * cam.f + torch.where(inside, g_tc, zero)  # u = f r + c
        g_zs = -((g_Jd * Jd).sum(0) + (g_r * r).sum(0)) / zs  # Jd = f / zs, r = xy / zs
        g_pc = torch.cat([g_r / zs, (torch.where(valid, g_zs, zero) + gz)[None]])  # [3, S]

        # --- SH direction: dir = normalise(mean - campos) ----------------------------------
        g_v = None
        if deg > 0 and (need[0] or need[5]):
            shr = sh[:, :nk] if idx is None else sh[:, :nk].index_select(0, idx)
            # [S, nk], a colour channel at a time: 1.7x faster than the batched 1x3 @ 3xnk products
            g_basis = shr[:, :, 0] * g_raw[:, 0:1]
            g_basis.addcmul_(shr[:, :, 1], g_raw[:, 1:2]).addcmul_(shr[:, :, 2], g_raw[:, 2:3])
            g_dir = sh_basis_rows_backward(ctx.dirs, g_basis.T, deg)
            dirs, dn = ctx.dirs, ctx.dn
            g_v = torch.where(dn >= 1e-12, (g_dir - dirs * (dirs * g_dir).sum(0)) / dn, g_dir / 1e-12)
        if need[0]:
            gm = Rw.T @ g_pc
            grads[0] = _full((gm if g_v is None else gm + g_v).T, idx, N)

        # --- the camera ---------------------------------------------------------------------
        if need[5]:
            gRw = g_pc @ ctx.mr.T  # pc = W mean + t
            gRw[:2] += (gT * Jd[:, None]).sum(-1)  # J W: row i of W times Jd_i, row 2 times Jz_i
            gRw[2] += (gT * Jz[:, None]).sum((0, 2))
            gt = g_pc.sum(1)
            if g_v is not None:  # dir from mean + W^T t
                gvs = g_v.sum(1)
                gRw += cam.t[:, None] * gvs[None]
                gt += Rw @ gvs
            grads[5] = torch.zeros(4, 4, dtype=gRw.dtype, device=gRw.device)
            grads[5][:3, :3], grads[5][:3, 3] = gRw, gt
            grads[5] = grads[5].to(ctx.camera_dtypes[0])
        if need[6]:
            clamped = (r > cam.lim).to(r.dtype) - (r < -cam.lim).to(r.dtype)
            g_lim = (g_tc * clamped).sum(1)  # lim = 0.65 width / fx
            gf = (g_Jd / zs).sum(1) + (gu * r).sum(1) - g_lim * cam.lim[:, 0] / cam.f[:, 0]
            gc = gu.sum(1)
            grads[6] = torch.zeros(3, 3, dtype=gf.dtype, device=gf.device)
            grads[6][0, 0], grads[6][1, 1], grads[6][0, 2], grads[6][1, 2] = gf[0], gf[1], gc[0], gc[1]
            grads[6] = grads[6].to(ctx.camera_dtypes[1])
        return (*grads, None, None, None, None, None)
