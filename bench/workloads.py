"""The rasterizer benchmarks' workloads, for bench/peers.py and
bench/gpu.py: seeded synthetic Gaussians, and garden's real points where the data is present."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from common import data_dir
from splatcli.render.sh import SH_C0


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
    f = 0.8 * width
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    return [t.to(dtype) for t in (means, quats, log_scales, logits, sh, torch.eye(4), K)]


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
