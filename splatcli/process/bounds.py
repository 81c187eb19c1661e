"""Scene bounds: from SfM points, or from the camera frustums when there are none.

Training initialises Gaussians randomly inside these bounds when the dataset has
no points (NeRF Blender scenes), so frustum bounds aim at the region most
cameras see, not at the cameras themselves.
"""

from __future__ import annotations

import numpy as np

from ..camera import Camera, focus_point


def points_bounds(points: np.ndarray, lo: float = 0.5, hi: float = 99.5) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis percentiles of points [P, 3]: robust to the stray far points SfM leaves."""
    return np.percentile(points, lo, axis=0), np.percentile(points, hi, axis=0)


def _half_fov(c: Camera) -> float:
    return float(np.arctan(min(c.width / (2 * c.K[0, 0]), c.height / (2 * c.K[1, 1]))))


def frustum_bounds(cameras: list[Camera], *, min_fraction: float = 0.9, grid: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """The box around the points seen by at least `min_fraction` of the cameras,
    searched near the cameras' common focus."""
    centers = np.stack([c.center for c in cameras])
    dirs = np.stack([c.viewmat[2, :3] for c in cameras])
    focus = focus_point(cameras)
    spread = float(np.linalg.norm(centers - centers.mean(0), axis=1).max()) if len(cameras) > 1 else 0.0
    if focus is None:  # forward-facing capture: look ahead of the cameras
        depth = max(2.0 * spread, 1.0)
        focus = centers.mean(0) + dirs.mean(0) / max(np.linalg.norm(dirs.mean(0)), 1e-9) * depth
    dist = np.linalg.norm(centers - focus, axis=1)
    radius = float(np.median(dist * np.tan([_half_fov(c) for c in cameras])))
    radius = max(radius, 1e-6)
    # Sample a grid around the focus and keep the points most cameras see.
    g = np.linspace(-1.5 * radius, 1.5 * radius, grid)
    pts = focus + np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)  # [G^3, 3]
    seen = np.zeros(len(pts))
    for c in cameras:
        cam = pts @ c.viewmat[:3, :3].T + c.viewmat[:3, 3]
        z = cam[:, 2]
        ok = z > 1e-6
        u = c.K[0, 0] * cam[:, 0] / np.where(ok, z, 1) + c.K[0, 2]
        v = c.K[1, 1] * cam[:, 1] / np.where(ok, z, 1) + c.K[1, 2]
        seen += ok & (u >= 0) & (u <= c.width) & (v >= 0) & (v <= c.height)
    keep = pts[seen >= min_fraction * len(cameras)]
    if len(keep) < 8:
        return focus - radius, focus + radius
    step = g[1] - g[0]
    return keep.min(0) - step / 2, keep.max(0) + step / 2


def depth_bounds(cameras: list[Camera], near: np.ndarray, far: np.ndarray, grid: int = 5,
                 lo: float = 2.0, hi: float = 98.0) -> tuple[np.ndarray, np.ndarray]:
    """The box around what the cameras see between each one's near and far depths
    (near, far: [N] world units, LLFF's bounds): per-axis percentiles of points spread
    over every frustum slice, so one camera's distant far plane does not inflate it."""
    pts = []
    uv = (np.arange(grid) + 0.5) / grid
    for c, n, f in zip(cameras, near, far):
        u, v = np.meshgrid(uv * c.width, uv * c.height, indexing="ij")
        rays = np.stack([(u.ravel() - c.K[0, 2]) / c.K[0, 0], (v.ravel() - c.K[1, 2]) / c.K[1, 1],
                         np.ones(u.size)], 1)  # [G^2, 3] camera space at depth 1
        for d in np.geomspace(n, f, grid):
            cam = rays * d
            pts.append((cam - c.viewmat[:3, 3]) @ c.viewmat[:3, :3])  # world = R^T (x - t)
    allp = np.concatenate(pts)
    return np.percentile(allp, lo, axis=0), np.percentile(allp, hi, axis=0)
