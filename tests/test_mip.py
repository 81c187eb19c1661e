"""Mip-Splatting's filters (train --mip-filter; render/eval --antialias): the 3D filter's
value against a direct float64 computation, its fold into scales and opacities (values,
gradcheck, hard cases), its rows through ops, the checkpoint -> model -> .ply path, and
a tiny training run."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from splatcli.files.checkpoint import load_checkpoint, save_checkpoint
from splatcli.gaussians import Gaussians, smooth_3d
from splatcli.model import load_model
from splatcli.render import render_camera
from splatcli.strategy import MipFilter, Splats, ops
from splatcli.strategy.mip import MARGIN, VARIANCE, filter_from_rate, sampling_rate
from splatcli.views.sources import choose_antialias, dataset_views
from support.tiny_project import make_tiny_project, ring_cameras, run_cli, run_ok, tiny_gaussians

CPU = torch.device("cpu")


def _cams(dtype=torch.float64):
    return [(*c.torch(CPU, dtype), c.width, c.height) for c in ring_cameras()]


def _direct_filter(means: np.ndarray, cams) -> np.ndarray:  # float64, one point and camera at a time
    out = np.zeros(len(means))
    for i, m in enumerate(means):
        best = 0.0
        for vm, K, w, h in cams:
            vm, K = vm.numpy(), K.numpy()
            x, y, z = vm[:3, :3] @ m + vm[:3, 3]
            if z <= 0.2:
                continue
            u, v = K[0, 0] * x / z + K[0, 2], K[1, 1] * y / z + K[1, 2]
            if -MARGIN * w <= u <= (1 + MARGIN) * w and -MARGIN * h <= v <= (1 + MARGIN) * h:
                best = max(best, max(K[0, 0], K[1, 1]) / z)
        out[i] = math.sqrt(VARIANCE) / best if best > 0 else np.nan
    seen = ~np.isnan(out)
    out[~seen] = out[seen].max() if seen.any() else 0.0
    return out


def test_filter_matches_a_direct_float64_computation():
    g = torch.Generator().manual_seed(0)
    means = torch.randn(200, 3, generator=g, dtype=torch.float64) * 1.5  # some outside every view
    cams = _cams()
    f = filter_from_rate(sampling_rate(means, cams))
    want = _direct_filter(means.numpy(), cams)
    assert (f > 0).all()
    np.testing.assert_allclose(f.numpy(), want, rtol=1e-12)
    # ... and in float32 on the same points, to float32 precision
    f32 = filter_from_rate(sampling_rate(means.float(), _cams(torch.float32)))
    np.testing.assert_allclose(f32.numpy(), want, rtol=1e-5)


def test_unseen_centres_get_the_largest_filter_and_nothing_seen_gives_zero():
    cams = _cams()
    means = torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 100.0, 0.0]], dtype=torch.float64)  # last: far below every view
    nu = sampling_rate(means, cams)
    assert nu[2] == 0 and (nu[:2] > 0).all()
    f = filter_from_rate(nu)
    assert f[2] == f[:2].max()
    behind = torch.tensor([[0.0, 0.0, -5.0]], dtype=torch.float64)
    one = [(torch.eye(4, dtype=torch.float64), cams[0][1], 48, 40)]  # a camera looking down +z: the point is behind
    assert filter_from_rate(sampling_rate(behind, one)).tolist() == [0.0]
    assert filter_from_rate(sampling_rate(torch.zeros(0, 3, dtype=torch.float64), one)).numel() == 0


def _direct_fold(log_scales, logits, f):  # float64 numpy, straight from the definition
    s = np.exp(log_scales)
    s2 = np.sqrt(s * s + f[:, None] ** 2)
    p = 1 / (1 + np.exp(-logits)) * np.prod(s / s2, axis=1)
    return np.log(s2), np.log(p / (1 - p))


def test_fold_matches_the_definition_and_is_the_identity_without_filter():
    g = torch.Generator().manual_seed(1)
    ls = torch.randn(64, 3, generator=g, dtype=torch.float64) - 3
    op = torch.randn(64, generator=g, dtype=torch.float64) * 3
    f = torch.rand(64, generator=g, dtype=torch.float64) * 0.1
    f[::4] = 0
    a, b = smooth_3d(ls, op, f)
    wa, wb = _direct_fold(ls.numpy(), op.numpy(), f.numpy())
    np.testing.assert_allclose(a.numpy(), wa, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(b.numpy(), wb, rtol=1e-10, atol=1e-10)  # logit of p near 1: a few ulps of 1 - p lost
    assert torch.equal(a[::4], ls[::4]) and torch.equal(b[::4], op[::4])  # no filter: exactly the input
    assert (b <= op).all() and (a >= ls).all()  # larger and fainter, never the reverse


def test_fold_gradcheck():
    g = torch.Generator().manual_seed(2)
    ls = (torch.randn(6, 3, generator=g, dtype=torch.float64) - 3).requires_grad_()
    op = (torch.randn(6, generator=g, dtype=torch.float64) * 2).requires_grad_()
    f = torch.rand(6, generator=g, dtype=torch.float64) * 0.08
    f[0] = 0  # the masked branch: exact zero gradient through it, no NaN
    assert torch.autograd.gradcheck(lambda a, b: smooth_3d(a, b, f), (ls, op))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fold_hard_cases_stay_finite(dtype):
    ls = torch.tensor([[-80.0] * 3, [40.0] * 3, [-3.0] * 3, [-3.0] * 3, [-3.0] * 3, [-30.0, 5.0, 0.0]], dtype=dtype)
    op = torch.tensor([0.0, 0.0, 60.0, -60.0, 200.0, 5.0], dtype=dtype)
    f = torch.tensor([1e-2, 1e-2, 1e-2, 1e-2, 0.0, 1e30 if dtype == torch.float64 else 1e15], dtype=dtype)
    ls.requires_grad_()
    op.requires_grad_()
    a, b = smooth_3d(ls, op, f)
    (a.sum() + b.sum()).backward()
    for t in (a, b, ls.grad, op.grad):
        assert torch.isfinite(t).all(), t
    assert a[1].sub(ls[1]).abs().max() < 1e-6  # huge Gaussians: unchanged
    assert b[0] < -100  # a tiny Gaussian blurred to the filter's size is nearly transparent
    assert b[4] == op[4]  # no filter: the logit itself, even where sigmoid rounds to 1


def _splats(g: Gaussians) -> Splats:
    p = {"means": g.means, "quats": g.quats, "log_scales": g.log_scales, "opacity_logits": g.opacity_logits,
         "sh0": g.sh[:, :1]}
    params = {k: torch.nn.Parameter(v.clone()) for k, v in p.items()}
    return Splats(params, {k: torch.optim.Adam([v]) for k, v in params.items()})


def test_filter_rows_follow_ops_and_new_rows_are_computed_before_drawing():
    g = tiny_gaussians(50)
    cams = _cams(torch.float32)
    mip = MipFilter(cams)
    sp = _splats(g)
    st = mip.initial_state(len(sp), CPU)
    sp.states.append(st)
    p = sp.params
    mip.shade(sp, st, p["log_scales"], p["opacity_logits"])
    full = filter_from_rate(sampling_rate(p["means"].detach(), cams))
    assert torch.equal(st.filter3d, full) and bool(st.known.all())
    keep = torch.arange(50) % 3 != 0
    ops.keep(sp, keep)
    assert torch.equal(st.filter3d, full[keep])
    new = {k: v.detach()[:5].clone() for k, v in p.items()}
    new["means"] = new["means"] + 0.3
    ops.append(sp, new)
    assert st.filter3d.shape == (len(sp),) and not bool(st.known[-5:].any())
    ls, op = mip.shade(sp, st, sp.params["log_scales"], sp.params["opacity_logits"])
    assert torch.equal(st.filter3d[:-5], full[keep])  # old rows untouched
    want = filter_from_rate(sampling_rate(sp.params["means"].detach()[-5:], cams))
    torch.testing.assert_close(st.filter3d[-5:], want)
    assert ls.requires_grad and op.requires_grad


def test_checkpoint_with_filter_renders_as_its_exported_ply_and_render_eval_say_they_antialias(tmp_path):
    proj = make_tiny_project(tmp_path / "p")
    raw = load_checkpoint(proj.latest_checkpoint())
    cams = [(*v.camera.torch(CPU), v.camera.width, v.camera.height) for v in dataset_views(proj, "train")]
    f = filter_from_rate(sampling_rate(raw.gaussians.means, cams)) * 4  # 4x: a filter that visibly changes the picture
    save_checkpoint(proj.checkpoint_path(300), step=300, gaussians=raw.gaussians, sh_degree=raw.sh_degree,
                    strategy={"default": {}, "mip": {"filter3d": f, "known": torch.ones_like(f)}},
                    config={"mip_filter": True})
    m = load_model(proj.root, CPU)
    assert m.antialiased is True and m.step == 300
    r = run_ok("export", proj.root, "-o", tmp_path / "s.ply")
    ply = load_model(tmp_path / "s.ply", CPU)
    cam = ring_cameras(scale=4)[3]  # 4x the training size: where the filter matters
    bg = torch.zeros(3)
    a = render_camera(m.gaussians, cam, bg, antialiased=True).image
    b = render_camera(ply.gaussians, cam, bg, antialiased=True).image
    c = render_camera(raw.model(), cam, bg, antialiased=True).image
    # The .ply stores float32 like the checkpoint: the same numbers, so nearly bitwise.
    torch.testing.assert_close(a, b, rtol=0, atol=1e-5)
    assert (a - c).abs().max() > 0.05
    r = run_ok("render", proj.root, "--json", "-o", tmp_path / "r")
    assert json.loads(r.stdout)["antialiased"] is True
    r = run_cli("render", proj.root, "--json", "-o", tmp_path / "r", "--antialias", "off")
    assert json.loads(r.stdout)["antialiased"] is False
    r = run_ok("eval", proj.root, "--no-plots", "--budgets", "1", "--downscale", "0.5", "--antialias", "auto")
    assert "2D antialiasing filter" in r.output
    r = run_cli("render", proj.root, "--antialias", "maybe")
    assert r.exit_code == 2 and "--antialias" in r.stderr


def test_choose_antialias():
    assert choose_antialias("auto", None, 1.0) == (False, None)
    assert choose_antialias("auto", False, 0.5)[0] is True  # drawn smaller than trained: aliasing
    assert choose_antialias("auto", False, 2.0) == (False, None)  # drawn larger: the filter only blurs
    assert choose_antialias("auto", False, None) == (False, None)  # unknown: as trained
    assert choose_antialias("auto", True, 1.0)[0] is True  # trained with it
    assert choose_antialias("off", True, 0.5) == (False, None)
    assert choose_antialias("on", None, 2.0)[0] is True


def test_auto_antialias_follows_the_zoom_of_a_plain_model(tmp_path):
    proj = make_tiny_project(tmp_path / "p")
    for downscale, on in (("2", True), ("0.5", False), ("1", False)):
        r = run_ok("render", proj.root, "--json", "-o", tmp_path / downscale, "--downscale", downscale)
        assert json.loads(r.stdout)["antialiased"] is on, downscale


def test_the_filters_lower_the_growth_threshold_and_plain_training_keeps_it():
    """Under --mip-filter the default strategy grows at GROW_GRAD2D x grow_grad2d (the filters
    lower small Gaussians' view-space gradients), a user-set threshold included."""
    from splatcli.cli.train_config import make_config
    from splatcli.strategy import DefaultStrategy
    from splatcli.strategy.mip import GROW_GRAD2D
    from splatcli.train.state import make_strategies
    from support.context import context

    ctx = context()

    def threshold(**opts) -> float:
        (d,) = [s for s in make_strategies(make_config("fast", **opts), 1.0, ctx) if isinstance(s, DefaultStrategy)]
        return d.config.grow_grad2d

    assert 0 < GROW_GRAD2D < 1
    assert threshold() == make_config("fast").default.grow_grad2d
    assert threshold(mip_filter=True) == pytest.approx(GROW_GRAD2D * make_config("fast").default.grow_grad2d)
    assert threshold(mip_filter=True, grow_grad2d=1e-3) == pytest.approx(GROW_GRAD2D * 1e-3)
    assert threshold(grow_grad2d=1e-3) == 1e-3
