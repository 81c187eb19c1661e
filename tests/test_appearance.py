"""`train --appearance exposure` (train/appearance.py) and eval's colour-fit PSNR.

The transforms: identity changes nothing, gradients reach only the view seen, a known
gain is learnt back, checkpoints carry them (resume is bitwise), exported files never
do, and two ranks keep them equal. The colour fit: an affinely recoloured render is
scored as perfect, and the fitted PSNR is never below the raw one.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import types

import cv2
import numpy as np
import pytest
import torch

import splatcli.train.loop as loop
from splatcli.cli.planning import resumed
from splatcli.cli.train_config import make_config
from splatcli.errors import Interrupted, SplatError
from splatcli.eval.metrics import color_fit, psnr, psnr_color_fit
from splatcli.events import Progress
from splatcli.files.checkpoint import load_checkpoint, save_checkpoint
from splatcli.formats.ply import read_ply, write_ply
from splatcli.formats.registry import write_format
from splatcli.gaussians import Gaussians
from splatcli.model import load_model
from splatcli.options import parse
from splatcli.render import rasterize
from splatcli.train.appearance import Exposure, ExposureConfig, identity, smooth_basis
from splatcli.train.config import TrainConfig
from splatcli.train.loop import train
from splatcli.train.loss import photometric_loss
from splatcli.viewer import open_scene
from support.tiny_project import assert_user_error, make_tiny_project, ring_cameras, run_cli, run_ok, tiny_gaussians

CPU = torch.device("cpu")
# block="model": the runs here are compared bit for bit, and a measured block (--block auto) follows the clock
SMALL = dict(block="model", iterations=20, init_random_points=300, max_gaussians=600, eval_every=10, log_every=5, refine_start=4,
             refine_every=4, opacity_reset=100, sh_degree_interval=8, checkpoint_every=10, appearance="exposure")


def _appearance(n: int = 4) -> Exposure:
    return Exposure(n, ExposureConfig(), CPU)


def _tiny(tmp_path, name="p", gains=None):
    """The tiny project (8 training views, 2 held out); `gains` multiplies each training photo."""
    proj = make_tiny_project(tmp_path / name, trained=False)
    proj.update_manifest(scene={**proj.manifest()["scene"], "bounds_min": [-1.0] * 3, "bounds_max": [1.0] * 3})
    if gains is not None:
        for name_, g in zip(proj.splits()["train"], gains):
            path = proj.images_dir / name_
            img = cv2.imread(str(path)).astype(np.float64) * g
            cv2.imwrite(str(path), np.clip(np.round(img), 0, 255).astype(np.uint8))
    return proj


# ---- the transform ------------------------------------------------------------------


def test_identity_leaves_the_image_and_the_loss_unchanged():
    gen = torch.Generator().manual_seed(0)
    img, target = torch.rand(24, 20, 3, generator=gen), torch.rand(24, 20, 3, generator=gen)
    app = _appearance()
    assert torch.equal(app.apply(img, 2), img)  # x * 1 + y * 0 + z * 0 + 0 is exact
    assert float(app.penalty(2).detach()) == 0.0
    loss = photometric_loss(app.apply(img, 2), target) + app.penalty(2)
    assert torch.equal(loss, photometric_loss(img, target))


def test_apply_is_image_times_a_transposed_plus_b_and_gradients_reach_only_that_view():
    gen = torch.Generator().manual_seed(1)
    app = _appearance(5)
    with torch.no_grad():
        app.transforms += 0.1 * torch.randn(app.transforms.shape, generator=gen)
    img = torch.rand(16, 12, 3, generator=gen)
    t = app.transforms[3].detach()
    torch.testing.assert_close(app.apply(img, 3), img @ t[:, :3].T + t[:, 3])
    (photometric_loss(app.apply(img, 3), torch.rand(16, 12, 3, generator=gen)) + app.penalty(3)).backward()
    g = app.transforms.grad
    assert g[3].abs().sum() > 0
    assert torch.count_nonzero(torch.cat([g[:3], g[4:]])) == 0


def test_gradcheck_of_the_transform_and_its_penalty():
    gen = torch.Generator().manual_seed(2)
    img = torch.rand(4, 3, 3, dtype=torch.float64, generator=gen, requires_grad=True)
    t = (identity(2, CPU).double() + 0.1 * torch.randn(2, 3, 4, dtype=torch.float64, generator=gen)).requires_grad_()

    def f(img, t):
        app = _appearance(2)
        app.transforms = t  # the maths of apply/penalty, on float64 leaves
        return app.apply(img, 1), app.penalty(1)

    assert torch.autograd.gradcheck(f, (img, t))


def test_learning_rate_decays_from_lr_to_lr_final():
    app = _appearance()
    # step 150: a fine-tune after the schedule holds the final rate
    for step, lr in ((0, 0.01), (50, math.sqrt(0.01 * 0.001)), (150, 0.001)):
        app.schedule(step, 100)
        assert app.optimizer.param_groups[0]["lr"] == pytest.approx(lr), step


def test_a_step_moves_only_the_views_trained_then_centres_all():
    """A view's transform moves on the step its view is trained and never on its momentum
    after (torch's Adam would carry row 0 on for the next ~20 steps); the centring moves
    every row by one common amount; one step of a row is Adam's first step, lr x sign."""
    app = _appearance(4)
    gen = torch.Generator().manual_seed(3)
    grads = torch.zeros(4, 3, 4)
    grads[0] = torch.randn(3, 4, generator=gen)
    app.transforms.grad = grads.clone()
    app.optimizer.step()
    moved = app.transforms.detach() - identity(4, CPU)
    own = -0.01 * grads[0].sign()  # Adam's first step: lr x m_hat / sqrt(v_hat) = lr x sign(g)
    torch.testing.assert_close(moved[0] - moved[1], own)
    torch.testing.assert_close(moved[1:], (-own / 4).expand(3, 3, 4))
    torch.testing.assert_close(moved.mean(0), torch.zeros(3, 4))
    before = app.transforms.detach().clone()
    grads = torch.zeros(4, 3, 4)
    grads[2] = torch.randn(3, 4, generator=gen)
    app.transforms.grad = grads
    app.optimizer.step()
    shift = app.transforms.detach() - before
    torch.testing.assert_close(shift[0], shift[1])  # row 0: the centring only, no momentum
    torch.testing.assert_close(shift[0], shift[3])
    assert app.optimizer.state[app.transforms]["step"].tolist() == [1, 0, 1, 0]


def _ring(n: int) -> torch.Tensor:  # [n, 3] cameras on a circle, in capture order
    a = torch.arange(n, dtype=torch.float64) * (2 * math.pi / n)
    return torch.stack([a.cos(), a.sin(), torch.zeros(n, dtype=torch.float64)], 1)


def test_smooth_basis_is_orthonormal_starts_with_the_mean_and_holds_slow_drift():
    """The modes are orthonormal, the first is the constant, and on a ring of cameras a
    slow exposure drift (one period round the ring) lies in the first 3 modes while
    shot-to-shot gains (seeded, independent) mostly do not."""
    n = 40
    b = smooth_basis(_ring(n), 6).double()
    torch.testing.assert_close(b.T @ b, torch.eye(6, dtype=torch.float64), atol=1e-6, rtol=0)  # float32 basis
    torch.testing.assert_close(b[:, 0], torch.full((n,), 1 / math.sqrt(n), dtype=torch.float64), atol=1e-6, rtol=0)
    a = torch.arange(n, dtype=torch.float64) * (2 * math.pi / n)
    drift = 0.1 * torch.cos(a + 0.3)
    b3 = b[:, :3]
    assert float((b3 @ (b3.T @ drift) - drift).norm()) < 1e-3 * float(drift.norm())
    shots = torch.rand(n, generator=torch.Generator().manual_seed(0), dtype=torch.float64) - 0.5
    shots -= shots.mean()
    kept = float((b.T @ shots).norm() ** 2 / shots.norm() ** 2)
    assert kept < 0.35, kept  # 6 of 40 modes: about 15% of independent gains' variance expected
    assert smooth_basis(_ring(n), 1).shape == (n, 1)
    # cameras on one spot (a panorama): nothing varies slowly but the mean
    assert smooth_basis(torch.zeros(n, 3), 6).shape == (n, 1)


def test_a_step_removes_the_smooth_modes_from_the_transforms():
    """With `modes` > 1 the step leaves the transforms' deviation from [I | 0] with no
    part in the smooth modes (with 1, their mean is the identity, as above)."""
    n = 40
    app = Exposure(n, ExposureConfig(smooth=0.075), CPU, _ring(n).float())  # 3 modes
    app.transforms.grad = torch.randn(n, 3, 4, generator=torch.Generator().manual_seed(1))
    app.optimizer.step()
    dev = (app.transforms.detach() - identity(n, CPU)).flatten(1)  # [n, 12]
    b = smooth_basis(_ring(n), 3)
    assert b.shape == (n, 3)
    torch.testing.assert_close(b.T @ dev, torch.zeros(3, 12), atol=1e-6, rtol=0)
    assert float(dev.abs().max()) > 1e-3  # and the rest was kept


# ---- training ------------------------------------------------------------------------


GAINS = [0.7, 1.25, 0.8, 1.2, 0.75, 1.3, 0.85, 1.15]  # the 8 training photos


def test_training_learns_each_photos_gain_back(tmp_path):
    """Start from the true Gaussians (--init-ply) so the transforms have the gains to learn;
    each training photo's mean diagonal moves from 1 towards its gain."""
    proj = _tiny(tmp_path, gains=GAINS)
    truth = tmp_path / "truth.ply"
    write_ply(truth, tiny_gaussians(300, seed=0))
    train(proj.root, make_config(**{**SMALL, "iterations": 80, "refine_start": 1000, "exposure_lr": 0.03,
                                    "exposure_lr_final": 0.01, "init_ply": str(truth)}), CPU)
    t = load_checkpoint(proj.latest_checkpoint()).appearance["transforms"]
    diag = t[:, :, :3].diagonal(dim1=1, dim2=2).mean(1)
    gains = torch.tensor(GAINS)
    # every photo's transform moved the right way, and a good part of the way (80 steps:
    # about ten updates per photo at these rates)
    assert torch.all(torch.sign(diag - 1) == torch.sign(gains - 1)), diag
    assert float((diag - gains).abs().mean()) < 0.6 * float((gains - 1).abs().mean()), diag


def test_checkpoint_round_trip_and_resume_is_bitwise(tmp_path):
    cfg = make_config(**SMALL)
    a = _tiny(tmp_path, "a", GAINS)
    train(a.root, cfg, CPU)
    b = _tiny(tmp_path, "b", GAINS)

    def stop_at_7(ev):
        if isinstance(ev, Progress) and ev.done == 7:
            os.kill(os.getpid(), signal.SIGINT)  # a real signal through the real handler

    with pytest.raises(Interrupted):
        train(b.root, cfg, CPU, on_event=stop_at_7)
    mid = load_checkpoint(b.latest_checkpoint())
    assert mid.step == 7 and mid.appearance["transforms"].shape == (8, 3, 4)
    assert not torch.equal(mid.appearance["transforms"], identity(8, CPU))
    # moved together after every step so that their mean stays the identity (the
    # scene keeps the photos' average exposure); float32 rounding of 8 rows
    torch.testing.assert_close(mid.appearance["transforms"].mean(0), torch.eye(3, 4), atol=1e-6, rtol=0)
    s = train(b.root, cfg, CPU, resume=True)
    assert s.resumed_from == 7
    ka, kb = load_checkpoint(a.latest_checkpoint()), load_checkpoint(b.latest_checkpoint())
    assert torch.equal(ka.appearance["transforms"], kb.appearance["transforms"])
    for k in ("exp_avg", "exp_avg_sq"):
        assert torch.equal(ka.appearance["optimizer"]["state"][0][k], kb.appearance["optimizer"]["state"][0][k])
    assert torch.equal(ka.gaussians.means, kb.gaussians.means)


def test_a_checkpoint_without_transforms_resumes_with_them_from_the_identity(tmp_path):
    proj = _tiny(tmp_path)
    train(proj.root, make_config(**{**SMALL, "appearance": "none", "iterations": 6}), CPU)
    assert load_checkpoint(proj.latest_checkpoint()).appearance == {}
    s = train(proj.root, resumed(proj, make_config(**SMALL), parse(TrainConfig, {"appearance": "exposure", "iterations": 10})), CPU,
              resume=True)
    assert s.resumed_from == 6 and s.steps == 10
    t = load_checkpoint(proj.latest_checkpoint()).appearance["transforms"]
    assert t.shape == (8, 3, 4) and not torch.equal(t, identity(8, CPU))


def test_transforms_for_another_number_of_photos_are_one_line(tmp_path):
    proj = _tiny(tmp_path)
    train(proj.root, make_config(**{**SMALL, "iterations": 4}), CPU)
    ck = load_checkpoint(proj.latest_checkpoint())
    save_checkpoint(ck.path, step=ck.step, gaussians=ck.gaussians, sh_degree=ck.sh_degree, optimizer=ck.optimizer,
                    strategy=ck.strategy, rng=ck.rng, config=ck.config, extra=ck.extra,
                    appearance={**ck.appearance, "transforms": identity(5, CPU)})
    r = run_cli("train", proj.root, "--resume", "--iterations", "8", "--device", "cpu")
    assert r.exit_code == 2 and str(ck.path) in r.stderr and "(5, 3, 4)" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


def test_a_transform_baked_into_the_sh_renders_what_the_render_through_it_shows():
    """Gaussians.recoloured: the model with [A | b] folded into its SH, over the background
    through the same transform, draws the picture the plain model draws and the transform then
    maps (up to colours clamped at 0, none here: every colour is well inside [0, 1])."""
    g0 = tiny_gaussians(300, seed=0)
    g = Gaussians(g0.means, g0.quats, g0.log_scales, g0.opacity_logits, 0.15 * g0.sh)  # colours inside (0, 1)
    t = torch.tensor([[0.8, 0.1, 0.0, 0.05], [0.0, 1.1, 0.05, -0.02], [0.1, 0.0, 0.7, 0.1]])
    cam = ring_cameras(2)[0]
    vm, K = torch.as_tensor(cam.viewmat, dtype=torch.float32), torch.as_tensor(cam.K, dtype=torch.float32)
    bg = torch.tensor([0.2, 0.4, 0.6])

    def draw(g, bg):
        return rasterize(g.means, g.quats, g.log_scales, g.opacity_logits, g.sh, vm, K, cam.width, cam.height,
                         bg).image  # [H, W, 3]

    through = draw(g, bg) @ t[:, :3].T + t[:, 3]
    baked = draw(g.recoloured(t), bg @ t[:, :3].T + t[:, 3])
    # float32 rounding of two different sums of the same terms
    assert torch.allclose(baked, through, atol=2e-5), float((baked - through).abs().max())
    assert float((through - draw(g, bg)).abs().max()) > 0.05  # the transform changed the picture


def test_render_and_export_take_one_training_photos_light_and_plain_exports_hold_none(tmp_path):
    """--appearance-of NAME: the model with that photo's learnt transform baked in, in render and
    export alike; a name that is not a training photo, or a run without transforms, is one line.
    Without it, exported files never hold the transforms."""
    proj = _tiny(tmp_path, gains=GAINS)
    train(proj.root, make_config(**{**SMALL, "iterations": 10}), CPU)
    name = proj.splits()["train"][1]
    ck = load_checkpoint(proj.latest_checkpoint())
    assert ck.appearance["transforms"].shape == (8, 3, 4)
    t = ck.appearance["transforms"][1]
    assert float((t - torch.eye(3, 4)).abs().max()) > 1e-3  # a light of its own, not the identity
    m = load_model(proj.root, CPU, appearance_of=name)
    assert torch.equal(m.light, t.float()) and torch.allclose(m.gaussians.sh, ck.model().recoloured(t).sh)
    run_ok("export", proj.root, "--appearance-of", name, "-o", str(tmp_path / "lit.ply"))
    assert torch.allclose(read_ply(tmp_path / "lit.ply").gaussians.sh, m.gaussians.sh, atol=1e-6)
    run_ok("render", proj.root, "--appearance-of", name, "--split", "train", "-o", str(tmp_path / "lit"))
    store = open_scene(proj.root, appearance_of=name)  # the viewer: the same light, the background through it
    bg = torch.tensor(proj.background() or (0.0, 0.0, 0.0)) @ t[:, :3].T.float() + t[:, 3].float()
    assert torch.allclose(torch.tensor(store.background), bg.clamp(0, 1))
    assert_user_error(run_cli("render", proj.root, "--appearance-of", "nope.png"), "not a training photo")
    plain = _tiny(tmp_path, name="plain")
    train(plain.root, make_config(**{**SMALL, "iterations": 4, "appearance": "none"}), CPU)
    assert_user_error(run_cli("export", plain.root, "--appearance-of", name), "trained without --appearance")
    run_ok("export", proj.root, "-o", tmp_path / "scene.ply")
    write_format("ply", tmp_path / "alone.ply", ck.model())  # the Gaussians alone
    assert (tmp_path / "scene.ply").read_bytes() == (tmp_path / "alone.ply").read_bytes()


def test_bad_appearance_is_a_one_line_error(tmp_path):
    proj = _tiny(tmp_path)
    r = run_cli("train", proj.root, "--appearance", "vignette")
    assert r.exit_code == 2 and "--appearance" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    with pytest.raises(SplatError, match="exposure_smooth"):
        make_config("demo", exposure_smooth=1.5)


@pytest.mark.slow
def test_two_ranks_keep_equal_transforms(tmp_path):
    """Through the real launcher: at each checkpoint every rank's parameters, transforms
    included (TrainState.trainable), equal rank 0's bitwise (rank_checks counts them)."""
    proj = _tiny(tmp_path, gains=GAINS)
    start = tmp_path / "start.ply"  # 300 Gaussians: seconds, where the preset's 20k random ones take longer
    write_ply(start, tiny_gaussians(300, seed=5))
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    r = subprocess.run([sys.executable, "-m", "splatcli", "train", str(proj.root), "--preset", "demo",
                        "--max-gaussians", "600", "--eval-every", "0", "--device", "cpu", "--iterations", "80",
                        "--init-ply", str(start), "--appearance", "exposure", "--nproc", "2", "--json"],
                       cwd=repo, capture_output=True, text=True, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout.strip().splitlines()[-1])
    assert s["nproc"] == 2 and s["rank_checks"] >= 1
    t = load_checkpoint(proj.latest_checkpoint()).appearance["transforms"]
    assert not torch.equal(t, identity(8, CPU))  # both ranks' views moved them


# ---- eval's colour fit -----------------------------------------------------------------


def test_colour_fit_undoes_an_affine_recolouring():
    gen = torch.Generator().manual_seed(3)
    target = torch.rand(30, 40, 3, dtype=torch.float64, generator=gen) * 0.6 + 0.2
    a = torch.tensor([[0.8, 0.05, 0.0], [0.0, 1.1, 0.05], [0.02, 0.0, 0.9]], dtype=torch.float64)
    render = (target - 0.03) @ a.T  # stays inside [0, 1]: the fit is exact
    assert float(psnr(render, target)) < 25
    assert psnr_color_fit(render, target) > 100
    torch.testing.assert_close(color_fit(render, target), target)


def test_fitted_psnr_is_never_below_the_raw_psnr():
    gen = torch.Generator().manual_seed(4)
    for _ in range(5):
        render, target = torch.rand(12, 14, 3, generator=gen), torch.rand(12, 14, 3, generator=gen)
        assert psnr_color_fit(render, target) >= float(psnr(render, target)) - 1e-9
    flat = torch.full((12, 14, 3), 0.5)  # a rank-deficient fit: the mean colour
    assert psnr_color_fit(flat, target) >= float(psnr(flat, target)) - 1e-9


def test_eval_reports_the_colour_fit_psnr(tmp_path):
    proj = make_tiny_project(tmp_path / "p")
    run_ok("eval", proj.root, "--budgets", "1", "--no-plots", "--json", "--device", "cpu")
    report = json.loads((proj.reports_dir / "eval.json").read_text())
    assert report["psnr_color_fit"] >= report["psnr"]
    assert all(s["psnr_color_fit"] >= s["psnr"] - 1e-9 for s in report["per_image"])
    assert "PSNR after a per-view colour fit" in (proj.reports_dir / "eval.md").read_text()
    # one camera, one light: raw leads; the compensated protocol is named beside it
    assert report["headline"] == "raw" and "left half" in report["compensated_protocol"]
    assert report["compensated_psnr"] > 0 and all(s["compensated_psnr"] is not None for s in report["per_image"])


def test_eval_of_a_run_that_learnt_each_photos_light_leads_with_the_compensated_score(tmp_path):
    """Trained with --appearance exposure: the held-out photo's light is unknowable, so eval's
    headline (eval.json, eval.md, the printed line) is the appearance-compensated score."""
    proj = _tiny(tmp_path, gains=GAINS)
    s = train(proj.root, make_config(**{**SMALL, "iterations": 10}), CPU)
    r = run_ok("eval", proj.root, "--budgets", "1", "--no-plots", "--device", "cpu")
    report = json.loads((proj.reports_dir / "eval.json").read_text())
    assert report["headline"] == "compensated" and report["compensated_psnr"] > report["psnr"]
    # training watched the held-out views under the same protocol: its last figure is eval's headline
    assert s.protocol == "compensated" and report["curve_protocol"] == "compensated"
    assert s.psnr == pytest.approx(report["compensated_psnr"], abs=1e-3)  # (the summary rounds)
    assert report["training_curve"][-1]["psnr"] == pytest.approx(s.psnr, abs=1e-3)  # (the log rounds)
    assert "appearance compensated" in r.output and "Headline: the appearance-compensated score" in (
        proj.reports_dir / "eval.md").read_text()
    assert "raw (colour fitted" not in " ".join(r.output.split())  # the raw score is not labelled with the other's protocol


def test_training_view_scores_go_through_each_photos_transform(monkeypatch):
    """train_psnr and the --sh-degree auto / --compact validation scores compare a training
    photo with its render through that photo's transform; held-out scores use the scene alone."""
    render = torch.full((12, 12, 3), 0.8)
    monkeypatch.setattr(loop, "render_view", lambda state, v, bg, d: types.SimpleNamespace(image=render))
    app = _appearance(3)
    with torch.no_grad():
        app.transforms[2, :, :3] *= 0.5  # photo 2 came out at half the exposure
    state = types.SimpleNamespace(image_model=app)
    photo = types.SimpleNamespace(image=torch.full((12, 12, 3), 102, dtype=torch.uint8), keep=None)  # 0.4 = 0.8 / 2
    through, _ = loop.evaluate_views(state, [photo], torch.zeros(3), 0, train_index=[2])
    alone, _ = loop.evaluate_views(state, [photo], torch.zeros(3), 0)
    assert math.isinf(through) or through > 60, through
    assert alone < 20, alone
