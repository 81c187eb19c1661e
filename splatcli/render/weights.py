"""Each Gaussian's total blending weight over a set of views: sum over pixels of
w_i = alpha_i T_i. It ranks Gaussians for `train --compact` and for eval's
Gaussian-budget curve (the least-contributing go first)."""

from __future__ import annotations

from collections.abc import Iterable

import torch
from torch import Tensor

from ..gaussians import SH_C0
from .rasterize import rasterize


def blending_weights(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    log_scales: Tensor,  # [N, 3]
    opacity_logits: Tensor,  # [N]
    views: Iterable[tuple[Tensor, Tensor, int, int]],  # (viewmat [4, 4], K [3, 3], width, height)
) -> Tensor:  # [N] float64, pixels
    """Exact, through autograd: with every colour 0.5 (DC = 0 at degree 0, so the
    clamp at 0 is inactive) the red channel is sum_i w_i c_i + T bg, hence its
    gradient with respect to dc_i is SH_C0 * sum_pixels w_i, whatever the background."""
    n = means.shape[0]
    args = [t.detach() for t in (means, quats, log_scales, opacity_logits)]
    total = torch.zeros(n, dtype=torch.float64, device=means.device)
    bg = torch.zeros(3, dtype=means.dtype, device=means.device)
    for viewmat, K, width, height in views:
        dc = torch.zeros(n, 1, 3, dtype=means.dtype, device=means.device, requires_grad=True)
        out = rasterize(*args, dc, viewmat, K, width, height, bg, sh_degree=0)
        (grad,) = torch.autograd.grad(out.image[..., 0].sum(), dc)
        total += grad[:, 0, 0].to(torch.float64) / SH_C0
    return total
