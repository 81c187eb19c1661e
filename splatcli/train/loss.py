"""The training loss: (1 - l) L1 + l (1 - SSIM), the 3DGS photometric loss.

SSIM is `metrics.ssim` itself (the metric's 11-tap sigma 1.5 window, constants
and valid region), so the loss optimises exactly what `eval` reports. With a mask
(--mask-mode ignore) L1 is the mean over the kept pixels and SSIM the masked one:
masked pixels take no part, in value or gradient.

Where structure from motion left tracks, the depth term (--depth-weight) compares the render's
depth with each point a training photo observed, at the pixel that holds it.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from ..eval.metrics import ssim
from ..render.projection import NEAR, in_frustum


def photometric_loss(image: Tensor, target: Tensor, lambda_dssim: float = 0.2,  # [H, W, 3] each
                     keep: Tensor | None = None) -> Tensor:  # keep [H, W] bool, None: every pixel
    """(1 - lambda) L1 + lambda (1 - SSIM), over the kept pixels."""
    if keep is None:
        l1 = F.l1_loss(image, target)
    else:
        l1 = ((image - target).abs() * keep[..., None]).sum() / (keep.sum() * image.shape[-1]).clamp_min(1)
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - ssim(image, target, keep))


def sparse_depth_loss(depth: Tensor, alpha: Tensor, points: Tensor,  # depth, alpha [H, W]; points [M, 3] world
                      viewmat: Tensor, K: Tensor,  # viewmat [4, 4], K [3, 3]
                      keep: Tensor | None = None) -> Tensor:  # keep [H, W] bool (None: all) -> [] loss
    """Mean |log(rendered depth) - log(SfM depth)| at the pixels where the view observed its SfM
    points. The rendered depth is the blending-weighted view depth over the pixel's alpha,
    taken only where the render covers the pixel (alpha > 0.5): the term moves surfaces along
    the ray and leaves coverage to the photometric loss. Log depth makes the weight the same at
    any scene scale and for near and far points alike. `keep`: the view's mask (--mask-mode
    ignore); points on the pixels it leaves out are left out too."""
    H, W = depth.shape
    uv, z, inside = in_frustum(points, viewmat, K, W, H)  # [M, 2] px, [M], [M]: the rasterizer's near plane and image
    col, row = uv[:, 0].floor().long(), uv[:, 1].floor().long()  # the pixel holding the point
    pix = torch.where(inside, row * W + col, 0)  # [M] (0 for the points left out)
    a = alpha.reshape(-1)[pix]  # [M]
    use = inside & (a.detach() > 0.5)  # [M] (a mask, not a selection: no host sync)
    if keep is not None:
        use = use & keep.reshape(-1)[pix]
    use = use.to(depth.dtype)
    pred = depth.reshape(-1)[pix] / torch.where(use > 0, a, 1.0)  # [M] the rendered depth there
    err = (pred.clamp_min(1e-6).log() - z.clamp_min(NEAR).log()).abs()  # finite everywhere, so 0 x err is 0
    return (err * use).sum() / use.sum().clamp_min(1.0)
