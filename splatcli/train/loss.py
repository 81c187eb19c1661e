"""The training loss: (1 - l) L1 + l (1 - SSIM), the 3DGS photometric loss.

SSIM is `metrics.ssim` itself (the metric's 11-tap sigma 1.5 window, constants
and valid region), so the loss optimises exactly what `eval` reports.
"""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor

from ..eval.metrics import ssim


def photometric_loss(image: Tensor, target: Tensor, lambda_dssim: float = 0.2) -> Tensor:  # [H, W, 3] each
    """(1 - lambda) L1 + lambda (1 - SSIM)."""
    return (1.0 - lambda_dssim) * F.l1_loss(image, target) + lambda_dssim * (1.0 - ssim(image, target))
