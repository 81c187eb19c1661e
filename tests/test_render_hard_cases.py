"""Hard cases for the rasterizer: each asserts finite outputs and gradients and the
right picture (often against the dense float64 reference).

Tolerances: float64 fast path against the float64 reference, atol 1e-9 (the two differ
only by rounding: different formulas for the same quantities); float32 against
float64, atol 1e-4 (issue 7's bound)."""

from __future__ import annotations

import math

import pytest
import torch

from splatcli import rasterize
from splatcli.render.reference import rasterize_reference
from support.scenes import test_scene as make_scene

W, H = 24, 20
K = torch.tensor([[20.0, 0.0, 12.0], [0.0, 20.0, 10.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
EYE = torch.eye(4, dtype=torch.float64)
BG = torch.tensor([0.25, 0.5, 0.75], dtype=torch.float64)


def gaussians(means, log_scales=-1.0, logits=2.0, quats=None, colors=None, dtype=torch.float64):
    means = torch.as_tensor(means, dtype=torch.float64).reshape(-1, 3)
    n = means.shape[0]
    ls = torch.as_tensor(log_scales, dtype=torch.float64)
    ls = ls.expand(n, 3).clone() if ls.dim() <= 1 else ls
    lo = torch.as_tensor(logits, dtype=torch.float64).expand(n).clone()
    q = torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64).expand(n, 4).clone() if quats is None else torch.as_tensor(quats, dtype=torch.float64).reshape(n, 4)
    g = torch.Generator().manual_seed(n)
    c = torch.rand(n, 3, generator=g, dtype=torch.float64) if colors is None else torch.as_tensor(colors, dtype=torch.float64)
    sh = ((c - 0.5) / 0.28209479177387814)[:, None, :]
    return [t.to(dtype) for t in (means, q, ls, lo, sh)]


def render(params, *, width=W, height=H, viewmat=EYE, K=K, bg=BG, check_grads=True, **kw):
    """Render with gradients on; assert everything that comes out is finite."""
    dt = params[0].dtype
    xs = [p.detach().clone().requires_grad_(True) for p in params]
    bgx = bg.to(dt).clone().requires_grad_(True)
    out = rasterize(*xs, viewmat.to(dt), K.to(dt), width, height, bgx, **kw)
    out.means2d.retain_grad()
    for t in (out.image, out.alpha, out.depth, out.means2d, out.depths):
        assert torch.isfinite(t).all()
    if check_grads:
        g = torch.Generator().manual_seed(0)
        v = torch.randn(out.image.shape, generator=g, dtype=dt)
        (out.image * v + out.alpha[..., None] + out.depth[..., None]).sum().backward()
        for x in xs + [bgx, out.means2d]:
            assert x.grad is not None and torch.isfinite(x.grad).all()
    return out, xs


def reference(params, *, width=W, height=H, viewmat=EYE, K=K, bg=BG, **kw):
    with torch.no_grad():
        return rasterize_reference(*[p.double() for p in params], viewmat, K, width, height, bg, **kw)


def assert_background(out, bg=BG):
    torch.testing.assert_close(out.image, bg.to(out.image.dtype).expand_as(out.image))
    assert (out.alpha == 0).all() and (out.depth == 0).all()


def test_behind_the_camera():
    p = gaussians([[0, 0, -5.0], [0.1, 0, -0.1], [0, 0.2, -50]], log_scales=0.5, logits=5)
    out, xs = render(p)
    assert_background(out)
    assert not out.visible.any() and (out.radii == 0).all()
    assert all((x.grad == 0).all() for x in xs)


def test_straddling_the_near_plane():
    # centre 0.05 in front of the camera (behind near = 0.2) but 1 unit wide: culled by its centre
    # like 3DGS; the second one is just in front of near and covers the screen
    p = gaussians([[0, 0, 0.05], [0.02, -0.01, 0.3]], log_scales=torch.tensor([[0.0, 0.0, 0.0], [-2.0, -2.5, -1.0]]))
    out, xs = render(p)
    assert out.visible.tolist() == [False, True]
    ref = reference(p)
    torch.testing.assert_close(out.image, ref.image, atol=1e-9, rtol=0)
    assert out.alpha.min() > 0.05  # the near one covers the whole image
    assert (xs[0].grad[0] == 0).all() and xs[0].grad[1].abs().sum() > 0
    out2, _ = render(p, near=0.01)  # configurable near plane
    assert out2.visible.all()


def test_exactly_at_the_camera_centre():
    p = gaussians([[0.0, 0.0, 0.0], [0.0, 0.0, 4.0]], log_scales=-1.5)
    out, xs = render(p)
    assert out.visible.tolist() == [False, True]
    assert (xs[0].grad[0] == 0).all() and (xs[4].grad[0] == 0).all()
    torch.testing.assert_close(out.image, reference(p).image, atol=1e-9, rtol=0)


def test_far_off_screen():
    p = gaussians([[1e4, 0, 5.0], [0, -3e3, 5.0], [1e6, 1e6, 0.25]], log_scales=-1.0, logits=5)
    out, xs = render(p)
    assert_background(out)
    assert not out.visible.any()
    assert all((x.grad == 0).all() for x in xs)


def test_at_the_fov_clamp():
    # x/z = 2.5 tan(half fov): J is evaluated at the clamp (1.3 tan); a wide Gaussian still
    # reaches into the image from the right
    tan_half = (W / 2) / 20.0
    p = gaussians([[2.5 * tan_half * 4.0, 0.0, 4.0], [1.3 * tan_half * 4.0, 0.5, 4.0]], log_scales=torch.tensor([[0.7, 0.0, 0.0], [-1.0, -1.0, -1.0]]))
    out, _ = render(p)
    ref = reference(p)
    torch.testing.assert_close(out.image, ref.image, atol=1e-9, rtol=0)
    assert out.visible.all() and out.alpha[:, -1].max() > 0.1


def test_needle_thin():
    # scale ratio 1e6, long axis in the image plane along the diagonal
    c, s = math.cos(math.pi / 8), math.sin(math.pi / 8)  # 45 degrees about z
    p = gaussians([[0, 0, 4.0]], log_scales=torch.tensor([[1.5, 1.5 + math.log(1e-6), 1.5 + math.log(1e-6)]]), logits=4, quats=[[c, 0, 0, s]])
    out, _ = render(p)
    torch.testing.assert_close(out.image, reference(p).image, atol=1e-9, rtol=0)
    diag = torch.stack([out.alpha[i, i + 2] for i in range(H)])
    assert diag[4:16].min() > 0.9  # on the line (these pixel centres lie exactly on it)
    assert out.alpha[0, -1] == 0 and out.alpha[-1, 0] == 0  # far from it: nothing
    out32, _ = render([t.float() for t in p])  # float32: the 2D determinant must not cancel
    torch.testing.assert_close(out32.image, out.image.float(), atol=1e-4, rtol=0)


def test_huge_covering_the_whole_screen():
    p = gaussians([[0, 0, 5.0]], log_scales=math.log(100.0), logits=0.0)
    out, xs = render(p)
    # sigma is ~400 px: across these 31 px, G stays above exp(-0.5 (16 / 400)^2) > 0.999
    assert 0.4995 < out.alpha.min() and out.alpha.max() <= 0.5
    torch.testing.assert_close(out.image, reference(p).image, atol=1e-9, rtol=0)
    assert out.visible.all() and out.radii[0] > 1000
    out32, _ = render([t.float() for t in p])
    torch.testing.assert_close(out32.alpha, out.alpha.float(), atol=1e-5, rtol=0)  # float32, smooth picture


def test_near_singular_2d_covariance():
    # a flat disk seen exactly edge-on: its 2D covariance is rank 1 before the 0.3 px blur
    q = [math.cos(math.pi / 4), 0, math.sin(math.pi / 4), 0]  # normal (z) turned to x
    p = gaussians([[0.0, 0.0, 4.0]], log_scales=torch.tensor([[-1.0, -1.0, -30.0]]), logits=3, quats=[q])
    out, _ = render(p)
    torch.testing.assert_close(out.image, reference(p).image, atol=1e-9, rtol=0)
    # a vertical line: sigma across is the 0.3 px^2 blur alone, along it ~1.8 px
    assert out.alpha[10, 11] > 0.5 and out.alpha[6, 11] > 0.01 and out.alpha[10, 14] < 0.05
    out32, _ = render([t.float() for t in p])
    torch.testing.assert_close(out32.image, out.image.float(), atol=1e-4, rtol=0)


def test_opacity_logits_plus_minus_30():
    p = gaussians([[0, 0, 4.0]], log_scales=-0.5, logits=30.0)
    K_c = K.clone()
    K_c[0, 2], K_c[1, 2] = 12.5, 10.5  # a pixel centre exactly at the mean
    out, xs = render(p, K=K_c)
    assert abs(float(out.alpha[10, 12].detach()) - 0.99) < 1e-12  # clamped at 0.99
    out, xs = render(gaussians([[0, 0, 4.0]], log_scales=-0.5, logits=-30.0))
    assert_background(out)
    for dt in (torch.float32, torch.float64):
        render(gaussians([[0, 0, 4.0]], log_scales=-0.5, logits=30.0, dtype=dt))


def test_zero_norm_and_huge_quaternions():
    q0 = torch.tensor([[0.9, 0.3, -0.2, 0.1]])
    base = gaussians([[0, 0, 4.0]], log_scales=torch.tensor([[-0.5, -1.5, -1.0]]), quats=q0, dtype=torch.float32)
    want, _ = render(base)
    huge = list(base)
    huge[1] = base[1] * 1e30
    got, xs = render(huge)
    torch.testing.assert_close(got.image, want.image, atol=1e-6, rtol=0)  # float32 rounding of q / |q|
    zero = list(base)
    zero[1] = torch.zeros(1, 4)
    ident = list(base)
    ident[1] = torch.tensor([[1.0, 0, 0, 0]])
    got, xs = render(zero)
    torch.testing.assert_close(got.image, render(ident)[0].image)


def test_ten_thousand_stacked_on_one_pixel():
    n = 10_000
    z = 3 + 4 * torch.arange(n, dtype=torch.float64) / n
    means = torch.stack([torch.zeros(n), torch.zeros(n), z], 1) * torch.tensor([1.0, 1.0, 1.0], dtype=torch.float64)
    p = gaussians(means, log_scales=-1.2, logits=1.0)
    out, xs = render(p, width=16, height=16, K=torch.tensor([[20.0, 0, 8], [0, 20, 8], [0, 0, 1]], dtype=torch.float64))
    ref = reference(p, width=16, height=16, K=torch.tensor([[20.0, 0, 8], [0, 20, 8], [0, 0, 1]], dtype=torch.float64))
    torch.testing.assert_close(out.image, ref.image, atol=1e-9, rtol=0)
    T = 1 - out.alpha
    assert T.min() >= 1e-4 and T[8, 8] < 1e-2  # saturated, and stopped before T < 1e-4
    # early stop: the Gaussians behind the stopping point get no colour gradient
    assert xs[4].grad[-100:].abs().max() == 0 and xs[4].grad[:10].abs().max() > 0


def test_empty_scene():
    p = [torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 1, 3)]
    out, xs = render(p)
    assert_background(out, BG.float())
    assert out.means2d.shape == (0, 2) and out.radii.shape == (0,) and out.visible.shape == (0,)


@pytest.mark.parametrize("size", [(1, 1), (17, 33), (33, 5)])
def test_odd_image_sizes(size):
    w, h = size
    g = torch.Generator().manual_seed(w * 100 + h)
    n = 60
    means = torch.cat([torch.rand(n, 2, generator=g, dtype=torch.float64) * 2 - 1, 3 + 3 * torch.randperm(n, generator=g)[:, None].double() / n], 1)
    Kx = torch.tensor([[2.0 * w, 0, w / 2], [0, 2.0 * w, h / 2], [0, 0, 1]], dtype=torch.float64)
    p = gaussians(means, log_scales=-1.0, logits=0.5)
    out, _ = render(p, width=w, height=h, K=Kx)
    assert out.image.shape == (h, w, 3)
    torch.testing.assert_close(out.image, reference(p, width=w, height=h, K=Kx).image, atol=1e-9, rtol=0)


def test_float32_vs_float64():
    args = make_scene(400, 40, 30, sh_degree=2)
    o64 = rasterize(*args, 40, 30)
    o32 = rasterize(*[a.float() for a in args], 40, 30)
    assert o32.image.dtype == torch.float32 and o64.image.dtype == torch.float64
    torch.testing.assert_close(o32.image, o64.image.float(), atol=1e-4, rtol=0)
    torch.testing.assert_close(o32.alpha, o64.alpha.float(), atol=1e-4, rtol=0)
