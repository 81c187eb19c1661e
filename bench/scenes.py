"""Seeded synthetic Gaussian scenes, for the tests (`test_scene`) and the rasterizer
benchmarks (`benchmark_scene`, `workloads`); not used by the pipeline."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from common import data_dir
from splatcli.render.sh import SH_C0


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


@dataclass
class Workload:
    name: str
    args: list  # [means, quats, log_scales, opacity_logits, sh, viewmat, K]
    width: int
    height: int


def workloads(only: list[str] | None) -> list[Workload]:
    out = []
    for n, w, h, d in [(10_000, 256, 256, 0), (10_000, 800, 600, 0), (100_000, 256, 256, 0),
                       (100_000, 800, 600, 0), (100_000, 800, 600, 3)]:
        name = f"synth-{n // 1000}k-{w if w == h else f'{w}x{h}'}" + (f"-sh{d}" if d else "")
        if only and name not in only:
            continue
        out.append(Workload(name, benchmark_scene(n, w, h, d, seed=0), w, h))
    garden = data_dir() / "garden" / "test_garden.npz"
    if (not only or "garden-648x420" in only) and garden.is_file():
        out.append(garden_workload(garden))
    elif not garden.is_file():
        print(f"garden: {garden} absent, skipped", flush=True)
    return out


def garden_workload(path: Path) -> Workload:
    d = np.load(path)
    pts = d["means3d"].astype(np.float32)
    keep = (np.abs(pts) <= 2).all(1)
    means = torch.from_numpy(pts[keep])
    colors = torch.from_numpy(d["colors"][keep].astype(np.float32) / 255.0)
    n = means.shape[0]
    g = torch.Generator().manual_seed(0)
    scales = torch.rand(n, 3, generator=g) * (0.02 - 1e-4) + 1e-4
    quats = torch.randn(n, 4, generator=g)
    quats = quats / quats.norm(dim=1, keepdim=True)
    op = torch.rand(n, generator=g).clamp(1e-4, 1 - 1e-4)
    sh = ((colors - 0.5) / SH_C0)[:, None, :]
    viewmat = torch.from_numpy(d["viewmats"][0].astype(np.float32))
    K = torch.from_numpy(d["Ks"][0].astype(np.float32))
    w, h = int(d["width"]), int(d["height"])
    return Workload(f"garden-{w}x{h}", [means, quats, scales.log(), torch.log(op / (1 - op)), sh, viewmat, K], w, h)
