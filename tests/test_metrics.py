"""PSNR and SSIM: against scikit-image and a hand computation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from splatcli.eval.metrics import _conv, _conv_t, _filter, _filter_t, psnr, ssim, ssim_map


def _pair(h: int, w: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    a = rng.random((h, w, 3))
    # a correlated, noisy, clipped copy: SSIM in a realistic range, not ~0 or ~1
    b = np.clip(a + rng.normal(0, 0.1, a.shape) + 0.05 * np.sin(np.arange(w) / 3.0)[None, :, None], 0, 1)
    return a, b


@pytest.mark.parametrize("shape,seed", [((32, 40), 0), ((11, 11), 1), ((57, 23), 2)])
def test_ssim_matches_scikit_image(shape: tuple[int, int], seed: int) -> None:
    a, b = _pair(*shape, seed)
    ref = structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                data_range=1.0, channel_axis=-1)
    got = float(ssim(torch.from_numpy(a), torch.from_numpy(b)))
    assert abs(got - ref) < 1e-4  # the bound; in float64 they agree to ~1e-12
    got32 = float(ssim(torch.from_numpy(a).float(), torch.from_numpy(b).float()))
    assert abs(got32 - ref) < 1e-4  # float32 accumulation error of the 11x11 blur is ~1e-6


def test_ssim_identical_is_one_and_map_shape() -> None:
    a = torch.rand(20, 30, 3, dtype=torch.float64)
    assert float(ssim(a, a)) == pytest.approx(1.0, abs=1e-12)
    assert ssim_map(a, a).shape == (3, 10, 20)  # valid region: 5-pixel border excluded


def test_ssim_refuses_bad_input() -> None:
    with pytest.raises(ValueError, match="at least 11x11"):
        ssim(torch.rand(10, 30, 3), torch.rand(10, 30, 3))
    with pytest.raises(ValueError, match="one shape"):
        ssim(torch.rand(12, 12, 3), torch.rand(12, 13, 3))


def test_psnr_hand_computation() -> None:
    # a 2x2 RGB image; errors 0.1 on 3 of 12 values, 0 elsewhere: MSE = 3 * 0.01 / 12
    gt = torch.zeros(2, 2, 3)
    pred = gt.clone()
    pred[0, 0, 0] = 0.1
    pred[1, 1, 2] = 0.1
    pred[0, 1, 1] = 0.1
    mse = 3 * 0.01 / 12
    expected = 10 * math.log10(1 / mse)  # 26.0206 dB
    assert float(psnr(pred, gt)) == pytest.approx(expected, abs=1e-5)  # float32 0.1 is 0.1 + 1.5e-9
    a, b = _pair(16, 16, 3)
    ref = 10 * np.log10(1 / np.mean((a - b) ** 2))
    assert float(psnr(torch.from_numpy(a), torch.from_numpy(b))) == pytest.approx(ref, abs=1e-10)


def test_psnr_of_identical_images_is_finite() -> None:
    a = torch.rand(4, 4, 3)
    assert math.isfinite(float(psnr(a, a))) and float(psnr(a, a)) >= 100


@pytest.mark.parametrize("masked", [False, True])
def test_ssim_gradcheck(masked: bool) -> None:
    # D-SSIM is a training loss: its closed-form gradient must be right, for both images and with a mask
    g = torch.Generator().manual_seed(0)
    a = torch.rand(12, 13, 2, dtype=torch.float64, generator=g, requires_grad=True)
    b = torch.rand(12, 13, 2, dtype=torch.float64, generator=g, requires_grad=True)
    keep = torch.rand(12, 13, generator=g) > 0.3 if masked else None
    assert torch.autograd.gradcheck(lambda x, y: ssim(x, y, keep), (a, b), fast_mode=True)  # random projections: 2 passes, not 312


@pytest.mark.parametrize("masked", [False, True])
def test_ssim_gradient_matches_autograd_through_the_map(masked: bool) -> None:
    """The closed-form backward against autograd through ssim_map (the reference), float32 at a
    training size, both images, through a random upstream gradient."""
    g = torch.Generator().manual_seed(1)
    a = torch.rand(64, 80, 3, generator=g, requires_grad=True)
    b = torch.rand(64, 80, 3, generator=g, requires_grad=True)
    keep = torch.rand(64, 80, generator=g) > 0.3 if masked else None
    cot = torch.randn((), generator=g)
    if keep is None:
        ref = ssim_map(a, b).mean()
    else:
        m = ssim_map(a * keep[..., None], b * keep[..., None])
        w = keep[5:-5, 5:-5].float()
        ref = (m * w).sum() / (w.sum() * m.shape[0])
    got = ssim(a, b, keep)
    assert float(got.detach()) == float(ref.detach())  # the same forward arithmetic
    ga, gb = torch.autograd.grad(got * cot, (a, b))
    ra, rb = torch.autograd.grad(ref * cot, (a, b))
    # float32 sums in another order: a few ulps of the largest entry
    for x, y in ((ga, ra), (gb, rb)):
        assert torch.allclose(x, y, rtol=0, atol=1e-5 * float(y.abs().max()))


@pytest.mark.parametrize("size", [(23, 31), (42, 75), (11, 11)], ids=["tail-blocks", "full-blocks", "one-pixel"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_ssim_window_products_equal_the_convolutions(dtype: torch.dtype, size: tuple[int, int]) -> None:
    """The CPU's window (banded matrix products, blocks of 16 rows and 32 columns, with a shorter last
    block or none) against the depthwise convolutions CUDA uses, and the transpose against the
    convolution's adjoint: <F x, y> = <x, F^T y>."""
    g = torch.Generator().manual_seed(3)
    H, W = size
    x = torch.rand(5, H, W, generator=g, dtype=dtype)
    y = torch.rand(4, H - 10, W - 10, generator=g, dtype=dtype)
    # float32: the products sum the 11 taps in another order than the convolution (and add the zero
    # entries of the band); 1e-6 is a few float32 ulps of values in [0, 1].
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(_filter(x), _conv(x), rtol=0, atol=tol)
    torch.testing.assert_close(_filter_t(y), _conv_t(y), rtol=0, atol=tol)
    torch.testing.assert_close((_filter(x[:4]) * y).sum(), (x[:4] * _filter_t(y)).sum(), rtol=1e-5, atol=0)
