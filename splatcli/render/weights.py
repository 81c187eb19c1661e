"""Each Gaussian's total blending weight over a set of views: sum over pixels of
w_i = alpha_i T_i. It ranks Gaussians for `train --compact` and for eval's
Gaussian-budget curve (the least-contributing go first)."""

from __future__ import annotations

from collections.abc import Iterable

import torch
from torch import Tensor

from .rasterize import render_weights


def blending_weights(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    log_scales: Tensor,  # [N, 3]
    opacity_logits: Tensor,  # [N]
    views: Iterable[tuple[Tensor, Tensor, int, int]],  # (viewmat [4, 4], K [3, 3], width, height)
) -> Tensor:  # [N] float64, pixels
    """Summed from each view's forward pass (rasterize.render_weights): the compositor adds each
    slot's alpha T_before into its Gaussian's total. (The gradient of the picture with respect to
    each colour is the same sum, tests/test_eval.py checks; through autograd it took 1.7-1.8x the time.)"""
    args = [t.detach() for t in (means, quats, log_scales, opacity_logits)]
    total = torch.zeros(means.shape[0], dtype=torch.float64, device=means.device)
    for viewmat, K, width, height in views:
        total += render_weights(*args, viewmat, K, width, height).to(torch.float64)
    return total
