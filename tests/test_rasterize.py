"""Fast rasterizer against the dense reference: forward, gradients, gradcheck."""

from __future__ import annotations

import pytest
import torch

from splatcli import RenderOutput, rasterize
from splatcli.render.reference import rasterize_reference


def make_scene(n: int, width: int, height: int, *, dtype=torch.float32, degree: int = 1, seed: int = 0):
    """Random Gaussians in front of an identity camera. View depths are spread over a
    permutation (gaps >= 4/n) so that float32 and float64 agree on the depth order."""
    g = torch.Generator().manual_seed(seed)
    z = 3 + 4 * torch.randperm(n, generator=g).to(dtype) / max(n, 1)
    xy = (torch.rand(n, 2, generator=g, dtype=dtype) * 4 - 2) * z[:, None] / 5
    means = torch.cat([xy, z[:, None]], 1)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    log_scales = torch.rand(n, 3, generator=g, dtype=dtype) * 2 - 4
    logits = torch.randn(n, generator=g, dtype=dtype)
    sh = torch.randn(n, (degree + 1) ** 2, 3, generator=g, dtype=dtype) * 0.5
    viewmat = torch.eye(4, dtype=dtype)
    K = torch.tensor([[0.8 * width, 0, width / 2], [0, 0.8 * width, height / 2], [0, 0, 1]], dtype=dtype)
    return [means, quats, log_scales, logits, sh, viewmat, K]


def test_api_shapes():
    args = make_scene(50, 33, 21)
    out = rasterize(*args, 33, 21)
    assert isinstance(out, RenderOutput)
    assert out.image.shape == (21, 33, 3) and out.alpha.shape == (21, 33) and out.depth.shape == (21, 33)
    assert out.means2d.shape == (50, 2) and out.radii.dtype == torch.int32 and out.visible.dtype == torch.bool
    assert out.depths.shape == (50,)


@pytest.mark.parametrize("block", [4, 8, 16])
def test_forward_matches_reference(block):
    W, H = 61, 47  # not multiples of 16
    args = make_scene(1000, W, H, degree=2)
    bg = torch.tensor([0.1, 0.2, 0.3])
    out = rasterize(*args, W, H, bg, block=block)
    with torch.no_grad():
        ref = rasterize_reference(*[a.double() for a in args], W, H, bg.double())
    assert out.image.mean() > 0.05  # a real picture, not an empty one
    torch.testing.assert_close(out.image, ref.image.float(), atol=1e-4, rtol=0)
    torch.testing.assert_close(out.alpha, ref.alpha.float(), atol=1e-4, rtol=0)
    # depth is in world units (3..7) summed with weights: 1e-4 relative to its scale
    torch.testing.assert_close(out.depth, ref.depth.float(), atol=1e-4 * 7, rtol=0)
    assert torch.equal(out.radii, ref.radii) and torch.equal(out.visible, ref.visible)


def test_gradients_match_reference():
    W, H = 37, 29
    args = [a.double().requires_grad_() for a in make_scene(300, W, H, degree=3, seed=1)]
    bg = torch.tensor([0.3, 0.5, 0.7], dtype=torch.float64, requires_grad=True)
    g = torch.Generator().manual_seed(2)
    v = torch.randn(H, W, 3, generator=g, dtype=torch.float64)
    va = torch.randn(H, W, generator=g, dtype=torch.float64)
    vd = torch.randn(H, W, generator=g, dtype=torch.float64)

    def loss(o):
        return (o.image * v).sum() + (o.alpha * va).sum() + (o.depth * vd).sum()

    xs = args + [bg]
    g_fast = torch.autograd.grad(loss(rasterize(*args, W, H, bg)), xs, allow_unused=True)
    g_ref = torch.autograd.grad(loss(rasterize_reference(*args, W, H, bg)), xs, allow_unused=True)
    for name, a, b in zip(["means", "quats", "log_scales", "opacity_logits", "sh", "viewmat", "K", "bg"], g_fast, g_ref):
        if name in ("viewmat", "K"):
            continue
        torch.testing.assert_close(a, b, atol=1e-9, rtol=1e-7, msg=name)


def test_means2d_grad_readable():
    W, H = 40, 30
    args = make_scene(100, W, H)
    ps = [a.clone().requires_grad_() for a in args[:5]]
    out = rasterize(*ps, args[5], args[6], W, H)
    out.means2d.retain_grad()
    out.image.sum().backward()
    gm = out.means2d.grad
    assert gm is not None and gm.shape == (100, 2) and torch.isfinite(gm).all()
    assert gm[out.visible].abs().sum() > 0 and (gm[~out.visible] == 0).all()
