"""The training loss: (1 - l) L1 + l (1 - SSIM), the 3DGS photometric loss.

SSIM is `metrics.ssim` itself (the metric's 11-tap sigma 1.5 window, constants
and valid region), so the loss optimises exactly what `eval` reports. With a mask
(--mask-mode ignore) L1 is the mean over the kept pixels and SSIM the masked one:
masked pixels take no part, in value or gradient.
"""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor

from ..eval.metrics import ssim


def photometric_loss(image: Tensor, target: Tensor, lambda_dssim: float = 0.2,  # [H, W, 3] each
                     keep: Tensor | None = None) -> Tensor:  # keep [H, W] bool, None: every pixel
    """(1 - lambda) L1 + lambda (1 - SSIM), over the kept pixels."""
    if keep is None:
        l1 = F.l1_loss(image, target)
    else:
        l1 = ((image - target).abs() * keep[..., None]).sum() / (keep.sum() * image.shape[-1]).clamp_min(1)
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - ssim(image, target, keep))
