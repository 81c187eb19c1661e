"""The first Gaussians: from SfM points, random points in the scene bounds, or a splat file.

3DGS recipe: one Gaussian per point, isotropic log scale from the RMS distance
to the 3 nearest neighbours, identity rotation, opacity sigma^-1(0.1), SH DC
from the point colour and zero higher bands.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from ..errors import SplatError
from ..gaussians import SH_C0, Gaussians, morton_order, num_sh_bases
from ..model import load_model
from ..render.projection import in_frustum
from .config import TrainConfig
from .data import TrainData, TrainView

KNN_BLOCK = 512  # query points per distance block (memory: BLOCK x candidates floats)
CDIST_MODE = "donot_use_mm_for_euclid_dist"  # exact differences: the matmul form loses digits for flat, offset clouds
MIN_KNN_DIST = 1e-7 ** 0.5  # 3DGS clamps the squared distance at 1e-7 (coincident points)


def gaussians_from_points(
    points: Tensor,  # [P, 3] world units
    colors: Tensor,  # [P, 3] in [0, 1]
    sh_degree: int,
    init_opacity: float = 0.1,
    knn: int = 3,
) -> Gaussians:
    """One isotropic Gaussian per point (the 3DGS initialisation)."""
    p = points.shape[0]
    if p == 0:
        raise SplatError("cannot initialise from zero points")
    dist = knn_rms_distance(points, knn)  # [P]
    log_scales = dist.clamp_min(MIN_KNN_DIST).log()[:, None].repeat(1, 3)
    quats = torch.zeros(p, 4, dtype=points.dtype, device=points.device)
    quats[:, 0] = 1.0
    opacity = torch.full((p,), math.log(init_opacity / (1.0 - init_opacity)), dtype=points.dtype, device=points.device)
    sh = torch.zeros(p, num_sh_bases(sh_degree), 3, dtype=points.dtype, device=points.device)
    sh[:, 0] = (colors.to(points.dtype) - 0.5) / SH_C0  # colour = SH_C0 * dc + 0.5
    return Gaussians(points.contiguous(), quats, log_scales, opacity, sh)


def random_points(
    n: int, lo: np.ndarray, hi: np.ndarray, seed: int, device: torch.device
) -> tuple[Tensor, Tensor]:  # -> points [n, 3], colors [n, 3]
    """Uniform points (and colours) in the box [lo, hi], from `seed` only."""
    g = torch.Generator().manual_seed(int(seed))
    lo_t = torch.as_tensor(np.asarray(lo, np.float64), dtype=torch.float32)
    hi_t = torch.as_tensor(np.asarray(hi, np.float64), dtype=torch.float32)
    pts = lo_t + torch.rand(n, 3, generator=g) * (hi_t - lo_t)
    cols = torch.rand(n, 3, generator=g)
    return pts.to(device), cols.to(device)


def subsample_index(n: int, k: int, seed: int) -> Tensor:  # -> [min(n, k)] sorted indices
    """A seeded random subset of k of n indices, in increasing order."""
    if n <= k:
        return torch.arange(n)
    gen = torch.Generator().manual_seed(int(seed) + 17)
    return torch.randperm(n, generator=gen)[:k].sort().values


def subsample(g: Gaussians, n: int, seed: int) -> Gaussians:
    """A seeded random subset of `n` Gaussians (to respect --max-gaussians from step 0)."""
    return g if len(g) <= n else g.select(subsample_index(len(g), n, seed).to(g.device))


def initial_gaussians(cfg: TrainConfig, data: TrainData, device: torch.device) -> Gaussians:
    """From --init-ply (any splat file we read), else the SfM points, else random points
    in the scene box (seeded); then a seeded subset if there are more than --max-gaussians.
    SH is at the trained degree."""
    budget = cfg.refine.max_gaussians
    # mcmc starts SfM points at its own opacity; random points always at init_opacity: they
    # fill the scene box, and at 0.5 they are a fog that hides the scene (lego scored lower
    # held out from 0.5 than from 0.1)
    opacity = cfg.mcmc.init_opacity if cfg.strategy == "mcmc" and len(data.points) else cfg.init_opacity
    if cfg.init_ply:
        g = load_model(cfg.init_ply, device).gaussians.with_sh_degree(cfg.max_sh_degree).to(device, torch.float32)
        return subsample(g, budget, cfg.seed) if budget is not None else g
    if len(data.points):
        pts = torch.as_tensor(data.points, dtype=torch.float32, device=device)
        cols = torch.as_tensor(data.colors, dtype=torch.float32, device=device) / 255.0
    else:
        n = cfg.init_random_points if budget is None else min(cfg.init_random_points, budget)
        pts, cols = random_points(n, data.bounds_min, data.bounds_max, cfg.seed, device)
    far = None
    if cfg.init_far:
        far_pts, far_cols = far_points(cfg.init_far, data.train, data.center, cfg.init_far_radius * data.extent)
        if len(far_pts):
            far = gaussians_from_points(far_pts.to(device), far_cols.to(device), cfg.max_sh_degree, opacity,
                                        cfg.init_knn)
            if budget is not None:
                far = subsample(far, budget // 2, cfg.seed)
                budget -= len(far)
    if budget is not None and pts.shape[0] > budget:  # subset first: kNN scales then match the kept density
        idx = subsample_index(pts.shape[0], budget, cfg.seed).to(device)
        pts, cols = pts[idx], cols[idx]
    g = gaussians_from_points(pts, cols, cfg.max_sh_degree, opacity, cfg.init_knn)
    if far is None:
        return g
    return Gaussians(*(torch.cat([a, b]) for a, b in zip(g.as_dict().values(), far.as_dict().values())))


@torch.no_grad()
def far_points(n: int, views: list[TrainView], center: np.ndarray, radius: float) -> tuple[Tensor, Tensor]:
    """Points on a sphere about `center` [3] (n spread evenly over it: a Fibonacci lattice),
    kept where some view sees them, coloured by the mean of the pixels they fall on:
    something at a far depth for the backdrop that structure from motion leaves empty, so
    that densification need not fill it with floaters near the cameras (issue 15).
    Returns points [M, 3] and colours [M, 3] in [0, 1] on the views' device."""
    dev = views[0].image.device if views else torch.device("cpu")
    i = torch.arange(n, dtype=torch.float64, device=dev) + 0.5
    z = 1.0 - 2.0 * i / n
    r = (1.0 - z * z).clamp_min(0.0).sqrt()
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    pts = torch.as_tensor(center, dtype=torch.float64, device=dev) + radius * torch.stack(
        [r * torch.cos(phi), r * torch.sin(phi), z], dim=1)
    total = torch.zeros(n, 3, dtype=torch.float64, device=dev)
    seen = torch.zeros(n, dtype=torch.float64, device=dev)
    for v in views:
        uv, _, inside = in_frustum(pts, v.viewmat, v.K, v.camera.width, v.camera.height)
        idx = inside.nonzero().squeeze(1)
        px = uv[idx].floor().long()  # [M, 2] the pixel each falls on
        total[idx] += v.image[px[:, 1], px[:, 0]].double() / 255.0
        seen[idx] += 1
    keep = seen > 0
    return pts[keep].float(), (total[keep] / seen[keep, None]).float()


# ---- nearest neighbours -----------------------------------------------------------


def knn_rms_distance(points: Tensor, k: int = 3) -> Tensor:  # [P, 3] -> [P]
    """Exact root-mean-square distance to each point's `k` nearest other points.

    Blocks of Morton-ordered (hence spatially compact) points are compared only
    against the points inside the block's box grown by an upper bound on any of
    its points' k-th neighbour distance (taken within the block), so the result
    is exact (up to float32 rounding) while costing far less than all pairs.
    """
    pts = points.detach().to(torch.float32)
    n = pts.shape[0]
    out = torch.empty(n, dtype=torch.float32, device=pts.device)
    if n <= 1:
        return out.fill_(1.0).to(points.dtype)  # nothing to measure against: unit scale
    kk = min(k, n - 1)
    order = morton_order(pts)
    sorted_pts = pts[order]
    for s in range(0, n, KNN_BLOCK):
        q = sorted_pts[s : s + KNN_BLOCK]  # [B, 3]
        # Upper bound on every query's k-th distance: its k-th nearest within a
        # window of neighbouring blocks (Morton neighbours are spatial neighbours).
        w = sorted_pts[max(0, s - 2 * KNN_BLOCK) : s + 3 * KNN_BLOCK]
        r = float(torch.cdist(q, w).topk(kk + 1, dim=1, largest=False).values[:, -1].max())
        lo, hi = q.min(0).values - r, q.max(0).values + r
        cand = sorted_pts[((sorted_pts >= lo) & (sorted_pts <= hi)).all(dim=1)]
        d = torch.cdist(q, cand, compute_mode=CDIST_MODE).topk(kk + 1, dim=1, largest=False).values[:, 1:]  # drop the point itself
        out[order[s : s + KNN_BLOCK]] = d.square().mean(dim=1).sqrt()
    return out.to(points.dtype)
