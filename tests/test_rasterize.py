"""Fast rasterizer against the dense reference: forward, gradients, gradcheck, API."""

from __future__ import annotations

import importlib

import pytest
import torch

import splatcli
import splatcli.render.blocks as blocks
import splatcli.render.composite as composite
from splatcli import RenderOutput, rasterize
from splatcli.render.reference import rasterize_reference
from support.scenes import test_scene as make_scene

PARAMS = ["means", "quats", "log_scales", "opacity_logits", "sh", "viewmat", "K"]


def _as(args, dtype, grad=False):
    return [a.to(dtype).detach().requires_grad_(grad) for a in args]


def test_api_is_exported_and_shapes():
    assert splatcli.rasterize is rasterize and splatcli.RenderOutput is RenderOutput
    args = make_scene(50, 33, 21, dtype=torch.float32)
    out = rasterize(*args, 33, 21)
    assert isinstance(out, RenderOutput)
    assert out.image.shape == (21, 33, 3) and out.alpha.shape == (21, 33) and out.depth.shape == (21, 33)
    assert out.means2d.shape == (50, 2) and out.radii.shape == (50,) and out.radii.dtype == torch.int32
    assert out.visible.shape == (50,) and out.visible.dtype == torch.bool and out.depths.shape == (50,)
    assert out.image.dtype == torch.float32 and out.visible.any()


@pytest.mark.parametrize("block", [4, 8, 16])
def test_forward_matches_reference_float32(block):
    W, H = 61, 47  # not multiples of 16
    args = make_scene(1200, W, H, sh_degree=2)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    out = rasterize(*_as(args, torch.float32), W, H, bg.float(), block=block)
    with torch.no_grad():
        ref = rasterize_reference(*args, W, H, bg)
    assert out.alpha.mean() > 0.3  # a dense, overlapping picture, not an empty one
    # issue 7's bound for float32 against the float64 reference: max abs error <= 1e-4
    torch.testing.assert_close(out.image, ref.image.float(), atol=1e-4, rtol=0)
    torch.testing.assert_close(out.alpha, ref.alpha.float(), atol=1e-4, rtol=0)
    # depth is sum(w z) with z in 3..7: 1e-4 relative to that scale
    torch.testing.assert_close(out.depth, ref.depth.float(), atol=7e-4, rtol=0)
    torch.testing.assert_close(out.means2d, ref.means2d.float(), atol=1e-3, rtol=1e-5)  # px, |u| up to ~100
    assert torch.equal(out.radii, ref.radii) and torch.equal(out.visible, ref.visible)
    torch.testing.assert_close(out.depths, ref.depths.float())


def test_early_termination_and_chunking_keep_the_picture(monkeypatch):
    """Saturated blocks (T < 1e-4 reached early) with tiny K segments and chunks."""
    W, H = 40, 32
    args = make_scene(800, W, H, sh_degree=0, seed=3)
    args[2] = args[2] + 1.5  # large and opaque: most pixels stop blending early
    args[3] = args[3] + 4.0
    with torch.no_grad():
        ref = rasterize_reference(*args, W, H)
    assert (ref.alpha > 0.99).float().mean() > 0.5
    for seg, chunk, every in [(4, 1 << 12, 1), (16, 1 << 14, 1), (1024, 1 << 24, 1), (4, 1 << 12, 3)]:
        # every: segments between termination tests (CUDA's setting; skipping a test only adds zeros)
        monkeypatch.setattr(composite, "device_settings", lambda dev, block=8, s=(seg, chunk, every): s)
        out = rasterize(*_as(args, torch.float32), W, H)
        # float32 against the float64 reference: the 1e-4 bound
        torch.testing.assert_close(out.image, ref.image.float(), atol=1e-4, rtol=0)
        torch.testing.assert_close(out.alpha, ref.alpha.float(), atol=1e-4, rtol=0)


@pytest.mark.parametrize("antialiased, every", [(False, 1), (True, 1), (False, 3)])
def test_gradients_match_reference(antialiased, every, monkeypatch):
    # short segments exercise the carried prefix sums; every 3rd: CUDA's sparser termination tests
    monkeypatch.setattr(composite, "device_settings", lambda dev, block=8: (8, 1 << 12, every))
    W, H = 37, 29
    args = make_scene(300, W, H, sh_degree=3, seed=1)
    args[3] = args[3] + 2.0  # opaque enough that blocks terminate early
    g = torch.Generator().manual_seed(2)
    v = torch.randn(H, W, 3, generator=g, dtype=torch.float64)
    va = torch.randn(H, W, generator=g, dtype=torch.float64)
    vd = torch.randn(H, W, generator=g, dtype=torch.float64)
    vm = torch.randn(300, 2, generator=g, dtype=torch.float64)

    def grads(fn):
        xs = _as(args, torch.float64, grad=True)
        bg = torch.tensor([0.3, 0.5, 0.7], dtype=torch.float64, requires_grad=True)
        o = fn(*xs, W, H, bg, antialiased=antialiased)
        o.means2d.retain_grad()
        loss = (o.image * v).sum() + (o.alpha * va).sum() + (o.depth * vd).sum() + (o.means2d * vm).sum() * 1e-3
        loss.backward()
        return [x.grad for x in xs] + [bg.grad, o.means2d.grad], o

    g_fast, o_fast = grads(rasterize)
    g_ref, o_ref = grads(rasterize_reference)
    torch.testing.assert_close(o_fast.image, o_ref.image, atol=1e-10, rtol=0)  # float64: rounding only
    for name, a, b in zip(PARAMS + ["background", "means2d"], g_fast, g_ref):
        assert torch.isfinite(a).all(), name
        # float64 both ways: only rounding differs (relative to the gradient's scale)
        torch.testing.assert_close(a, b, atol=1e-9 * float(b.abs().max()), rtol=1e-7, msg=name)


def test_gradcheck_float64():
    W, H = 12, 10
    args = make_scene(4, W, H, sh_degree=1, seed=5)
    args[2] = args[2] + 1.5  # a few px wide: every Gaussian touches several pixels
    xs = _as(args[:5], torch.float64, grad=True)
    bg = torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64, requires_grad=True)
    viewmat, K = args[5], args[6]

    def f(means, quats, log_scales, logits, sh, bg):
        o = rasterize(means, quats, log_scales, logits, sh, viewmat, K, W, H, bg)
        return o.image, o.alpha, o.depth

    # fast_mode: random projections of the Jacobian (the full one needs 600 backward passes).
    # atol/rtol above the defaults: the central differences of exp() over eps = 1e-6 carry
    # O(eps^2) truncation error times the large curvature of opaque, small Gaussians.
    assert torch.autograd.gradcheck(f, (*xs, bg), eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


def test_sh_degree_argument_uses_leading_bands():
    W, H = 30, 20
    args = make_scene(100, W, H, sh_degree=3, dtype=torch.float32)
    a = rasterize(*args, W, H, sh_degree=1).image
    args1 = list(args)
    args1[4] = args[4][:, :4]
    torch.testing.assert_close(a, rasterize(*args1, W, H).image)
    with pytest.raises(ValueError, match="sh_degree"):
        rasterize(*args1, W, H, sh_degree=2)


def test_occlusion_order():
    """A near red Gaussian in front of a far green one shows red in the middle."""
    means = torch.tensor([[0.0, 0.0, 5.0], [0.0, 0.0, 3.0]])
    quats = torch.tensor([[1.0, 0, 0, 0]] * 2)
    ls = torch.full((2, 3), -1.0)
    logits = torch.full((2,), 6.0)
    sh = torch.zeros(2, 1, 3)
    sh[0, 0, 1] = sh[1, 0, 0] = 1.5
    K = torch.tensor([[20.0, 0, 8], [0, 20, 8], [0, 0, 1]])
    out = rasterize(means, quats, ls, logits, sh, torch.eye(4), K, 16, 16)
    c = out.image[8, 8]
    assert c[0] > 0.8 and c[1] < 0.55
    assert 3.0 < float(out.depth[8, 8] / out.alpha[8, 8]) < 3.1  # mostly the near one


@pytest.mark.parametrize("i", range(7))
def test_non_finite_input_names_the_parameter(i):
    args = make_scene(10, 16, 16, dtype=torch.float32)
    args[i] = args[i].clone()
    args[i].view(-1)[0] = float("nan") if i % 2 else float("inf")
    with pytest.raises(ValueError, match=rf"\b{PARAMS[i]}\b"):
        rasterize(*args, 16, 16)


def test_bad_background_and_shapes():
    args = make_scene(10, 16, 16, dtype=torch.float32)
    with pytest.raises(ValueError, match="background"):
        rasterize(*args, 16, 16, torch.tensor([0.0, float("nan"), 0.0]))
    with pytest.raises(ValueError, match="quats"):
        rasterize(args[0], args[1][:, :3], *args[2:], 16, 16)
    with pytest.raises(ValueError, match="width"):
        rasterize(*args, 0, 16)
    with pytest.raises(ValueError, match="dtype|float64"):
        rasterize(args[0].double(), *args[1:], 16, 16)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu():
    W, H = 64, 48
    args = make_scene(2000, W, H, dtype=torch.float32)
    dev = torch.device("cuda")
    cpu = rasterize(*args, W, H)
    gpu = rasterize(*[a.to(dev) for a in args], W, H)
    assert gpu.image.device.type == "cuda"
    torch.testing.assert_close(gpu.image.cpu(), cpu.image, atol=1e-5, rtol=0)  # float32, different kernels


def test_banded_rendering_matches(monkeypatch):
    """Above the pair budget the image is rendered in bands of tile rows, re-planned in
    backward: same picture, same gradients."""
    R = importlib.import_module("splatcli.render.rasterize")  # the module, not the function

    W, H = 45, 70
    args = make_scene(400, W, H, sh_degree=1, seed=7)
    cot = torch.randn(H, W, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)

    def run():
        xs = _as(args, torch.float64, grad=True)
        o = rasterize(*xs, W, H)
        ((o.image * cot).sum() + o.alpha.sum() + o.depth.sum()).backward()
        return o, [x.grad for x in xs]

    o1, g1 = run()
    monkeypatch.setattr(R, "PAIR_BUDGET", 50)  # forces the maximum number of bands (5)
    o2, g2 = run()
    # float64; bands change only which chunk a block lands in and the order gradients add up
    torch.testing.assert_close(o2.image, o1.image, atol=1e-12, rtol=0)
    torch.testing.assert_close(o2.depth, o1.depth, atol=1e-12, rtol=0)
    for a, b in zip(g2, g1):
        torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-9)


@pytest.mark.parametrize("sigma, many, expected", [(3.0, 2000, 4), (12.0, 5000, 8), (120.0, 20, 16)])
def test_auto_block_follows_screen_size_not_overlap(sigma, many, expected):
    """The chooser's measured cost model: small blocks for small Gaussians, 16 px only for
    ones hundreds of pixels wide. Stacking the same Gaussians deeper (more overlap, which
    the old model answered with larger blocks at 1.3-1.5x the time on fox) changes nothing."""
    for n in (many, 10 * many):
        cov2d = torch.tensor([[sigma**2, 0.0, sigma**2]]).repeat(n, 1)
        opac = torch.full((n,), 0.9)
        assert blocks.choose_block(blocks.extents(cov2d, opac), 1000, 1000) == expected


@pytest.mark.parametrize("slots", [1, 1000], ids=["every-segment", "batched"])
def test_batching_the_backwards_scatter_changes_no_bit(monkeypatch, slots):
    """The backward adds its per-slot gradients into the per-Gaussian sums once SCATTER_SLOTS are pending:
    the same additions in the same order as one call per segment, so the same bits whatever the batch."""
    args = make_scene(1500, 80, 64, dtype=torch.float32, seed=5)
    cot = torch.rand(64, 80, 3, generator=torch.Generator().manual_seed(3))

    def grads(pending: int):
        monkeypatch.setattr(composite, "SCATTER_SLOTS", pending)
        p = [t.clone().requires_grad_(i < 5) for i, t in enumerate(args)]
        (rasterize(*p, 80, 64, block=4).image * cot).sum().backward()
        return [t.grad for t in p[:5]]

    base = grads(1 << 30)  # one call for the whole backward
    assert any(bool(g.abs().sum() > 0) for g in base)
    assert all(torch.equal(a, b) for a, b in zip(base, grads(slots)))


@pytest.mark.parametrize("keep", [0, 1 << 14, 1 << 30], ids=["none", "some", "all"])
def test_backward_from_the_forwards_kept_alpha_is_bit_for_bit_the_recomputed_one(monkeypatch, keep):
    """The forward keeps its segments' alpha and transmittance (up to KEEP_BYTES) for the backward; what it
    did not keep is computed again. Every gradient is the same bits whichever, also in a second backward
    (retain_graph), which finds the kept tensors used up and computes them all again."""
    args = make_scene(1500, 80, 64, dtype=torch.float32, seed=7)
    cot = torch.rand(64, 80, 3, generator=torch.Generator().manual_seed(2))

    def grads(budget: int, twice: bool = False):
        monkeypatch.setattr(composite, "KEEP_BYTES", budget)
        p = [t.clone().requires_grad_(i < 5) for i, t in enumerate(args)]
        out = rasterize(*p, 80, 64, block=4)
        (out.image * cot).sum().backward(retain_graph=twice)
        first = [t.grad.clone() for t in p[:5]]
        if twice:
            for t in p[:5]:
                t.grad = None
            (out.image * cot).sum().backward()
            assert all(torch.equal(a, t.grad) for a, t in zip(first, p[:5]))
        return first

    base = grads(0)
    assert all(torch.equal(a, b) for a, b in zip(base, grads(keep, twice=True)))
