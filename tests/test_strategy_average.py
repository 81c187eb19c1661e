"""Parameter averaging (`train --average`): the run ends with each Gaussian's exponential moving
average over its last steps, a Gaussian that density control adds or moves starts its average
again, and the loop calls it after the last step, before the final measurement and checkpoint."""

from __future__ import annotations

import math

import torch
from torch import nn

from splatcli.cli.train_config import make_config
from splatcli.files.checkpoint import load_checkpoint
from splatcli.project import Project
from splatcli.strategy import AverageStep, Splats, StepInfo, ops
from splatcli.strategy.average import WINDOW
from splatcli.train.state import make_strategies
from support.context import context
from support.tiny_project import make_tiny_project, run_ok


def _splats(n: int, seed: int = 0) -> Splats:
    g = torch.Generator().manual_seed(seed)
    p = {"means": torch.randn(n, 3, generator=g), "quats": torch.randn(n, 4, generator=g),
         "log_scales": torch.randn(n, 3, generator=g), "opacity_logits": torch.randn(n, generator=g),
         "sh0": torch.randn(n, 1, 3, generator=g), "shN": torch.randn(n, 15, 3, generator=g)}
    params = {k: nn.Parameter(v) for k, v in p.items()}
    return Splats(params, {k: torch.optim.Adam([v], lr=1e-3) for k, v in params.items()}, [])


def _info(n: int) -> StepInfo:
    return StepInfo(None, 8, 8)  # (averaging reads nothing of the step)


def _run(step: AverageStep, splats: Splats, state, steps: range, seed: int = 1) -> dict[str, list[torch.Tensor]]:
    """Random moves of every parameter, then the strategy's hook, at each of `steps`; the values seen."""
    g = torch.Generator().manual_seed(seed)
    seen: dict[str, list[torch.Tensor]] = {k: [] for k in splats.params}
    for s in steps:
        with torch.no_grad():
            for k, p in splats.params.items():
                p.add_(torch.randn(p.shape, generator=g))
                seen[k].append(p.detach().clone())
        step.step_post_backward(splats, state, s, _info(len(splats)))
    return seen


def test_finish_leaves_the_exponential_moving_average():
    splats = _splats(5)
    avg = AverageStep(0.05, 200)  # tau 10 steps, from step 160
    assert avg.tau == 10 and avg.start == 200 - WINDOW * 10
    st = avg.initial_state(5, torch.device("cpu"))
    seen = _run(avg, splats, st, range(1, 201))
    moments = {k: o.state[p]["exp_avg"].clone() if o.state else None
               for (k, p), o in zip(splats.params.items(), splats.optimizers.values())}
    avg.finish(splats, st)
    for k, p in splats.params.items():
        window = seen[k][159:]  # steps 160..200: the first taken whole, then 1/2, 1/3, ... 1/10, then 1/10 each
        want = window[0].double()
        for i, v in enumerate(window[1:], start=2):
            want = want + (v.double() - want) / min(i, 10)
        torch.testing.assert_close(p.detach().double(), want, rtol=0, atol=1e-5)  # float32 lerps, 41 of them
        assert moments[k] is None  # (no moments were made or dropped)
    assert st.values.shape == (5, 0)  # (not kept in the checkpoint)


def test_nothing_before_the_window():
    splats = _splats(3)
    avg = AverageStep(0.03, 1000)
    st = avg.initial_state(3, torch.device("cpu"))
    seen = _run(avg, splats, st, range(1, 100))
    assert st.values.shape == (3, 0) and float(st.count.sum()) == 0
    avg.finish(splats, st)  # the window never opened: the last values stay
    for k, p in splats.params.items():
        assert torch.equal(p.detach(), seen[k][-1])


def test_a_moved_gaussian_starts_its_average_again():
    """MCMC's relocation overwrites rows with `ops.replace_rows`, which zeroes strategy rows: the moved
    Gaussian ends at its new values (the average since it moved), not halfway to where it was."""
    splats = _splats(4)
    avg = AverageStep(0.25 - 1e-9, 8)  # tau 2 steps; the window is the whole run
    st = avg.initial_state(4, torch.device("cpu"))
    splats.states = [st]
    _run(avg, splats, st, range(1, 8))
    new = {k: torch.full((1, *p.shape[1:]), 7.0) for k, p in splats.params.items()}
    ops.replace_rows(splats, torch.tensor([2]), new)
    assert float(st.count[2]) == 0
    avg.step_post_backward(splats, st, 8, _info(4))
    before = {k: p.detach().clone() for k, p in splats.params.items()}
    avg.finish(splats, st)
    for k, p in splats.params.items():
        assert torch.equal(p.detach()[2], new[k][0])  # its first step since the move: taken whole
        assert not torch.equal(p.detach()[0], before[k][0])  # the others: averaged


def test_cut_bands_start_the_average_again():
    """--sh-degree auto drops SH bands: the rows no longer fit, and the averages start again."""
    splats = _splats(2)
    avg = AverageStep(0.1, 20)
    st = avg.initial_state(2, torch.device("cpu"))
    splats.states = [st]
    _run(avg, splats, st, range(1, 19))
    ops.truncate_bands(splats, "shN", 3)
    seen = _run(avg, splats, st, range(19, 21), seed=2)
    assert float(st.count.max()) == 2
    avg.finish(splats, st)
    want = seen["shN"][0] + (seen["shN"][1] - seen["shN"][0]) / 2
    torch.testing.assert_close(splats.params["shN"].detach(), want)


def test_bands_cut_at_the_last_step_keep_their_averages():
    """--sh-degree auto cuts the bands at the last step, after that step's average: the bands kept
    end at their averages, as every other parameter does."""
    splats = _splats(2)
    avg = AverageStep(0.1, 20)
    st = avg.initial_state(2, torch.device("cpu"))
    splats.states = [st]
    _run(avg, splats, st, range(1, 21))
    want = dict(zip([k for k, _ in st.layout], st.values.clone().split([w for _, w in st.layout], 1)))
    ops.truncate_bands(splats, "shN", 3)  # degree 1: bands 1-3 of 15 kept
    avg.finish(splats, st)
    assert torch.equal(splats.params["shN"].detach(), want["shN"][:, :9].reshape(2, 3, 3))
    assert torch.equal(splats.params["means"].detach(), want["means"])
    # degree 0: shN leaves the parameters, and the others still end at their averages
    splats = _splats(2)
    st = avg.initial_state(2, torch.device("cpu"))
    splats.states = [st]
    _run(avg, splats, st, range(1, 21))
    want = dict(zip([k for k, _ in st.layout], st.values.clone().split([w for _, w in st.layout], 1)))
    ops.truncate_bands(splats, "shN", 0)
    avg.finish(splats, st)
    assert "shN" not in splats.params
    assert torch.equal(splats.params["sh0"].detach(), want["sh0"].reshape(2, 1, 3))


def test_made_by_default_before_the_model_steps():
    cfg = make_config(sh_degree="auto", compact=True, iterations=1000)
    names = [s.name for s in make_strategies(cfg, 1.0, context())]
    assert names.index("average") < names.index("sh_auto") < names.index("compact")
    avg = next(s for s in make_strategies(cfg, 1.0, context()) if s.name == "average")
    assert math.isclose(avg.tau, 0.02 * cfg.total_steps)  # the fine-tune included: it ends the run
    assert "average" not in [s.name for s in make_strategies(make_config(average=0), 1.0, context())]


def test_train_ends_with_the_average(tmp_path):
    """Through the CLI, the same seeded run with and without averaging: the checkpoints differ, and
    the averaged run's last holds no averages (they became its parameters). A run resumed from a
    checkpoint inside the window (its averages saved with it) ends as the uninterrupted one."""
    outs = {}
    for a in ("0", "0.2"):
        proj = make_tiny_project(tmp_path / a, trained=False)
        run_ok("train", proj.root, "--preset", "demo", "--iterations", "40", "--average", a, "--device", "cpu",
               "--block", "model", "--checkpoint-every", "30", "--keep-checkpoints", "3")
        outs[a] = load_checkpoint(proj.latest_checkpoint(), torch.device("cpu"))
    g0, g1 = outs["0"].gaussians, outs["0.2"].gaussians
    assert g0.means.shape == g1.means.shape and outs["0"].step == outs["0.2"].step == 40
    assert not torch.equal(g0.means, g1.means)
    assert "average" not in outs["0"].strategy
    assert outs["0.2"].strategy["average"]["values"].shape[1] == 0

    proj = Project.open(tmp_path / "0.2")
    mid = load_checkpoint(proj.checkpoint_path(30), torch.device("cpu"))  # the window: steps 8-40
    assert mid.strategy["average"]["values"].shape == (len(mid.gaussians.means), 59)
    proj.checkpoint_path(40).unlink()
    run_ok("train", proj.root, "--resume", "--device", "cpu")
    resumed = load_checkpoint(proj.latest_checkpoint(), torch.device("cpu"))
    assert resumed.step == 40
    assert torch.equal(resumed.gaussians.means, g1.means) and torch.equal(resumed.gaussians.sh, g1.sh)
