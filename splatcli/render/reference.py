"""Slow, obviously correct twins of the fast paths, for tests.

`project_autograd` is the per-Gaussian model (projection, SH colour) through plain
autograd: the twin of `projection.project`, whose backward is written by hand.

`rasterize_reference` is a slow rasterizer of the same model. Dense: every Gaussian
is evaluated at every pixel ([N, H*W] tensors), written with explicit 3x3 / 2x3
matrices straight from the 3DGS paper, and differentiated by plain autograd. Use
float64 and small scenes (memory is O(N * H * W)).

It applies exactly the fast path's rules: near-plane culling, the 16x16 tile rule
(a Gaussian reaches a pixel only if its 3-sigma square overlaps the pixel's tile),
alpha = min(0.99, o G) skipped below 1/255, front-to-back blending in (stable)
depth order that stops before transmittance would drop below 1e-4.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .output import RenderOutput
from .projection import BLUR, FOV_CLAMP, MAX_MEAN_PX, MAX_VAR_PX2, NEAR, quat_to_rotmat
from .sh import sh_to_rgb

TILE = 16


def _rotmat(quats: Tensor) -> Tensor:  # [N, 4] -> [N, 3, 3]
    """R = I + 2 w [v]x + 2 [v]x^2 for the unit quaternion (w, v); q = 0 -> I."""
    n = torch.linalg.vector_norm(quats, dim=-1, keepdim=True)
    q = torch.where(n > 0, quats / torch.where(n > 0, n, torch.ones_like(n)), torch.zeros_like(quats))
    w, x, y, z = q.unbind(-1)
    o = torch.zeros_like(w)
    vx = torch.stack([o, -z, y, z, o, -x, -y, x, o], -1).reshape(-1, 3, 3)  # cross-product matrix of v
    eye = torch.eye(3, dtype=quats.dtype, device=quats.device).expand_as(vx)
    return eye + 2 * w[:, None, None] * vx + 2 * vx @ vx


@dataclass
class ReferenceProjection:
    means2d: Tensor  # [N, 2] pixel coordinates of the projected means (0 where invalid)
    conics: Tensor  # [N, 3] (A, B, C): inverse 2D covariance [[A, B], [B, C]], px^-2
    cov2d: Tensor  # [N, 3] (a, b, c): 2D covariance incl. the 0.3 blur, px^2
    opacities: Tensor  # [N] sigmoid(logit), times the Mip-Splatting compensation if antialiased
    colors: Tensor  # [N, 3] SH colour + 0.5 clamped at 0
    depths: Tensor  # [N] camera-space z, world units
    radii: Tensor  # [N] int32 ceil(3 sqrt(lambda_max)), 0 where invalid
    valid: Tensor  # [N] bool: in front of the near plane with finite, sane screen data


def _screen(
    means: Tensor,  # [N, 3] world
    quats: Tensor,  # [N, 4]
    log_scales: Tensor,  # [N, 3]
    viewmat: Tensor,  # [4, 4] world -> camera
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    near: float,
    valid: Tensor | None,  # [N] bool or None (first pass)
):
    """Camera-space depth, pixel mean, 2D covariance (without blur) and det(JWRS...)."""
    Rw, t = viewmat[:3, :3], viewmat[:3, 3]
    pc = means @ Rw.T + t  # [N, 3] camera space
    x, y, z = pc.unbind(-1)
    front = z > near if valid is None else valid
    zs = torch.where(front, z, torch.ones_like(z))  # no division by z <= near, ever
    ls = log_scales if valid is None else torch.where(valid[:, None], log_scales, torch.zeros_like(log_scales))
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    u = fx * x / zs + cx
    v = fy * y / zs + cy
    # J at the camera-space mean with x/z, y/z clamped (3DGS): keeps the Jacobian of
    # off-screen Gaussians from exploding.
    limx = FOV_CLAMP * 0.5 * width / fx
    limy = FOV_CLAMP * 0.5 * height / fy
    txz = torch.maximum(torch.minimum(x / zs, limx), -limx)
    tyz = torch.maximum(torch.minimum(y / zs, limy), -limy)
    zero = torch.zeros_like(zs)
    J = torch.stack(
        [fx / zs, zero, -fx * txz / zs, zero, fy / zs, -fy * tyz / zs], dim=-1
    ).reshape(-1, 2, 3)  # [N, 2, 3]
    M = (J @ Rw) @ quat_to_rotmat(quats) * torch.exp(ls)[:, None, :]  # [N, 2, 3]: Sigma' = M M^T
    m1, m2 = M[:, 0], M[:, 1]
    a = (m1 * m1).sum(-1)
    b = (m1 * m2).sum(-1)
    c = (m2 * m2).sum(-1)
    # det(M M^T) = |m1 x m2|^2 (Cauchy-Binet): a sum of squares, so no cancellation for
    # needle-thin Gaussians, where a*c - b^2 would lose every digit in float32.
    det0 = (torch.linalg.cross(m1, m2, dim=-1) ** 2).sum(-1)
    return z, front, torch.stack([u, v], -1), a, b, c, det0


def project_autograd(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    log_scales: Tensor,  # [N, 3]
    opacity_logits: Tensor,  # [N]
    sh: Tensor,  # [N, K, 3]
    viewmat: Tensor,  # [4, 4]
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    sh_degree: int,
    near: float = NEAR,
    antialiased: bool = False,
) -> ReferenceProjection:
    """The per-Gaussian model through plain autograd, on every row (no culling): the twin
    `projection.project` is tested against. Invalid Gaussians get exactly zero gradients
    through a first pass without gradients that finds them and a second whose inputs for
    them are replaced by benign values before any division."""
    with torch.no_grad():
        z, front, uv, a, b, c, det0 = _screen(means, quats, log_scales, viewmat, K, width, height, near, None)
        lam = 0.5 * (a + c) + BLUR + torch.sqrt((0.5 * (a - c)) ** 2 + b * b)
        valid = front & torch.isfinite(torch.stack([a, b, c, det0, lam], -1)).all(-1)
        valid &= torch.isfinite(uv).all(-1) & (lam < MAX_VAR_PX2) & (uv.abs() < MAX_MEAN_PX).all(-1)

    z, _, uv, a, b, c, det0 = _screen(means, quats, log_scales, viewmat, K, width, height, near, valid)
    ap, cp = a + BLUR, c + BLUR
    det = det0 + BLUR * (a + c) + BLUR * BLUR  # = ap * cp - b^2, without cancellation
    conics = torch.stack([cp / det, -b / det, ap / det], -1)
    opac = torch.sigmoid(opacity_logits)
    if antialiased:
        # Mip-Splatting 2D filter: the blur would brighten small Gaussians; scale the
        # opacity by sqrt(det before / det after) so their integrated mass is kept.
        opac = opac * torch.sqrt(torch.clamp_min(det0 / det, 1e-30))

    with torch.no_grad():
        lam = 0.5 * (ap + cp) + torch.sqrt((0.5 * (ap - cp)) ** 2 + b * b)
        r = torch.ceil(3.0 * torch.sqrt(lam))
        radii = torch.where(valid, r, torch.zeros_like(r)).clamp(0, 2**30).to(torch.int32)

    # View direction from the camera centre to the mean (world frame) for SH.
    Rw, t = viewmat[:3, :3], viewmat[:3, 3]
    campos = -(Rw.T @ t)
    d = means - campos
    d = d / torch.linalg.vector_norm(d, dim=-1, keepdim=True).clamp_min(1e-12)
    colors = sh_to_rgb(sh, d, sh_degree)

    vz = valid[:, None]
    return ReferenceProjection(
        means2d=torch.where(vz, uv, torch.zeros_like(uv)),
        conics=torch.where(vz, conics, torch.zeros_like(conics)),
        cov2d=torch.stack([ap, b, cp], -1).detach(),
        opacities=torch.where(valid, opac, torch.zeros_like(opac)),
        colors=colors,
        depths=z,
        radii=radii,
        valid=valid,
    )



def rasterize_reference(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    log_scales: Tensor,  # [N, 3]
    opacity_logits: Tensor,  # [N]
    sh: Tensor,  # [N, (d+1)^2, 3]
    viewmat: Tensor,  # [4, 4]
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    background: Tensor | None = None,  # [3]
    *,
    sh_degree: int | None = None,
    near: float = 0.2,
    antialiased: bool = False,
    rows: tuple[int, int] | None = None,
) -> RenderOutput:
    """The full picture, or only image rows [y0, y1) when `rows` is given (the blend is
    per pixel, so a band of rows is exactly that part of the image; benchmarks use
    bands to bound memory)."""
    dt, dev, N = means.dtype, means.device, means.shape[0]
    y0, y1 = rows if rows is not None else (0, height)
    if background is None:
        background = torch.zeros(3, dtype=dt, device=dev)
    if sh_degree is None:
        sh_degree = int(round(math.sqrt(sh.shape[1]))) - 1

    # --- camera space ---------------------------------------------------------------
    hom = torch.cat([means, torch.ones_like(means[:, :1])], 1)  # [N, 4]
    pc = (viewmat @ hom.T).T[:, :3]
    x, y, z = pc.unbind(-1)
    front = z > near
    z1 = torch.where(front, z, torch.ones_like(z))
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    means2d = torch.stack([fx * x / z1 + cx, fy * y / z1 + cy], -1)

    # --- 2D covariance: Sigma' = J W R S S^T R^T W^T J^T + 0.3 I ---------------------
    S = torch.diag_embed(torch.exp(torch.where(front[:, None], log_scales, torch.zeros_like(log_scales))))
    R = _rotmat(quats)
    Sigma = R @ S @ S.transpose(1, 2) @ R.transpose(1, 2)
    W = viewmat[:3, :3]
    limx, limy = 1.3 * (width / 2) / fx, 1.3 * (height / 2) / fy
    tx = torch.clamp(x / z1, -limx, limx) * z1
    ty = torch.clamp(y / z1, -limy, limy) * z1
    J = torch.zeros(N, 2, 3, dtype=dt, device=dev)
    J[:, 0, 0] = fx / z1
    J[:, 0, 2] = -fx * tx / z1**2
    J[:, 1, 1] = fy / z1
    J[:, 1, 2] = -fy * ty / z1**2
    cov = J @ W @ Sigma @ W.T @ J.transpose(1, 2)
    det_before = cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] ** 2
    cov = cov + 0.3 * torch.eye(2, dtype=dt, device=dev)
    det_after = cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] ** 2
    conic = torch.linalg.inv(cov)  # [N, 2, 2]
    opac = torch.sigmoid(opacity_logits)
    if antialiased:
        opac = opac * torch.sqrt(torch.clamp_min(det_before / det_after, 1e-30))
    lam_max = torch.linalg.eigvalsh(cov.detach())[:, -1]
    radius = torch.ceil(3 * torch.sqrt(lam_max))

    # --- tiles: the 3-sigma square [mean - r, mean + r]^2 against 16x16 tiles ----------
    gx, gy = math.ceil(width / TILE), math.ceil(height / TILE)
    m = means2d.detach()
    tx0 = torch.floor((m[:, 0] - radius) / TILE).clamp(0, gx)
    tx1 = torch.ceil((m[:, 0] + radius) / TILE).clamp(0, gx)
    ty0 = torch.floor((m[:, 1] - radius) / TILE).clamp(0, gy)
    ty1 = torch.ceil((m[:, 1] + radius) / TILE).clamp(0, gy)
    visible = front & (tx1 > tx0) & (ty1 > ty0)

    # --- every Gaussian at every pixel centre --------------------------------------------
    vv, uu = torch.meshgrid(
        torch.arange(y0, y1, dtype=dt, device=dev), torch.arange(width, dtype=dt, device=dev), indexing="ij"
    )
    pix = torch.stack([uu.reshape(-1), vv.reshape(-1)], -1) + 0.5  # [P, 2]
    ptx, pty = torch.floor(pix[:, 0] / TILE), torch.floor(pix[:, 1] / TILE)
    in_tile = (
        (ptx[None] >= tx0[:, None]) & (ptx[None] < tx1[:, None]) & (pty[None] >= ty0[:, None]) & (pty[None] < ty1[:, None])
    )  # [N, P]
    d = pix[None, :, :] - means2d[:, None, :]  # [N, P, 2]
    maha = torch.einsum("npi,nij,npj->np", d, conic, d)
    alpha = torch.clamp(opac[:, None] * torch.exp(-0.5 * maha), max=0.99)
    use = in_tile & visible[:, None] & (alpha >= 1.0 / 255.0)
    alpha = torch.where(use, alpha, torch.zeros_like(alpha))

    # --- front-to-back blending -------------------------------------------------------------
    order = torch.argsort(z.detach(), stable=True)
    a = alpha[order]  # [N, P] in depth order
    T_after = torch.cumprod(1 - a, dim=0)
    T_before = torch.cat([torch.ones_like(a[:1]), T_after[:-1]], 0)
    include = (T_after >= 1e-4).detach()  # stop before T would fall below 1e-4
    wgt = torch.where(include, a * T_before, torch.zeros_like(a))
    T_final = torch.prod(torch.where(include, 1 - a, torch.ones_like(a)), dim=0)  # [P]

    campos = -(viewmat[:3, :3].T @ viewmat[:3, 3])
    dirs = means - campos
    dirs = dirs / torch.linalg.vector_norm(dirs, dim=-1, keepdim=True).clamp_min(1e-12)
    colors = sh_to_rgb(sh, dirs, sh_degree)[order]  # [N, 3]
    image = wgt.T @ colors + T_final[:, None] * background
    depth = wgt.T @ z[order]
    radii = torch.where(visible, radius, torch.zeros_like(radius)).clamp(0, 2**30).to(torch.int32)
    return RenderOutput(
        image=image.reshape(y1 - y0, width, 3),
        alpha=(1 - T_final).reshape(y1 - y0, width),
        depth=depth.reshape(y1 - y0, width),
        means2d=means2d,
        radii=radii,
        visible=visible,
        depths=z,
    )
