"""What a smaller model costs: each Gaussian's contribution to the training views and
the model kept at a budget (eval's render-time-against-PSNR curve).

A Gaussian's contribution is its total blending weight sum_pixels alpha_i T_i over
the training views (render/weights.py, exact through autograd).
"""

from __future__ import annotations

from collections.abc import Sequence

from torch import Tensor

from ..camera import Camera
from ..gaussians import Gaussians, kept_count, top_by_weight
from ..render.weights import blending_weights


def contributions(g: Gaussians, cams: Sequence[Camera]) -> Tensor:  # -> [N] total blending weight, pixels
    """sum over views and pixels of alpha_i T_i, exactly (render.weights)."""
    return blending_weights(g.means, g.quats, g.log_scales, g.opacity_logits,
                            (cam.torch(g.device, g.means.dtype) + (cam.width, cam.height) for cam in cams))


def prune_to(g: Gaussians, weight: Tensor, fraction: float) -> Gaussians:  # weight [N]
    """The `fraction` of the Gaussians with the largest weight (gaussians.kept_count and
    top_by_weight: the rules --compact uses), in their original order (depth sorting does
    not care, files diff better)."""
    k = kept_count(len(g), fraction)
    if k >= len(g):
        return g
    return g.select(top_by_weight(weight, k))
