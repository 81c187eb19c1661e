"""The set of Gaussians, stored raw exactly as in the .ply:

means [N, 3] world units; quats [N, 4] w,x,y,z unnormalised; log_scales [N, 3];
opacity_logits [N]; sh [N, (d+1)^2, 3], DC first.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch
import torch.nn.functional as F
from torch import Tensor

SH_C0 = 0.28209479177387814  # Y_0^0; colour = SH_C0 * dc + 0.5


def num_sh_bases(degree: int) -> int:
    return (degree + 1) ** 2


def sh_degree_from_bases(k: int) -> int:
    d = int(round(math.sqrt(k))) - 1
    if (d + 1) ** 2 != k or d < 0:
        raise ValueError(f"{k} SH coefficients per channel is not (d+1)^2 for any degree d")
    return d


@dataclass
class Gaussians:
    means: Tensor  # [N, 3]
    quats: Tensor  # [N, 4] w, x, y, z (unnormalised)
    log_scales: Tensor  # [N, 3]
    opacity_logits: Tensor  # [N]
    sh: Tensor  # [N, (d+1)^2, 3]

    PARAM_NAMES = ("means", "quats", "log_scales", "opacity_logits", "sh")

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_bases(int(self.sh.shape[1]))

    @property
    def device(self) -> torch.device:
        return self.means.device

    def as_dict(self) -> dict[str, Tensor]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def to(self, device: torch.device | str, dtype: torch.dtype | None = None) -> Gaussians:
        return Gaussians(**{k: v.to(device=device, dtype=dtype) if dtype else v.to(device) for k, v in self.as_dict().items()})

    def detach(self) -> Gaussians:
        return Gaussians(**{k: v.detach() for k, v in self.as_dict().items()})

    def select(self, mask_or_index: Tensor) -> Gaussians:
        return Gaussians(**{k: v[mask_or_index] for k, v in self.as_dict().items()})

    def with_sh_degree(self, degree: int) -> Gaussians:
        """Truncate (or zero-pad) SH to `degree`."""
        k = num_sh_bases(degree)
        sh = self.sh
        if sh.shape[1] >= k:
            sh = sh[:, :k]
        else:
            pad = sh.new_zeros(sh.shape[0], k - sh.shape[1], 3)
            sh = torch.cat([sh, pad], dim=1)
        return Gaussians(self.means, self.quats, self.log_scales, self.opacity_logits, sh.contiguous())

    def recoloured(self, transform: Tensor) -> Gaussians:  # transform [3, 4]: [A | b]
        """The model seen through a colour transform (colour -> A colour + b, what train
        --appearance exposure learns per photo), baked into the SH: every band times A, and the
        DC shifted so that the constant 0.5 maps too. Over any background it renders what the
        original renders through the transform when the background goes through it as well
        (the blending weights and what shows through sum to 1); only colours that the render
        clamps at 0 differ."""
        t = transform.to(self.sh)
        a, b = t[:, :3], t[:, 3]  # [3, 3], [3]
        sh = self.sh @ a.T  # [N, K, 3]
        sh[:, 0] += (0.5 * a.sum(1) + b - 0.5) / SH_C0  # A (0.5, 0.5, 0.5) + b - 0.5, in DC units
        return Gaussians(self.means, self.quats, self.log_scales, self.opacity_logits, sh)

    def smoothed(self, filter3d: Tensor) -> Gaussians:  # filter3d [N] world units
        """The model with a 3D smoothing filter folded in (`smooth_3d`): what it renders as."""
        ls, op = smooth_3d(self.log_scales, self.opacity_logits, filter3d)
        return Gaussians(self.means, self.quats, ls, op, self.sh)

    def finite_mask(self) -> Tensor:  # [N] bool
        ok = torch.ones(len(self), dtype=torch.bool, device=self.device)
        for v in self.as_dict().values():
            ok &= torch.isfinite(v.reshape(v.shape[0], -1)).all(dim=1)
        return ok

    @staticmethod
    def empty(sh_degree: int = 0, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32) -> Gaussians:
        z = lambda *s: torch.zeros(*s, device=device, dtype=dtype)  # noqa: E731
        return Gaussians(z(0, 3), z(0, 4), z(0, 3), z(0), z(0, num_sh_bases(sh_degree), 3))


def smooth_3d(
    log_scales: Tensor,  # [N, 3]
    opacity_logits: Tensor,  # [N]
    filter3d: Tensor,  # [N] world units, >= 0 (0: no filter)
) -> tuple[Tensor, Tensor]:  # ([N, 3], [N])
    """Mip-Splatting's 3D smoothing filter (Yu et al. 2024, eq. 9) folded into the raw
    parameters: the covariance convolved with an isotropic Gaussian of standard deviation
    `filter3d` (per axis s'^2 = s^2 + f^2) and the opacity scaled by
    sqrt(det Sigma / det Sigma') = prod s / s' in (0, 1], so the integrated mass is kept.

    In log space throughout: with d = 2 (log f - log s), log s' = log s + softplus(d) / 2
    and the log ratio L = -sum softplus(d) / 2 <= 0; the new logit is
    logit(sigmoid(o) e^L) = o + L - softplus(o + log(1 - e^L)). f = 0 gives back exactly
    the input, with finite gradients (the log(1 - e^L) branch is masked before its log).
    Differentiable in log_scales and opacity_logits; the filter is a constant."""
    f = filter3d.detach().to(log_scales.dtype)
    log_f = torch.where(f > 0, torch.log(f.clamp_min(torch.finfo(f.dtype).tiny)), float("-inf"))
    sp = F.softplus(2.0 * (log_f[:, None] - log_scales))  # [N, 3]; 0 where f = 0
    ls = log_scales + 0.5 * sp
    L = -0.5 * sp.sum(-1)  # [N] log ratio of determinants' square roots
    some = L < 0
    safe = torch.where(some, L, torch.full_like(L, -1.0))  # no log(0) and no 1/0 in its gradient
    log_gap = torch.where(some, torch.log(-torch.expm1(safe)), float("-inf"))  # log(1 - e^L)
    op = opacity_logits + L - F.softplus(opacity_logits + log_gap)
    return ls, op


def kept_count(n: int, fraction: float) -> int:
    """How many of `n` Gaussians a budget of `fraction` (in (0, 1]) keeps: the nearest whole
    number, halves up, and at least one of a non-empty set. Nearest, not floor or ceiling:
    the kept fraction is then the closest to the one asked, and floating-point noise in
    `fraction * n` cannot move the count by a whole Gaussian when the product is meant to
    be whole (0.1 * 30 is 3.0000000000000004, whose ceiling is 4; 0.29 * 100 is
    28.999999999999996, which int() cuts to 28)."""
    if n <= 0:
        return 0
    return min(n, max(1, math.floor(n * fraction + 0.5)))


def top_by_weight(weight: Tensor, k: int) -> Tensor:  # [N] -> [N] bool
    """The `k` largest entries of `weight` as a mask (ties: the lower index), the one
    top-k rule of --compact (strategy/compact.py) and eval's budgets (eval/budgets.py)."""
    keep = torch.zeros(weight.shape[0], dtype=torch.bool, device=weight.device)
    keep[torch.argsort(weight, descending=True, stable=True)[: max(k, 0)]] = True
    return keep


def morton_order(points: Tensor) -> Tensor:  # [N, 3] -> [N] int64 permutation
    """Order along a Z curve through the bounding box, 10 bits per axis (x in the lowest
    bit), stable: the one spatial order of init's nearest neighbours and of the formats
    that store Gaussians in chunks (.compressed.ply, .sog)."""
    lo = points.min(0).values
    span = (points.max(0).values - lo).clamp_min(1e-12)
    q = ((points - lo) / span * 1023).long().clamp(0, 1023)

    def spread(v: Tensor) -> Tensor:  # insert two zero bits between each of 10 bits
        v = (v | (v << 16)) & 0x030000FF
        v = (v | (v << 8)) & 0x0300F00F
        v = (v | (v << 4)) & 0x030C30C3
        return (v | (v << 2)) & 0x09249249

    return torch.argsort(spread(q[:, 0]) | (spread(q[:, 1]) << 1) | (spread(q[:, 2]) << 2), stable=True)


@dataclass
class Histogram:
    edges: list[float]  # len(counts) + 1
    counts: list[int]


def histogram(values, bins: int = 40, range_: tuple[float, float] | None = None) -> Histogram:
    """Counts of the finite `values` (a numpy array) in `bins` equal bins."""
    import numpy as np

    values = values[np.isfinite(values)]
    if values.size == 0 and range_ is None:
        range_ = (-1.0, 0.0)
    counts, edges = np.histogram(values, bins=bins, range=range_)
    return Histogram(edges=[round(float(e), 6) for e in edges], counts=[int(c) for c in counts])
