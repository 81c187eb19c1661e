"""Per-Gaussian part of the forward model: 3D Gaussians -> screen-space ellipses.

Everything here is O(N) and differentiated by plain autograd; the per-pixel work
lives in `composite.py`. The model is the published 3DGS one:

    Sigma   = R S S^T R^T                      (R from the normalised quaternion)
    Sigma'  = J W Sigma W^T J^T + 0.3 I        (EWA; J at the camera-space mean,
                                                x/z, y/z clamped to +-1.3 tan(fov/2))
    radius  = ceil(3 sqrt(lambda_max(Sigma')))  pixels
    colour  = max(SH(dir) + 0.5, 0), dir = normalise(mean - camera centre)

Robustness: a first pass without gradients finds the Gaussians whose screen data
is finite and sane (in front of the near plane, finite 2D covariance, ...). The
differentiable pass then replaces the inputs of the others by benign values
*before* any division, so they get exactly zero (never NaN) gradients.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .sh import sh_to_rgb

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
class Projection:
    means2d: Tensor  # [N, 2] pixel coordinates of the projected means (0 where culled)
    conics: Tensor  # [N, 3] (A, B, C): inverse 2D covariance [[A, B], [B, C]], px^-2
    cov2d: Tensor  # [N, 3] (a, b, c): 2D covariance incl. the 0.3 blur, px^2
    opacities: Tensor  # [N] sigmoid(logit), times the Mip-Splatting compensation if antialiased
    colors: Tensor  # [N, 3] SH colour + 0.5 clamped at 0
    depths: Tensor  # [N] camera-space z, world units
    radii: Tensor  # [N] int32 ceil(3 sqrt(lambda_max)), 0 where culled
    valid: Tensor  # [N] bool: in front of the near plane with finite, sane screen data


def quat_to_rotmat(quats: Tensor) -> Tensor:  # [N, 4] w,x,y,z (any norm) -> [N, 3, 3]
    """Rotation of the normalised quaternion. The zero quaternion maps to the identity
    (its normalised value is taken as 0, and the formula below gives I at q = 0)."""
    # Normalising is scale invariant, so divide by a detached max-abs first: keeps
    # |q|^2 finite for huge quaternions without changing the value or the gradient.
    s = quats.detach().abs().amax(dim=-1, keepdim=True).clamp_min(torch.finfo(quats.dtype).tiny)
    q = quats / s
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(quats.shape[:-1] + (3, 3))


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


def project(
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
) -> Projection:
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
    return Projection(
        means2d=torch.where(vz, uv, torch.zeros_like(uv)),
        conics=torch.where(vz, conics, torch.zeros_like(conics)),
        cov2d=torch.stack([ap, b, cp], -1).detach(),
        opacities=torch.where(valid, opac, torch.zeros_like(opac)),
        colors=colors,
        depths=z,
        radii=radii,
        valid=valid,
    )


def tile_rect(
    means2d: Tensor,  # [N, 2] px
    radii: Tensor,  # [N] int32 px
    width: int,
    height: int,
) -> Tensor:  # [N, 4] int64 (tx0, ty0, tx1, ty1), tiles [tx0, tx1) x [ty0, ty1), clamped
    """The 16x16 tiles that the 3-sigma square [mean - r, mean + r]^2 overlaps."""
    gx, gy = math.ceil(width / TILE), math.ceil(height / TILE)
    m = means2d.detach().to(torch.float64)  # float64: exact integer tile bounds
    r = radii.to(torch.float64)
    tx0 = torch.floor((m[:, 0] - r) / TILE).clamp(0, gx)
    tx1 = torch.ceil((m[:, 0] + r) / TILE).clamp(0, gx)
    ty0 = torch.floor((m[:, 1] - r) / TILE).clamp(0, gy)
    ty1 = torch.ceil((m[:, 1] + r) / TILE).clamp(0, gy)
    return torch.stack([tx0, ty0, tx1, ty1], -1).to(torch.int64)
