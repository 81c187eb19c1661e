"""The training loss is 0.8 L1 + 0.2 (1 - SSIM) with the metric's SSIM, and that
SSIM is differentiable (float64 gradcheck)."""

from __future__ import annotations

import math

import pytest
import torch

from splatcli.eval.metrics import ssim
from splatcli.train.loss import photometric_loss, sparse_depth_loss


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


def _view(f: float = 20.0, w: int = 16, h: int = 12) -> tuple[torch.Tensor, torch.Tensor]:
    K = torch.tensor([[f, 0.0, w / 2], [0.0, f, h / 2], [0.0, 0.0, 1.0]])
    return torch.eye(4), K  # camera at the origin looking down +z


def test_sparse_depth_loss_is_the_log_depth_error_at_the_observed_pixels():
    vm, K = _view()
    depth = torch.full((12, 16), 2.0)  # unnormalised: 2.5 x alpha 0.8
    alpha = torch.full((12, 16), 0.8)
    depth[3, 10] = 0.8 * 5.0  # the pixel holding the second point renders at depth 5
    pts = torch.tensor([[0.0, 0.0, 2.5],  # pixel (8, 6): rendered 2.5, no error
                        [0.2, -0.3, 2.0],  # u = 8 + 20 * 0.1 = 10, v = 6 - 3 = 3: rendered 5 against 2
                        [5.0, 0.0, 1.0],  # outside the image: left out
                        [0.0, 0.0, -1.0]])  # behind the camera: left out
    got = sparse_depth_loss(depth, alpha, pts, vm, K)
    assert float(got) == pytest.approx(0.5 * abs(math.log(5.0 / 2.0)), rel=1e-5)
    keep = torch.ones(12, 16, dtype=torch.bool)
    keep[3, 10] = False  # the mask removes the second point's pixel: only the first counts
    assert float(sparse_depth_loss(depth, alpha, pts, vm, K, keep)) == pytest.approx(0.0, abs=1e-6)
    alpha[3, 10] = 0.3  # an uncovered pixel: the photometric loss's business, not this term's
    assert float(sparse_depth_loss(depth, alpha, pts, vm, K)) == pytest.approx(0.0, abs=1e-6)


def test_sparse_depth_loss_moves_the_depth_towards_the_point():
    vm, K = _view()
    depth = torch.full((12, 16), 3.0, requires_grad=True)
    alpha = torch.ones(12, 16, requires_grad=True)
    sparse_depth_loss(depth, alpha, torch.tensor([[0.0, 0.0, 2.0]]), vm, K).backward()
    assert depth.grad[6, 8] > 0 and alpha.grad[6, 8] < 0  # too far: less depth, or more coverage at it
    assert int((depth.grad != 0).sum()) == 1
    nothing = sparse_depth_loss(depth, alpha, torch.tensor([[0.0, 0.0, -2.0]]), vm, K)
    assert float(nothing.detach()) == 0.0 and nothing.requires_grad  # no usable point: a zero that backpropagates


def test_scene_lists_the_points_each_image_observed():
    from colmap_models import synthetic_model

    model = synthetic_model(num_images=4, num_points=30, camera_model="PINHOLE")
    pts, _ = model.points()
    obs = model.observations()
    assert sorted(obs) == model.registered_names()
    for name, view in model.views().items():
        rows = obs[name]
        assert len(rows) > 0 and rows.max() < len(pts)
        cam = (view.pose[:, :3] @ pts[rows].T + view.pose[:, 3:]).T  # [M, 3]
        assert (cam[:, 2] > 0).all()  # the points it observed lie in front of it
