"""Seeded synthetic Gaussian scenes for the rasterizer's tests; not used by the pipeline."""

from __future__ import annotations

import math

import torch
from torch import Tensor


def intrinsics(width: int, height: int, focal_factor: float = 0.8, dtype=torch.float32) -> Tensor:  # [3, 3]
    """f = focal_factor * width, principal point at the image centre."""
    f = focal_factor * width
    return torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]], dtype=dtype)


def test_scene(
    n: int, width: int, height: int, *, sh_degree: int = 1, seed: int = 0, dtype=torch.float64, rotate: bool = True
):
    """Random Gaussians seen by a rotated, translated camera. View depths are a shuffled
    ramp 3..7 (gaps >= 4/n) so float32 and float64 agree on the blending order;
    opacities, scales and SH are random. Returns [means, quats, log_scales,
    opacity_logits, sh, viewmat, K]."""
    g = torch.Generator().manual_seed(seed)
    z = 3 + 4 * torch.randperm(n, generator=g).double() / max(n, 1)
    xy = (torch.rand(n, 2, generator=g, dtype=torch.float64) * 2.4 - 1.2) * z[:, None] * (width / 2) / (0.8 * width)
    xy[:, 1] *= height / width
    pc = torch.cat([xy, z[:, None]], 1)  # camera space
    viewmat = torch.eye(4, dtype=torch.float64)
    if rotate:
        a, b = 0.3, -0.2
        Rz = torch.tensor([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]], dtype=torch.float64)
        Rx = torch.tensor([[1, 0, 0], [0, math.cos(b), -math.sin(b)], [0, math.sin(b), math.cos(b)]], dtype=torch.float64)
        viewmat[:3, :3] = Rz @ Rx
        viewmat[:3, 3] = torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64)
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    means = (pc - t) @ R  # world = R^T (pc - t)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    log_scales = torch.rand(n, 3, generator=g, dtype=torch.float64) * 2 - 4.5
    logits = torch.randn(n, generator=g, dtype=torch.float64) * 1.5
    sh = torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g, dtype=torch.float64) * 0.5
    out = [means, quats, log_scales, logits, sh, viewmat, intrinsics(width, height, dtype=torch.float64)]
    return [t.to(dtype) for t in out]
