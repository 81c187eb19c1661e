"""`Trainer.step` alone, without the run around it (no signals, log, checkpoints or plan):
one step renders, backpropagates and updates; over a few epochs the loss falls."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from splatcli.cli.train_config import make_config
from splatcli.train.data import load_train_data
from splatcli.train.state import means_lr, new_state
from splatcli.train.trainer import Trainer, _all_finite
from support.context import context
from support.tiny_project import make_tiny_project, tiny_gaussians

REPO = Path(__file__).resolve().parents[1]

CPU = torch.device("cpu")


def _trainer(tmp_path, **opts) -> Trainer:
    """The tiny scene's photos, and its true Gaussians with their colours and positions disturbed."""
    proj = make_tiny_project(tmp_path / "p", trained=False)
    cfg = make_config(block="model", iterations=40, sh_degree=1, **opts)
    data = load_train_data(proj, cfg.downscale, cfg.max_size, CPU)
    g = tiny_gaussians(seed=0)
    gen = torch.Generator().manual_seed(3)
    g.means += torch.randn(g.means.shape, generator=gen) * 0.05
    g.sh[:, 0] += torch.randn(g.sh[:, 0].shape, generator=gen) * 0.5
    ctx = context()
    return Trainer(new_state(g, cfg, data.extent, CPU, len(data.train), ctx), cfg, data, ctx)


def test_a_step_alone_updates_the_model_and_the_loss_falls(tmp_path):
    t = _trainer(tmp_path)
    n_views = len(t.data.train)
    losses = []
    for step in range(1, 4 * n_views + 1):  # four epochs: each sees every training view once
        before = {k: p.detach().clone() for k, p in t.state.params.items()}
        batch = t.next_batch(step)
        stats = t.step(step, batch)
        assert stats.finite and not stats.stopping and t.state.counts.step == step
        assert stats.loss.shape == () and not stats.loss.requires_grad and 0.0 < float(stats.loss) < 1.0
        assert (stats.info.width, stats.info.height) == (batch.view.camera.width, batch.view.camera.height)
        assert stats.info.render.image.shape == batch.target.shape == (40, 48, 3)
        assert all(p.grad is None for p in t.state.params.values())  # consumed by the update
        assert not torch.equal(before["means"], t.state.params["means"])
        assert not torch.equal(before["sh0"], t.state.params["sh0"])
        assert t.state.optimizers["means"].param_groups[0]["lr"] == means_lr(t.cfg, step, t.data.extent)
        assert len(t.refine(step, stats.info)) == len(t.state.strategies)
        losses.append(float(stats.loss))
    epochs = [sum(losses[i:i + n_views]) / n_views for i in range(0, len(losses), n_views)]  # mean loss of each
    assert all(b < a for a, b in zip(epochs, epochs[1:])) and epochs[-1] < 0.9 * epochs[0], epochs
    assert t.state.counts.bad_steps == 0


def test_a_non_finite_step_changes_nothing_and_is_counted(tmp_path):
    t = _trainer(tmp_path)
    batch = t.next_batch(1)
    batch.target = batch.target * float("nan")  # [H, W, 3]
    before = {k: p.detach().clone() for k, p in t.state.params.items()}
    stats = t.step(1, batch, stop=True)
    assert not stats.finite and not stats.info.finite and stats.stopping  # (one process: its own signal)
    assert (t.state.counts.bad_steps, t.state.counts.bad_run) == (1, 1)
    for k, p in t.state.params.items():
        assert torch.equal(before[k], p), k


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_one_non_finite_gradient_value_anywhere_is_caught(tmp_path, bad):
    t = _trainer(tmp_path)
    params = t.state.trainable()
    for p in params.values():
        p.grad = torch.randn(p.shape, generator=torch.Generator().manual_seed(1))
    loss = torch.tensor(0.5)
    assert _all_finite(loss, t.state)
    for name, p in params.items():
        for i in {0, p.numel() // 2, p.numel() - 1}:  # the first, a middle and the last (a vector's tail) value
            g = p.grad.view(-1)
            keep = float(g[i])
            g[i] = bad
            assert not _all_finite(loss, t.state), (name, i)
            g[i] = keep
    assert _all_finite(loss, t.state) and not _all_finite(torch.tensor(bad), t.state)


def test_a_new_schedule_keeps_the_strategies_rows(tmp_path):
    t = _trainer(tmp_path, refine_start=2, refine_every=2)
    for step in (1, 2, 3):
        t.refine(step, t.step(step, t.next_batch(step)).info)
    rows = list(t.state.splats.states)
    longer = make_config(block="model", iterations=400, sh_degree=1, refine_start=2, refine_every=2)
    t.reschedule(longer)
    assert t.cfg is longer and t.state.splats.states == rows
    assert all(a is b for a, b in zip(t.state.splats.states, rows))
    t.step(4, t.next_batch(4))
    assert t.state.optimizers["means"].param_groups[0]["lr"] == means_lr(longer, 4, t.data.extent)


def test_a_step_of_a_collection_leaves_a_passer_by_out_of_its_loss(tmp_path):
    """--transients ignore: past robust_start x the steps, a region of the photo that disagrees with
    the render leaves the loss (train/transients.py); before it, and with keep, it counts."""
    losses = {}
    for mode, start in (("keep", 0.0), ("ignore", 0.5), ("ignore", 0.0)):
        t = _trainer(tmp_path / f"{mode}{start}", transients=mode, robust_start=start)
        batch = t.next_batch(1)
        batch.target = batch.target.clone()
        batch.target[5:25, 10:30] = 1.0 - batch.target[5:25, 10:30]  # a passer-by in a 40x48 photo
        losses[mode, start] = float(t.step(1, batch).loss)
    assert losses["ignore", 0.5] == losses["keep", 0.0]  # step 1 of 40: not yet
    assert losses["ignore", 0.0] < 0.8 * losses["keep", 0.0], losses


def test_one_backward_per_step():
    """The step has one loss: strategies and image models return their terms, the trainer sums
    them and calls backward once (two backward calls would each walk the graph they share)."""
    calls = [f"{p.relative_to(REPO)}:{i}" for folder in ("train", "strategy")
             for p in sorted((REPO / "splatcli" / folder).rglob("*.py"))
             for i, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1)
             if ".backward(" in line.split("#")[0]]
    assert calls == ["splatcli/train/trainer.py:" + calls[0].rsplit(":", 1)[1]], calls


def test_the_depth_term_moves_the_means_only_where_a_view_has_sfm_points(tmp_path):
    moved = []
    for i, (weight, points) in enumerate(((0.0, True), (1.0, False), (1.0, True))):
        t = _trainer(tmp_path / str(i), depth_weight=weight)
        for v in t.data.train:  # the true Gaussians' centres stand in for the points each photo observed
            v.sparse = tiny_gaussians(seed=0).means if points else None
        t.step(1, t.next_batch(1))
        moved.append(t.state.params["means"].detach().clone())
    assert torch.equal(moved[0], moved[1])  # off, or no points: the photometric step alone
    assert not torch.equal(moved[0], moved[2])
