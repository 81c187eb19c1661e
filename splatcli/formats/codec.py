"""What the compressed splat formats share: the Gaussians as float64 arrays, the
frame change some formats need, smallest-three quaternions, and the one-line
refusal of a file that does not hold what it claims.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..errors import SplatError
from ..gaussians import Gaussians, num_sh_bases, sh_degree_from_bases

# Signs of (x, y, z) between OpenCV's right-down-front frame and the right-up-back frame of SPZ.
YZ = (1.0, -1.0, -1.0)
MAX_RATIO = 1100  # decoded bytes per stored byte a real file can reach (deflate: ~1032); beyond it a file lies


def sh_signs(s: tuple[float, float, float]) -> np.ndarray:
    """Sign of each SH basis function (degrees 1-3, 3DGS order) under (x, y, z) -> s * (x, y, z):
    degree 1: y, z, x; degree 2: xy, yz, 3z^2-1, xz, x^2-y^2; degree 3: y(3x^2-y^2), xyz,
    y(5z^2-1), z(5z^2-3), x(5z^2-1), z(x^2-y^2), x(x^2-3y^2)."""
    x, y, z = s
    return np.array([y, z, x, x * y, y * z, 1, x * z, 1, y, x * y * z, y, z, x, z, x], dtype=np.float64)


@dataclass
class Arrays:
    """Gaussians as float32 numpy arrays (the codecs' working form; float32 as trained,
    so a million Gaussians cost their raw size once, not twice)."""

    means: np.ndarray  # [N, 3]
    quats: np.ndarray  # [N, 4] w, x, y, z, normalised, w >= 0 where it matters to a codec
    log_scales: np.ndarray  # [N, 3]
    opacity_logits: np.ndarray  # [N]
    sh: np.ndarray  # [N, K, 3], DC first

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_bases(self.sh.shape[1])

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @staticmethod
    def of(g: Gaussians) -> tuple[Arrays, int]:
        """The finite rows of `g` (quaternions normalised), and how many were dropped."""
        f32 = lambda t: t.detach().to(device="cpu", dtype=torch.float32).numpy()  # noqa: E731  (no copy when already so)
        means, quats, ls, op, sh = (f32(g.means), f32(g.quats), f32(g.log_scales), f32(g.opacity_logits), f32(g.sh))
        qn = np.linalg.norm(quats.astype(np.float64), axis=1)
        ok = (np.isfinite(means).all(1) & np.isfinite(quats).all(1) & np.isfinite(ls).all(1) & np.isfinite(op)
              & np.isfinite(sh.reshape(len(sh), -1)).all(1) & (qn > 0))
        if ok.all():  # the common case: no copies
            return Arrays(means, (quats / qn[:, None]).astype(np.float32), ls, op, sh), 0
        a = Arrays(means[ok], (quats[ok] / qn[ok, None]).astype(np.float32), ls[ok], op[ok], sh[ok])
        return a, int((~ok).sum())

    def gaussians(self, device: torch.device | str = "cpu") -> Gaussians:
        t = lambda x: torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32)).to(device)  # noqa: E731
        return Gaussians(t(self.means), t(self.quats), t(self.log_scales), t(self.opacity_logits), t(self.sh))

    def flip(self, s: tuple[float, float, float] = YZ, sh: bool = True) -> Arrays:
        """The same Gaussians with axes negated where `s` (x, y, z signs) is -1; the default
        YZ is a half turn about x, OpenCV <-> right-up-back. With `sh=False` the SH is left
        as it is (a caller that flips it block by block, with `flip_sh`, never holds a
        second copy)."""
        x, y, z = s
        q = self.quats * np.array([1.0, y * z, x * z, x * y], self.quats.dtype)  # w never changes
        return Arrays(self.means * np.array(s, self.means.dtype), q, self.log_scales,
                      self.opacity_logits, flip_sh(self.sh.copy(), s) if sh else self.sh)


def flip_sh(sh: np.ndarray, s: tuple[float, float, float] = YZ) -> np.ndarray:  # [M, K, 3], in place, returned
    """SH coefficients under (x, y, z) -> s * (x, y, z) (sh_signs; DC unchanged)."""
    k = sh.shape[1] - 1
    sh[:, 1:] *= sh_signs(s)[:k, None].astype(sh.dtype)
    return sh


def blocks(n: int, size: int = 65536) -> list[slice]:
    """Row blocks: per-coefficient work on a million Gaussians in a few MB at a time."""
    return [slice(i, min(i + size, n)) for i in range(0, n, size)]


def sigmoid(x: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * x))  # no overflow warnings for large |x|


def logit(p: np.ndarray, eps: float) -> np.ndarray:
    p = np.clip(p, eps, 1.0 - eps)  # a stored 0 or 1 stays finite
    return np.log(p) - np.log1p(-p)


def pack_smallest_three(q: np.ndarray, order: tuple[int, ...] = (0, 1, 2, 3)) -> tuple[np.ndarray, np.ndarray]:
    """Quaternions [N, 4] (w, x, y, z) -> (index of the largest component in `order`,
    [N, 3] the other three in `order`, each in [-1/sqrt2, 1/sqrt2]). The quaternion is
    negated where needed so that the dropped component is positive."""
    a = q[:, list(order)]
    big = np.abs(a).argmax(axis=1)
    a = a * np.where(a[np.arange(len(a)), big] < 0, -1.0, 1.0)[:, None]
    keep = np.ones_like(a, dtype=bool)
    keep[np.arange(len(a)), big] = False
    return big, a[keep].reshape(-1, 3)


def unpack_smallest_three(big: np.ndarray, rest: np.ndarray, order: tuple[int, ...] = (0, 1, 2, 3)) -> np.ndarray:
    """Inverse of pack_smallest_three: -> [N, 4] (w, x, y, z)."""
    n = len(big)
    a = np.zeros((n, 4))
    keep = np.ones((n, 4), dtype=bool)
    keep[np.arange(n), big] = False
    a[keep] = rest.reshape(-1)
    a[np.arange(n), big] = np.sqrt(np.clip(1.0 - (rest ** 2).sum(1), 0.0, None))
    q = np.zeros_like(a)
    q[:, list(order)] = a
    return q


def check_sh_degree(degree: int, where: Path) -> int:
    if not 0 <= degree <= 3:
        raise SplatError(f"{where}: SH degree {degree} is not 0-3")
    return num_sh_bases(degree)


def refuse(path: Path, what: str) -> SplatError:
    return SplatError(f"{path}: {what}")
