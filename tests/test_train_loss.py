"""The training loss's fast SSIM is the metric's SSIM (forward and gradient)."""

from __future__ import annotations

import pytest
import torch

from splatcli.loss import photometric_loss, ssim_fast
from splatcli.metrics import ssim


@pytest.mark.parametrize("h,w", [(11, 11), (32, 45), (40, 48)])
def test_ssim_fast_matches_metric_forward_and_gradient(h, w):
    g = torch.Generator().manual_seed(h * w)
    a = torch.rand(h, w, 3, generator=g, dtype=torch.float64, requires_grad=True)
    b = torch.rand(h, w, 3, generator=g, dtype=torch.float64)
    v = torch.randn((), generator=g, dtype=torch.float64)
    torch.testing.assert_close(ssim_fast(a, b), ssim(a, b), rtol=0, atol=1e-12)
    (ga,) = torch.autograd.grad(ssim_fast(a, b) * v, a)
    (gr,) = torch.autograd.grad(ssim(a, b) * v, a)
    torch.testing.assert_close(ga, gr, rtol=1e-9, atol=1e-12)


def test_ssim_fast_gradcheck():
    g = torch.Generator().manual_seed(3)
    a = torch.rand(12, 13, 3, generator=g, dtype=torch.float64, requires_grad=True)
    b = torch.rand(12, 13, 3, generator=g, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda x: ssim_fast(x, b), (a,))


def test_loss_is_l1_plus_dssim():
    g = torch.Generator().manual_seed(4)
    a, b = torch.rand(20, 20, 3, generator=g), torch.rand(20, 20, 3, generator=g)
    want = 0.8 * (a - b).abs().mean() + 0.2 * (1 - ssim(a, b))
    torch.testing.assert_close(photometric_loss(a, b, 0.2), want, rtol=1e-6, atol=1e-6)  # float32 sums
    assert float(photometric_loss(a, a, 0.2)) == pytest.approx(0.0, abs=1e-6)
    with pytest.raises(ValueError):
        ssim_fast(torch.rand(10, 30, 3), torch.rand(10, 30, 3))
