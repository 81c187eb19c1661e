"""Seeded synthetic Gaussian scenes for benchmarks (not used by the pipeline)."""

from __future__ import annotations

import torch
from torch import Tensor

from splatcli.render.sh import SH_C0


def intrinsics(width: int, height: int, focal_factor: float = 0.8, dtype=torch.float32) -> Tensor:  # [3, 3]
    """f = focal_factor * width, principal point at the image centre."""
    f = focal_factor * width
    return torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]], dtype=dtype)


def benchmark_scene(n: int, width: int, height: int, sh_degree: int = 0, seed: int = 0, dtype=torch.float32):
    """The issue-7 benchmark workload: camera at the origin (viewmat = I), f = 0.8 W;
    means x, y ~ U(-2, 2), z ~ U(3, 7); log scales ~ U(-4, -2) per axis; quats
    normalised Gaussian noise; opacity 0.5 + 0.1 N(0, 1) clamped to [0.05, 0.95];
    colour U(0, 1) RGB as SH degree 0 (higher bands zero).
    Returns [means, quats, log_scales, opacity_logits, sh, viewmat, K]."""
    g = torch.Generator().manual_seed(seed)
    means = torch.cat([torch.rand(n, 2, generator=g) * 4 - 2, torch.rand(n, 1, generator=g) * 4 + 3], 1)
    log_scales = torch.rand(n, 3, generator=g) * 2 - 4
    quats = torch.randn(n, 4, generator=g)
    quats = quats / quats.norm(dim=1, keepdim=True)
    op = (0.5 + 0.1 * torch.randn(n, generator=g)).clamp(0.05, 0.95)
    logits = torch.log(op / (1 - op))
    sh = torch.zeros(n, (sh_degree + 1) ** 2, 3)
    sh[:, 0] = (torch.rand(n, 3, generator=g) - 0.5) / SH_C0
    out = [means, quats, log_scales, logits, sh, torch.eye(4), intrinsics(width, height)]
    return [t.to(dtype) for t in out]
