"""The CUDA path: the same rasterizer and the same commands on a GPU (skipped without one).

CI has no GPU; these run where one is lent (docs/benchmarks.md, "GPU: gsplat against the PyTorch path")."""

from __future__ import annotations

import json

import pytest
import torch

from splatcli import rasterize
from splatcli.render.reference import rasterize_reference
from support.scenes import test_scene as make_scene

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
CUDA = torch.device("cuda")
DEV = "cuda"
PARAMS = ["means", "quats", "log_scales", "opacity_logits", "sh", "viewmat", "K"]


def _grads(fn, args, device, W, H, cot, antialiased=False):
    xs = [a.to(device).detach().requires_grad_(True) for a in args]
    o = fn(*xs, W, H, antialiased=antialiased)
    v, va, vd = (c.to(device) for c in cot)
    ((o.image * v).sum() + (o.alpha * va).sum() + (o.depth * vd).sum()).backward()
    return o, [None if x.grad is None else x.grad.cpu() for x in xs]  # gsplat gives K no gradient


@pytest.mark.parametrize("antialiased", [False, True])
def test_cuda_float64_matches_reference_forward_and_backward(antialiased):
    W, H = 45, 33
    args = make_scene(500, W, H, sh_degree=3, seed=11)
    g = torch.Generator().manual_seed(3)
    cot = (torch.randn(H, W, 3, generator=g, dtype=torch.float64), torch.randn(H, W, generator=g, dtype=torch.float64),
           torch.randn(H, W, generator=g, dtype=torch.float64))
    o_gpu, g_gpu = _grads(rasterize, args, CUDA, W, H, cot, antialiased)
    o_ref, g_ref = _grads(rasterize_reference, args, torch.device("cpu"), W, H, cot, antialiased)
    assert o_gpu.image.device.type == "cuda"
    torch.testing.assert_close(o_gpu.image.cpu(), o_ref.image, atol=1e-10, rtol=0)  # float64: rounding only
    torch.testing.assert_close(o_gpu.depth.cpu(), o_ref.depth, atol=1e-9, rtol=0)  # depth is ~5x the colour scale
    for name, a, b in zip(PARAMS, g_gpu, g_ref):
        assert torch.isfinite(a).all(), name
        # float64 both ways: only the order of summation differs (relative to the gradient's scale)
        torch.testing.assert_close(a, b, atol=1e-9 * float(b.abs().max()), rtol=1e-7, msg=name)


def test_cuda_float32_matches_cpu_float32():
    W, H = 160, 120
    args = [a.float() for a in make_scene(5000, W, H, sh_degree=2, seed=4)]
    g = torch.Generator().manual_seed(5)
    cot = tuple(c.float() for c in (torch.randn(H, W, 3, generator=g), torch.randn(H, W, generator=g),
                                    torch.randn(H, W, generator=g)))
    o_gpu, g_gpu = _grads(rasterize, args, CUDA, W, H, cot)
    o_cpu, g_cpu = _grads(rasterize, args, torch.device("cpu"), W, H, cot)
    torch.testing.assert_close(o_gpu.image.cpu(), o_cpu.image, atol=1e-4, rtol=0)  # issue 7's float32 bound
    for name, a, b in zip(PARAMS, g_gpu, g_cpu):
        # float32, different kernels and summation order: 1e-3 of the gradient's scale
        torch.testing.assert_close(a, b, atol=1e-3 * float(b.abs().max()), rtol=1e-3, msg=name)


def test_cuda_gradcheck_float64():
    W, H = 12, 10
    args = make_scene(4, W, H, sh_degree=1, seed=5)
    args[2] = args[2] + 1.5  # a few px wide: every Gaussian touches several pixels
    xs = [a.to(CUDA).requires_grad_(True) for a in args[:5]]
    viewmat, K = args[5].to(CUDA), args[6].to(CUDA)

    def f(means, quats, log_scales, logits, sh):
        o = rasterize(means, quats, log_scales, logits, sh, viewmat, K, W, H)
        return o.image, o.alpha, o.depth

    # the CPU test's tolerances (tests/test_rasterize.py::test_gradcheck_float64), for the same reason
    assert torch.autograd.gradcheck(f, xs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


def test_train_render_eval_on_cuda_and_the_checkpoint_loads_on_cpu(tmp_path):
    """The commands end to end with --device cuda; the checkpoint is portable."""
    from typer.testing import CliRunner

    from splatcli.cli.main import app
    from splatcli.model import load_model
    from support.tiny_project import make_tiny_project

    proj = make_tiny_project(tmp_path / "p", trained=False).root
    run = CliRunner().invoke
    r = run(app, ["train", str(proj), "--device", DEV, "--renderer", "torch", "--iterations", "60", "--eval-every", "30",
                  "--json", "-q"])
    assert r.exit_code == 0, r.output
    s = json.loads(r.output.strip().splitlines()[-1])
    assert s["steps"] == 60 and DEV in s["device"] and s["renderer"] == "torch"
    r = run(app, ["train", str(proj), "--device", "cpu", "--iterations", "80", "--resume", "--json", "-q"])
    assert r.exit_code == 0, r.output  # a CUDA checkpoint resumes on the CPU
    for cmd in (["render", str(proj), "--device", DEV], ["eval", str(proj), "--device", DEV, "--json"]):
        r = run(app, cmd)
        assert r.exit_code == 0, r.output
    g = load_model(proj, torch.device("cpu")).gaussians
    assert g.means.device.type == "cpu" and torch.isfinite(g.means).all()


# ---- gsplat's kernels (the cuda extra), against the PyTorch path ---------------------------


def _gsplat_or_skip():
    from splatcli.render.backends import gsplat_problem

    why = gsplat_problem()
    if why is not None:
        pytest.skip(why)


@pytest.mark.parametrize("antialiased", [False, True])
def test_gsplat_matches_the_pytorch_path_forward_and_backward(antialiased):
    """On the rasterizer tests' scene, opacities kept below 0.98 so that neither alpha clamp
    (0.99 here, 0.999 in gsplat) binds: the images and the parameter gradients agree."""
    _gsplat_or_skip()
    from splatcli.render.backends import rasterize_gsplat

    W, H = 160, 120
    args = [a.float() for a in make_scene(5000, W, H, sh_degree=2, seed=4)]
    args[3] = args[3].clamp(max=3.8)  # sigmoid(3.8) = 0.978
    g = torch.Generator().manual_seed(5)
    cot = tuple(c.float() for c in (torch.randn(H, W, 3, generator=g), torch.randn(H, W, generator=g),
                                    torch.randn(H, W, generator=g)))
    o_gs, g_gs = _grads(rasterize_gsplat, args, CUDA, W, H, cot, antialiased)
    o_pt, g_pt = _grads(rasterize, args, CUDA, W, H, cot, antialiased)
    # float32 kernels with fast-math exp and another summation order; gsplat also skips the
    # pixels beyond its opacity-aware footprint (alpha < 1/255 there, skipped by both). A
    # Gaussian whose alpha sits at the 1/255 cut is drawn by one and skipped by the other (the
    # exp rounds differently), which moves a pixel by up to alpha * colour, about 1.5/255 for
    # these SH colours: seen on an H200 at 2 of 57,600 values with antialiasing (0.0059).
    for a, b in ((o_gs.image, o_pt.image), (o_gs.alpha, o_pt.alpha)):
        diff = (a - b).detach().abs().cpu()
        assert float((diff > 2e-3).float().mean()) < 1e-3, "more than 0.1% of pixels differ by over 2e-3"
        assert float(diff.max()) < 2e-3 + 2 / 255
    for name, a, b in zip(PARAMS[:5], g_gs, g_pt):  # the camera's gradients are the PyTorch path's alone
        torch.testing.assert_close(a, b, atol=1e-2 * float(b.abs().max()), rtol=1e-2, msg=name)


def test_train_render_eval_with_gsplat(tmp_path):
    """The commands with --renderer gsplat; its checkpoint resumes on the PyTorch path."""
    _gsplat_or_skip()
    from typer.testing import CliRunner

    from splatcli.cli.main import app
    from support.tiny_project import make_tiny_project

    proj = make_tiny_project(tmp_path / "p", trained=False).root
    run = CliRunner().invoke
    r = run(app, ["train", str(proj), "--renderer", "gsplat", "--iterations", "200", "--eval-every", "100", "--json", "-q"])
    assert r.exit_code == 0, r.output
    s = json.loads(r.output.strip().splitlines()[-1])
    # the PyTorch path on the same settings (12.13 dB on the CPU: 200 steps from random points)
    twin = make_tiny_project(tmp_path / "q", trained=False).root
    r = run(app, ["train", str(twin), "--renderer", "torch", "--iterations", "200", "--eval-every", "100", "--json", "-q"])
    assert r.exit_code == 0, r.output
    t = json.loads(r.output.strip().splitlines()[-1])
    assert s["renderer"] == "gsplat" and t["renderer"] == "torch"
    assert abs(s["psnr"] - t["psnr"]) < 0.3 and s["psnr"] > 11, (s["psnr"], t["psnr"])
    for cmd in (["render", str(proj), "--renderer", "gsplat", "--json"], ["eval", str(proj), "--renderer", "gsplat", "--json"]):
        r = run(app, cmd)
        assert r.exit_code == 0, r.output
        assert json.loads(r.output.strip().splitlines()[-1])["renderer"] == "gsplat"
    r = run(app, ["train", str(proj), "--renderer", "torch", "--iterations", "220", "--resume", "--json", "-q"])
    assert r.exit_code == 0, r.output
