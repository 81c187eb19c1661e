"""What a smaller model costs: each Gaussian's contribution to the training views and
the model kept at a budget (eval's render-time-against-PSNR curve).

A Gaussian's contribution is its total blending weight sum_pixels alpha_i T_i over
the training views (render/weights.py, exact through autograd).
"""

from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import Tensor

from ..camera import Camera
from ..gaussians import Gaussians
from ..render.weights import blending_weights


def contributions(g: Gaussians, cams: Sequence[Camera]) -> Tensor:  # -> [N] total blending weight, pixels
    """sum over views and pixels of alpha_i T_i, exactly (render.weights)."""
    return blending_weights(g.means, g.quats, g.log_scales, g.opacity_logits,
                            (cam.torch(g.device, g.means.dtype) + (cam.width, cam.height) for cam in cams))


def prune_to(g: Gaussians, weight: Tensor, fraction: float) -> Gaussians:  # weight [N]
    """The `fraction` of the Gaussians with the largest weight (ties: lower index first)."""
    k = max(1, int(math.ceil(fraction * len(g))))
    if k >= len(g):
        return g
    order = torch.argsort(-weight, stable=True)[:k]
    keep, _ = torch.sort(order)  # keep the original order (depth sorting does not care, files diff better)
    return g.select(keep)
