"""The training loss: (1 - l) L1 + l (1 - SSIM), the 3DGS photometric loss.

SSIM is exactly `metrics.ssim` (same 11-tap sigma 1.5 window, constants and
valid region; tests hold them equal), computed with a depthwise convolution: the
five moment maps as 15 channels of one image, `groups=15`. On CPU that layout is
~30x faster forward+backward than a batch of 15 one-channel images (measured at
200x200: 13 ms against 390 ms), which matters because the loss runs every step.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from .metrics import _C1, _C2, SSIM_WINDOW, _gauss_1d


def ssim_fast(pred: Tensor, gt: Tensor) -> Tensor:  # [H, W, C] each in [0, 1] -> scalar
    """Mean SSIM, equal to metrics.ssim, differentiable with respect to `pred`."""
    H, W, C = pred.shape
    if H < SSIM_WINDOW or W < SSIM_WINDOW:
        raise ValueError(f"ssim needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels, got {W}x{H}")
    x = pred.permute(2, 0, 1)  # [C, H, W]
    y = gt.permute(2, 0, 1).to(x.dtype)
    stack = torch.cat([x, y, x * x, y * y, x * y], dim=0).unsqueeze(0)  # [1, 5C, H, W]
    g = _gauss_1d(x.dtype, x.device)
    k = stack.shape[1]
    m = F.conv2d(stack, g.view(1, 1, 1, -1).expand(k, 1, 1, SSIM_WINDOW).contiguous(), groups=k)
    m = F.conv2d(m, g.view(1, 1, -1, 1).expand(k, 1, SSIM_WINDOW, 1).contiguous(), groups=k)
    mu_x, mu_y, e_xx, e_yy, e_xy = m[0].split(C, dim=0)
    var_x = e_xx - mu_x * mu_x
    var_y = e_yy - mu_y * mu_y
    cov = e_xy - mu_x * mu_y
    num = (2 * mu_x * mu_y + _C1) * (2 * cov + _C2)
    den = (mu_x * mu_x + mu_y * mu_y + _C1) * (var_x + var_y + _C2)
    return (num / den).mean()


def photometric_loss(image: Tensor, target: Tensor, lambda_dssim: float = 0.2) -> Tensor:  # [H, W, 3] each
    """(1 - lambda) L1 + lambda (1 - SSIM)."""
    return (1.0 - lambda_dssim) * F.l1_loss(image, target) + lambda_dssim * (1.0 - ssim_fast(image, target))
