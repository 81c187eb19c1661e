"""The training loss is 0.8 L1 + 0.2 (1 - SSIM) with the metric's SSIM, and that
SSIM is differentiable (float64 gradcheck)."""

from __future__ import annotations

import pytest
import torch

from splatcli.eval.metrics import ssim
from splatcli.train.loss import photometric_loss


def test_ssim_gradcheck():
    g = torch.Generator().manual_seed(3)
    a = torch.rand(12, 13, 3, generator=g, dtype=torch.float64, requires_grad=True)
    b = torch.rand(12, 13, 3, generator=g, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda x: ssim(x, b), (a,))


def test_loss_is_l1_plus_dssim():
    g = torch.Generator().manual_seed(4)
    a, b = torch.rand(20, 20, 3, generator=g), torch.rand(20, 20, 3, generator=g)
    want = 0.8 * (a - b).abs().mean() + 0.2 * (1 - ssim(a, b))
    torch.testing.assert_close(photometric_loss(a, b, 0.2), want, rtol=1e-6, atol=1e-6)  # float32 sums
    assert float(photometric_loss(a, a, 0.2)) == pytest.approx(0.0, abs=1e-6)
    with pytest.raises(ValueError):
        ssim(torch.rand(10, 30, 3), torch.rand(10, 30, 3))
