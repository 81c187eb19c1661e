"""The fused projection (`projection.project`, a hand-written backward) against its autograd
twin (`reference.project_autograd`): forward and backward through random cotangents, float64
gradcheck, and the cull: it changes no picture, bit for bit, and culled rows get exactly zero
gradients.

Tolerances: float64 both ways differ only by rounding (different formulas for the same
quantities), hence 1e-10 relative to each tensor's scale; float32, 1e-4 relative (an ulp is
6e-8, and the chains here are tens of operations long)."""

from __future__ import annotations

import math

import pytest
import torch

import splatcli.render.projection as P
from splatcli import rasterize
from splatcli.render.reference import project_autograd
from splatcli.render.sh import sh_basis, sh_basis_rows_backward
from support.scenes import test_scene as make_scene

W, H = 37, 29
OUTS = ("means2d", "conics", "opacities", "colors", "depths")
INPUTS = ("means", "quats", "log_scales", "opacity_logits", "sh", "viewmat", "K")


def hard_scene(dtype, n=300, seed=1):
    """A random scene with rows behind the camera, off screen, beyond the FOV clamp yet
    reaching into the image, and a needle-thin one."""
    args = make_scene(n, W, H, sh_degree=3, seed=seed, dtype=torch.float64)
    R, t = args[5][:3, :3], args[5][:3, 3]
    pc = args[0] @ R.T + t
    pc[:5, 2] = -1.0  # behind the camera
    pc[5:15, :2] *= 4.0  # off screen, or beyond the FOV clamp (|x/z| up to 3 tan(half fov))
    args[2][5:15] += 1.5  # wide enough that some still reach into the image
    args[2][15] = torch.tensor([0.5, math.log(1e-6), math.log(1e-6)])  # needle-thin
    args[0] = (pc - t) @ R
    return [a.to(dtype) for a in args]


@pytest.fixture
def no_cull(monkeypatch):
    monkeypatch.setattr(P, "_cull", lambda z, *a: torch.ones_like(z, dtype=torch.bool))


def run(fn, args, deg, aa, seed=3):
    """Outputs and the gradients of every input through a random cotangent on every output."""
    xs = [a.detach().clone().requires_grad_(True) for a in args]
    pr = fn(*xs, W, H, deg, antialiased=aa)
    outs = [getattr(pr, k) for k in OUTS]
    g = torch.Generator().manual_seed(seed)
    torch.autograd.backward(outs, [torch.randn(o.shape, generator=g, dtype=o.dtype) for o in outs])
    return pr, dict(zip(INPUTS, (x.grad for x in xs)))


def close(a, b, rel, name):
    scale = max(float(b.detach().abs().max()), 1e-30) if b.numel() else 1.0
    torch.testing.assert_close(a, b, atol=rel * scale, rtol=0, msg=name)


@pytest.mark.parametrize("dtype, rel", [(torch.float64, 1e-10), (torch.float32, 1e-4)])
@pytest.mark.parametrize("aa", [False, True])
@pytest.mark.parametrize("deg", [0, 1, 2, 3])
@pytest.mark.usefixtures("no_cull")
def test_matches_autograd_twin(dtype, rel, aa, deg):
    args = hard_scene(dtype)
    got, g_got = run(P.project, args, deg, aa)
    want, g_want = run(project_autograd, args, deg, aa)
    assert ((want.depths < 0.2) & want.valid).sum() == 0 and (~want.valid).sum() >= 5
    rect = P.tile_rect(want.means2d, want.radii, W, H)
    visible = want.valid & (rect[:, 2] > rect[:, 0]) & (rect[:, 3] > rect[:, 1])
    assert torch.equal(got.visible, visible) and 0 < int(visible.sum()) < len(visible)
    assert torch.equal(got.radii, torch.where(visible, want.radii, 0))
    for k in OUTS:
        close(getattr(got, k), getattr(want, k), rel, k)
    for k in INPUTS:
        assert torch.isfinite(g_got[k]).all(), k
        close(g_got[k], g_want[k], rel, "grad " + k)


def test_footprint_is_the_drawable_rows_in_depth_order():
    args = hard_scene(torch.float64)
    pr = P.project(*args, W, H, 3)
    fp = pr.footprint
    o = pr.opacities.detach()
    drawable = pr.visible & (2 * torch.log((255 * o).clamp_min(1e-30)) + 1e-3 > 0)
    assert sorted(fp.gid.tolist()) == torch.nonzero(drawable).squeeze(1).tolist()
    assert (pr.depths[fp.gid].diff() >= 0).all()
    torch.testing.assert_close(fp.means2d, pr.means2d.detach()[fp.gid], atol=0, rtol=0)
    torch.testing.assert_close(fp.opacities, o[fp.gid], atol=0, rtol=0)
    torch.testing.assert_close(fp.vx, 1 / pr.conics.detach()[fp.gid, 0], atol=0, rtol=1e-15)
    a, b, c = fp.cov2d.unbind(1)
    A, B, C = pr.conics.detach()[fp.gid].unbind(1)
    det = a * c - b * b
    torch.testing.assert_close(torch.stack([c / det, -b / det, a / det], 1), torch.stack([A, B, C], 1))


@pytest.mark.parametrize("aa", [False, True])
@pytest.mark.parametrize("deg", [0, 1, 2, 3])
def test_gradcheck_float64(aa, deg):
    """A few Gaussians, one of them beyond the FOV clamp, every input differentiated
    (the camera too). Away from the kinks (clamps, culls), so central differences hold."""
    g = torch.Generator().manual_seed(deg + 10 * aa)
    n = 4
    pc = torch.tensor([[0.2, -0.1, 3.0], [-0.5, 0.3, 4.0], [1.1 * 2.0, 0.1, 2.0], [0.0, 0.0, 5.0]],
                      dtype=torch.float64)  # the third: x/z = 1.1 > 1.3 * tan(half fov) = 0.81
    vm = make_scene(1, W, H, dtype=torch.float64)[5]
    R, t = vm[:3, :3], vm[:3, 3]
    means = (pc - t) @ R
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    log_scales = torch.rand(n, 3, generator=g, dtype=torch.float64) - 2.0
    log_scales[2] += 1.5  # wide: reaches into the image from beyond the clamp
    logits = torch.randn(n, generator=g, dtype=torch.float64)
    sh = torch.randn(n, 16, 3, generator=g, dtype=torch.float64) * 0.1
    sh[:, 0] = 1.0  # colours well above the clamp at 0
    K = make_scene(1, W, H, dtype=torch.float64)[6]
    xs = [x.requires_grad_(True) for x in (means, quats, log_scales, logits, sh, vm.clone(), K.clone())]

    def f(*xs):
        pr = P.project(*xs, W, H, deg, antialiased=aa)
        return tuple(getattr(pr, k) for k in OUTS)

    assert P.project(*xs, W, H, deg).visible.all()
    assert torch.autograd.gradcheck(f, xs, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_sh_basis_backward_matches_autograd():
    d = torch.randn(40, 3, dtype=torch.float64)
    d = (d / d.norm(dim=1, keepdim=True)).requires_grad_(True)
    for deg in range(4):
        g = torch.randn(40, (deg + 1) ** 2, dtype=torch.float64)
        got = sh_basis_rows_backward(d.detach().T.contiguous(), g.T.contiguous(), deg).T
        if deg == 0:  # a constant
            assert (got == 0).all()
            continue
        torch.testing.assert_close(got, torch.autograd.grad((sh_basis(d, deg) * g).sum(), d)[0])


@pytest.mark.parametrize("inverse", [False, True], ids=["R", "R-transposed"])
def test_quat_rotate_is_quat_to_rotmat_applied(inverse):
    g = torch.Generator().manual_seed(3)
    q = torch.randn(64, 4, generator=g, dtype=torch.float64) * torch.rand(64, 1, generator=g, dtype=torch.float64) * 10
    q[0] = 0.0  # the identity
    q[1] = torch.tensor([1e300, 0.0, 2e300, 0.0], dtype=torch.float64)  # finite only through the max-abs scaling
    v = torch.randn(64, 3, generator=g, dtype=torch.float64)
    R = P.quat_to_rotmat(q)
    want = torch.einsum("mji,mj->mi" if inverse else "mij,mj->mi", R, v)
    got = torch.stack(P.quat_rotate(P.unit_quat(q), v.unbind(1), inverse=inverse), 1)
    torch.testing.assert_close(got, want, rtol=0, atol=1e-14)  # float64 rounding of a few products
    assert torch.equal(got[0], v[0])


def render_with_grads(args, **kw):
    xs = [a.detach().clone().requires_grad_(True) for a in args[:5]]
    out = rasterize(*xs, *args[5:], 48, 40, **kw)
    g = torch.Generator().manual_seed(5)
    (out.image * torch.randn(out.image.shape, generator=g, dtype=out.image.dtype)).sum().backward()
    return out, [x.grad for x in xs]


def spread_scene(dtype=torch.float32):
    """Half the Gaussians far off screen, some big ones just outside every edge (the
    cull's bound must keep those that reach in), a few behind the camera."""
    args = make_scene(600, 48, 40, sh_degree=3, seed=7, dtype=torch.float64)
    R, t = args[5][:3, :3], args[5][:3, 3]
    pc = args[0] @ R.T + t
    pc[::2, :2] *= 3.0
    pc[1:40:3, 0] = pc[1:40:3, 2] * torch.linspace(-1.2, 1.2, 13, dtype=torch.float64)
    args[2][1:40:3] += 2.5
    pc[-4:, 2] = 0.1
    args[0] = (pc - t) @ R
    return [a.to(dtype) for a in args]


@pytest.mark.parametrize("compact_below", [0.0, 2.0])  # mask the culled rows / gather the kept ones
def test_culling_changes_nothing_bit_for_bit(monkeypatch, compact_below):
    args = spread_scene()
    monkeypatch.setattr(P, "COMPACT_BELOW", compact_below)
    cut, g_cut = render_with_grads(args)
    with monkeypatch.context() as m:
        m.setattr(P, "_cull", lambda z, *a: torch.ones_like(z, dtype=torch.bool))
        full, g_full = render_with_grads(args)
    assert 0 < int(full.visible.sum()) < 600 * 0.75  # a real share of the rows is off screen
    for k in ("image", "alpha", "depth", "means2d", "radii", "visible", "depths"):
        assert torch.equal(getattr(cut, k), getattr(full, k)), k
    for a, b in zip(g_cut, g_full):
        if compact_below == 0.0:
            assert torch.equal(a, b)
        else:  # gathered rows: the backward's matrix products (BLAS) may round by position
            torch.testing.assert_close(a, b, atol=0, rtol=1e-6)


def test_culled_rows_get_zero_gradients_and_are_never_visible():
    args = spread_scene(torch.float64)
    pr = P.project(*args, 48, 40, 3)
    cam = P._Camera(args[5], args[6], 48, 40, torch.float64)
    pc = torch.addmm(cam.t[:, None], cam.Rw, args[0].T)
    zs = torch.where(pc[2] > 0.2, pc[2], torch.ones_like(pc[2]))
    _, uv, _ = P._mean2d(pc[:2], zs, cam)
    keep = P._cull(pc[2], 0.2, zs, uv, args[2].exp().T, cam, 48, 40)
    assert (~keep).sum() > 200 and not (pr.visible & ~keep).any()
    torch.testing.assert_close(pr.depths, (args[0] @ args[5][:3, :3].T + args[5][:3, 3])[:, 2])  # every row's
    out, grads = render_with_grads(args)
    for gr in grads:
        assert (gr[~keep] == 0).all()
