"""The gsplat renderer without a GPU: choosing it (--renderer), falling back when its kernels
cannot load, and the adapter's conversions, held against gsplat's own pure-PyTorch projection
and SH (gsplat/cuda/_torch_impl.py, which runs on the CPU). Its CUDA kernels are tested beside
tests/test_cuda.py, where a GPU is lent."""

from __future__ import annotations

import sys
import types

import pytest
import torch

from splatcli.errors import SplatError
from splatcli.render import backends
from splatcli.render.backends import gsplat_inputs, gsplat_output, rasterize_gsplat, resolve_renderer
from splatcli.render.projection import project
from splatcli.render.rasterize import rasterize
from support.scenes import test_scene as make_scene

CPU, CUDA = torch.device("cpu"), torch.device("cuda")  # a device object needs no GPU


def test_renderer_choice_on_cpu():
    assert resolve_renderer("auto", CPU).name == "torch"
    assert resolve_renderer("auto", CPU).note is None  # nothing to say where gsplat cannot run anyway
    assert resolve_renderer(" Torch ", CUDA).name == "torch"
    assert resolve_renderer("torch", CPU).draw is rasterize
    with pytest.raises(SplatError, match="--renderer gsplat needs a CUDA device"):
        resolve_renderer("gsplat", CPU)
    with pytest.raises(SplatError, match="--renderer 'opengl' is not known; allowed values: auto, torch, gsplat"):
        resolve_renderer("opengl", CPU)


def _fake_gsplat(monkeypatch, backend: types.ModuleType | None, *, installed: bool = True) -> None:
    """gsplat as the import system will find it: absent, or with its kernel module `backend`
    (None: importing it fails, as a failed build does)."""
    backends.gsplat_problem.cache_clear()
    if not installed:
        monkeypatch.setitem(sys.modules, "gsplat", None)  # import gsplat -> ImportError
    else:
        pkg, cuda = types.ModuleType("gsplat"), types.ModuleType("gsplat.cuda")
        pkg.cuda = cuda
        monkeypatch.setitem(sys.modules, "gsplat", pkg)
        monkeypatch.setitem(sys.modules, "gsplat.cuda", cuda)
        monkeypatch.setitem(sys.modules, "gsplat.cuda._backend", backend)
    monkeypatch.setattr(backends, "gsplat_problem", backends.gsplat_problem.__wrapped__)


@pytest.mark.parametrize("case, why", [
    ("absent", "gsplat is not installed (pip install 'splatcli[cuda]'"),
    ("no toolkit", "gsplat found no CUDA toolkit"),
    ("build failed", "gsplat's CUDA kernels did not build"),
    ("loaded", None),
])
def test_gsplat_on_cuda_falls_back_with_one_line(monkeypatch, case, why):
    """gsplat leaves its `_C` unset when it finds no toolkit, and a failed build raises on
    import: both fall back to torch with one line (no traceback); kernels that load are used."""
    backend = types.ModuleType("gsplat.cuda._backend")
    backend._C = None if case == "no toolkit" else object()
    _fake_gsplat(monkeypatch, None if case == "build failed" else backend, installed=case != "absent")
    for asked in ("auto", "gsplat"):
        r = resolve_renderer(asked, CUDA)
        if why is None:
            assert (r.name, r.note, r.draw) == ("gsplat", None, rasterize_gsplat)
        else:
            assert r.name == "torch" and r.draw is rasterize
            assert r.note.startswith(why) and r.note.endswith("drawing with the PyTorch path instead")
            assert "\n" not in r.note


def test_gsplat_output_shapes():
    """gsplat's [camera, ...] results as a RenderOutput: the radius is the larger axis's, and
    means2d stays gsplat's tensor, so the screen gradient reaches densification."""
    H, W, N = 5, 7, 4
    colors, alphas = torch.rand(1, H, W, 4), torch.rand(1, H, W, 1)
    means2d = torch.rand(1, N, 2, requires_grad=True)
    radii = torch.tensor([[[0, 0], [3, 5], [2, 1], [0, 4]]], dtype=torch.int32)
    out = gsplat_output(colors, alphas, {"means2d": means2d, "radii": radii, "depths": torch.rand(1, N)})
    assert out.image.shape == (H, W, 3) and out.alpha.shape == (H, W) and out.depth.shape == (H, W)
    torch.testing.assert_close(out.depth, colors[0, ..., 3])
    assert out.radii.tolist() == [0, 5, 2, 4] and out.visible.tolist() == [False, True, True, True]
    assert out.screen_grad() is None
    (means2d * torch.arange(2 * N, dtype=torch.float32).view(1, N, 2)).sum().backward()
    assert out.screen_grad().shape == (N, 2) and out.screen_grad()[1].tolist() == [2.0, 3.0]


@pytest.mark.parametrize("antialiased", [False, True])
def test_adapter_matches_gsplat_projection_and_sh(antialiased):
    """What gsplat_inputs hands gsplat, projected by gsplat's PyTorch reference, gives our
    projection's screen means, conics, depths, opacities (with the 2D filter's compensation)
    and SH colours, forward and through a random cotangent, in float64. (The scene's principal
    point is the image centre, where gsplat's FOV clamp and ours coincide.)"""
    _impl = pytest.importorskip("gsplat.cuda._torch_impl", reason="gsplat (the cuda extra) is not installed")
    W, H = 64, 48
    args = make_scene(300, W, H, sh_degree=2, seed=5)
    means, quats, log_scales, logits, sh, viewmat, K = (a.clone().requires_grad_(i < 5) for i, a in enumerate(args))
    assert float(K[0, 2]) == W / 2 and float(K[1, 2]) == H / 2
    ours = project(means, quats, log_scales, logits, sh, viewmat, K, W, H, 2, 0.2, antialiased)
    kw = gsplat_inputs(means, quats, log_scales, logits, sh, viewmat, K, W, H, torch.zeros(3, dtype=torch.float64),
                       sh_degree=2, near=0.2, antialiased=antialiased)
    assert kw["rasterize_mode"] == ("antialiased" if antialiased else "classic") and kw["render_mode"] == "RGB+D"
    covars, _ = _impl._quat_scale_to_covar_preci(kw["quats"], kw["scales"], compute_preci=False)
    radii, m2d, depths, conics, comp = _impl._fully_fused_projection(
        kw["means"], covars, kw["viewmats"], kw["Ks"], W, H, eps2d=kw["eps2d"], near_plane=kw["near_plane"],
        calc_compensations=antialiased)
    m2d, depths, conics = m2d[0], depths[0], conics[0]
    opac = kw["opacities"] * (comp[0] if antialiased else 1.0)
    campos = torch.linalg.inv(kw["viewmats"][0])[:3, 3]
    colors = (_impl._spherical_harmonics(kw["sh_degree"], kw["means"] - campos, kw["colors"]) + 0.5).clamp_min(0.0)
    both = ours.visible & (radii[0] > 0).all(-1)
    assert int(both.sum()) > 200
    pairs = [(ours.means2d, m2d), (ours.conics, conics), (ours.depths, depths), (ours.opacities, opac),
             (ours.colors, colors)]
    for a, b in pairs:  # float64 both ways: rounding only
        torch.testing.assert_close(a[both], b[both], atol=1e-9, rtol=1e-9)
    g = torch.Generator().manual_seed(2)
    cots = [torch.randn(a[both].shape, generator=g, dtype=torch.float64) for a, _ in pairs]
    grads = []
    for side in (0, 1):
        loss = sum((p[side][both] * c).sum() for p, c in zip(pairs, cots))
        grads.append(torch.autograd.grad(loss, [means, quats, log_scales, logits, sh]))
    for a, b in zip(*grads):  # relative to each gradient's scale: float64 rounding through two formulas
        torch.testing.assert_close(a, b, atol=1e-9 * float(b.abs().max()), rtol=1e-7)


def test_gsplat_refuses_float64_before_importing_it():
    args = make_scene(10, 16, 16, sh_degree=0, seed=1)
    with pytest.raises(ValueError, match="gsplat draws float32 only"):
        rasterize_gsplat(*args, 16, 16)


def _gsplat_on_torch(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *, near_plane, eps2d,
                     sh_degree, packed, backgrounds, render_mode, rasterize_mode):
    """gsplat's `rasterization()` as far as the adapter calls it, drawn by our rasterizer: its
    results in gsplat's shapes, with means2d the tensor the image depends on."""
    assert (packed, render_mode, eps2d) == (False, "RGB+D", 0.3)
    o = rasterize(means, quats, scales.log(), torch.logit(opacities), colors, viewmats[0], Ks[0], width, height,
                  backgrounds[0], sh_degree=sh_degree, near=near_plane, antialiased=rasterize_mode == "antialiased")
    meta = {"means2d": o.means2d, "radii": torch.stack([o.radii, o.radii], -1)[None], "depths": o.depths[None]}
    return torch.cat([o.image, o.depth[..., None]], -1)[None], o.alpha[None, ..., None], meta


def test_training_through_the_adapter_densifies_and_resumes_on_the_other_renderer(tmp_path, monkeypatch):
    """The loop draws through the renderer it was given: densification reads the screen
    gradient from gsplat's means2d, the result matches the PyTorch path's (the fake gsplat
    draws with it; only exp/log and sigmoid/logit round trips differ), and a run started on one
    renderer resumes on the other."""
    from splatcli.cli.planning import resumed
    from splatcli.cli.train_config import make_config
    from splatcli.options import parse
    from splatcli.project import Project
    from splatcli.train.config import TrainConfig
    from splatcli.train.loop import train
    from support.tiny_project import make_tiny_project

    small = dict(iterations=30, init_random_points=300, max_gaussians=600, eval_every=15, log_every=10,
                 refine_start=4, refine_every=4, opacity_reset=16, sh_degree_interval=8, checkpoint_every=10,
                 grow_grad2d=2e-5)

    def blind(*a, **k):  # gsplat without the screen gradient: nothing for densification to read
        colors, alphas, meta = _gsplat_on_torch(*a, **k)
        return colors, alphas, {**meta, "means2d": meta["means2d"].detach()}

    runs = {}
    for name, renderer, fake in (("torch", "torch", None), ("gsplat", "gsplat", _gsplat_on_torch),
                                 ("blind", "gsplat", blind)):
        monkeypatch.setitem(sys.modules, "gsplat", types.SimpleNamespace(rasterization=fake))
        proj = make_tiny_project(tmp_path / name, trained=False)
        proj.update_manifest(scene={**proj.manifest()["scene"], "bounds_min": [-1.0] * 3, "bounds_max": [1.0] * 3})
        runs[name] = train(proj.root, make_config(**small, renderer=renderer), CPU)
    a, b, c = runs["torch"], runs["gsplat"], runs["blind"]
    assert (a.renderer, b.renderer) == ("torch", "gsplat")
    assert abs(b.num_gaussians - a.num_gaussians) <= 0.1 * a.num_gaussians, (a.num_gaussians, b.num_gaussians)
    assert b.num_gaussians > c.num_gaussians + 0.2 * a.num_gaussians, (b.num_gaussians, c.num_gaussians)
    assert abs(b.psnr - a.psnr) < 0.3  # the same model drawn the same way, up to float32 round trips
    back = train(tmp_path / "gsplat", resumed(Project.open(tmp_path / "gsplat"),
                                              make_config(**{**small, "iterations": 40}, renderer="torch"),
                                              parse(TrainConfig, {"iterations": 40})), CPU, resume=True)
    assert (back.renderer, back.resumed_from, back.steps) == ("torch", 30, 40)


def test_gsplat_draws_an_empty_model_without_its_kernels(monkeypatch):
    monkeypatch.setitem(sys.modules, "gsplat", None)  # never imported for it
    args = [a.float()[:0] if i < 5 else a.float() for i, a in enumerate(make_scene(3, 16, 12, sh_degree=0, seed=1))]
    out = rasterize_gsplat(*args, 16, 12, torch.tensor([0.2, 0.3, 0.4]))
    assert out.image.shape == (12, 16, 3) and torch.allclose(out.image, torch.tensor([0.2, 0.3, 0.4]).expand(12, 16, 3))
