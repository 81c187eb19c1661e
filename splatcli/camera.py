"""Pinhole cameras in the COLMAP/OpenCV frame (x right, y down, z forward).

`viewmat` maps world to camera; `K` is in pixels with pixel (u, v) sampled at its
centre (u + 0.5, v + 0.5). Cameras are kept in float64 numpy for I/O and turned
into torch tensors on the caller's device when rendering.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import torch


@dataclass(frozen=True)
class Camera:
    name: str  # image file name relative to images/ (e.g. "frame_0001.png"), or a generated id
    width: int  # pixels
    height: int  # pixels
    K: np.ndarray  # [3, 3] float64 intrinsics, pixels
    viewmat: np.ndarray  # [4, 4] float64 world-to-camera

    @property
    def center(self) -> np.ndarray:  # [3] camera centre in world units
        R, t = self.viewmat[:3, :3], self.viewmat[:3, 3]
        return -R.T @ t

    def scaled(self, factor: float) -> Camera:
        """The same camera at `factor` times the resolution (factor < 1 shrinks).
        Width and height are rounded; K is scaled by the actual size ratio so the
        image plane maps exactly (pixel-centre convention preserved)."""
        w = max(1, int(round(self.width * factor)))
        h = max(1, int(round(self.height * factor)))
        return self.resized(w, h)

    def at_resolution(self, downscale: float = 1.0, max_size: int | None = None) -> Camera:
        """The one resolution rule of train, eval and render: divide the size by
        `downscale`, then cap the longest side at `max_size` pixels."""
        c = self.scaled(1.0 / downscale) if downscale != 1.0 else self
        if max_size and max(c.width, c.height) > max_size:
            c = c.scaled(max_size / max(c.width, c.height))
        return c

    def resized(self, width: int, height: int) -> Camera:
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0, :] *= sx
        K[1, :] *= sy
        return replace(self, width=int(width), height=int(height), K=K)

    def torch(self, device: torch.device, dtype: torch.dtype = torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
        """(viewmat [4, 4], K [3, 3]) as tensors on `device`."""
        return (
            torch.as_tensor(self.viewmat, dtype=dtype, device=device),
            torch.as_tensor(self.K, dtype=dtype, device=device),
        )


@dataclass
class SceneData:
    """What `process` produced, as read back from the project's sparse model.

    cameras: one per registered image, in the order of the sorted image names.
    points / colors: SfM points [P, 3] float64 world units and [P, 3] uint8 RGB,
    or empty arrays when none exist (Blender scenes: train initialises randomly).
    """

    cameras: list[Camera]
    points: np.ndarray  # [P, 3] float64
    colors: np.ndarray  # [P, 3] uint8
    views_per_point: float = 0.0  # the mean SfM track length (0: no points, or no tracks)
    observed: dict[str, np.ndarray] = field(default_factory=dict)  # image name -> [M] int64 rows of `points` it saw


def scene_extent(cameras: list[Camera]) -> tuple[np.ndarray, float]:
    """3DGS's normalisation: centre of the camera centres and 1.1 × the largest
    distance from it (the "cameras_extent" that scales learning rates and
    densification thresholds)."""
    centers = np.stack([c.center for c in cameras]) if cameras else np.zeros((1, 3))
    mid = centers.mean(axis=0)
    radius = float(np.linalg.norm(centers - mid, axis=1).max()) * 1.1
    return mid, max(radius, 1e-6)


def focus_point(cameras: list[Camera]) -> np.ndarray | None:  # [3]
    """The point closest (least squares) to every optical axis, or None when the
    axes are near parallel or the point is behind most cameras."""
    if len(cameras) < 2:
        return None
    centers = np.stack([c.center for c in cameras])
    dirs = np.stack([c.viewmat[2, :3] for c in cameras])  # camera +z in world
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    P = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]  # [N, 3, 3] projectors off each axis
    A = P.sum(0)
    b = (P @ centers[:, :, None]).sum(0)[:, 0]
    ev = np.linalg.eigvalsh(A)
    if ev[0] < 1e-3 * ev[-1]:
        return None
    x = np.linalg.solve(A, b)
    in_front = ((x - centers) * dirs).sum(1) > 0
    return x if in_front.mean() > 0.8 else None
