"""`--strategy mcmc` (Kheradmand et al. 2024): relocation keeps the picture, the budget
holds, dead Gaussians are reused, noise moves only transparent ones, the penalties
reach the gradients, and the training loop needed no change for it."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch
from torch import nn

from splatcli.cli.train_config import make_config
from splatcli.render.output import RenderOutput
from splatcli.strategy import MCMCStrategy, MCMCStrategyConfig, RegularizeStep, Splats, StepInfo
from splatcli.strategy.mcmc import relocation
from splatcli.train.config import TrainConfig
from splatcli.train.state import make_strategies
from support.context import context
from support.tiny_project import assert_user_error, make_tiny_project, run_cli

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("o", [0.05, 0.3, 0.7, 0.99])
@pytest.mark.parametrize("n", [1, 2, 3, 7])
def test_relocation_keeps_centre_and_mass(o, n):
    """n copies with the new opacity and scale, drawn over one another: the same alpha at
    the centre (exactly) and the same integral along a line (the paper's approximation)."""
    new_o, new_s = relocation(torch.tensor([o], dtype=torch.float64), torch.full((1, 3), 0.7, dtype=torch.float64),
                              torch.tensor([n]), 51)
    x = torch.linspace(0, 6, 3001, dtype=torch.float64)
    orig = o * torch.exp(-0.5 * (x / 0.7) ** 2)
    comp = 1 - (1 - new_o * torch.exp(-0.5 * (x / new_s[0, 0]) ** 2)) ** n
    torch.testing.assert_close(comp[0], orig[0], atol=1e-12, rtol=0)
    assert abs(float(comp.sum() / orig.sum()) - 1) < 1e-3  # measured: at most 7e-5 over these cases
    if n == 1:
        torch.testing.assert_close(new_s, torch.full((1, 3), 0.7, dtype=torch.float64))
    else:
        assert float(new_o) < o and float(new_s[0, 0]) < 0.7


def _splats(n: int, opacity: torch.Tensor | None = None, seed: int = 0) -> Splats:
    g = torch.Generator().manual_seed(seed)
    p = {"means": torch.randn(n, 3, generator=g), "quats": torch.randn(n, 4, generator=g),
         "log_scales": torch.full((n, 3), math.log(0.05)),
         "opacity_logits": torch.logit(opacity) if opacity is not None else torch.randn(n, generator=g),
         "sh0": torch.randn(n, 1, 3, generator=g)}
    params = {k: nn.Parameter(v) for k, v in p.items()}
    opt = {k: torch.optim.Adam([v], lr=1e-3) for k, v in params.items()}
    for k, v in params.items():  # non-zero moments, to see which rows are reset
        v.grad = torch.ones_like(v)
        opt[k].step()
        opt[k].zero_grad()
    return Splats(params, opt, [])


def _info(n: int, visible: torch.Tensor | None = None) -> StepInfo:  # visible [n] bool: every one drawn by default
    z = torch.zeros(n)
    r = RenderOutput(image=torch.zeros(2, 2, 3), alpha=torch.zeros(2, 2), depth=torch.zeros(2, 2),
                     means2d=torch.zeros(n, 2), radii=torch.zeros(n, dtype=torch.int32),
                     visible=torch.ones(n, dtype=torch.bool) if visible is None else visible, depths=z)
    return StepInfo(r, 2, 2)


def _strategy(cap: int, **kw) -> MCMCStrategy:
    return MCMCStrategy(MCMCStrategyConfig(max_gaussians=cap, refine_start=0, refine_stop=10_000, refine_every=100, **kw))


def test_grows_by_the_fraction_up_to_the_cap_and_never_past_it():
    s = _strategy(cap=130)
    sp = _splats(100)
    sp.states = [s.initial_state(100, torch.device("cpu"))]
    counts = []
    for step in range(100, 1100, 100):
        s.step_post_backward(sp, sp.states[0], step, _info(len(sp)))
        counts.append(len(sp))
    assert counts[:3] == [105, 110, 115] and max(counts) == 130 and counts[-1] == 130
    for k, v in sp.params.items():  # parameters and moments grew together
        assert sp.optimizers[k].state[v]["exp_avg"].shape == v.shape


def test_a_cap_raised_after_the_growth_target_is_reached_within_what_is_left_of_the_window():
    """--time-budget raises the cap on its curve; one raised after grow_until's target step is
    reached by grow_until of the window left, not at the 5% floor (fox from its photos, 180 s:
    17.0k Gaussians and 29.25 dB before, 30.0k and 29.80 dB after, in one run), nor only by the
    window's end, which a plan that shrinks the run brings forward."""
    s = MCMCStrategy(MCMCStrategyConfig(max_gaussians=4000, refine_start=0, refine_stop=1000, refine_every=100))
    assert s.growth_rate(1000, 300) == pytest.approx(4.0 ** (1 / 2) - 1)  # before the target (step 400): 300 and 400
    rate = s.growth_rate(1000, 600)  # past the target: 0.4 of the 400 steps left, the refinements at 600 and 700
    assert rate == pytest.approx(4.0 ** (1 / 2) - 1) and rate > s.config.growth
    assert s.growth_rate(1000, 900) == pytest.approx(3.0)  # the last refinement of the window: all at once
    assert s.growth_rate(4000, 600) == s.config.growth  # at the cap: nothing to reach


def test_dead_gaussians_move_onto_live_ones_with_fresh_moments():
    op = torch.full((50,), 0.6)
    op[:10] = 0.001  # dead
    s = _strategy(cap=50, noise_lr=0.0, spread=0.0, shrink=1.0)  # the paper's: copies on their source's centre
    sp = _splats(50, op)
    st = s.initial_state(50, torch.device("cpu"))
    before = {k: v.detach().clone() for k, v in sp.params.items()}
    stats = s.step_post_backward(sp, st, 100, _info(50))
    after = torch.sigmoid(sp.params["opacity_logits"])
    assert len(sp) == 50 and stats.pruned == 10  # relocated, not removed: the count holds
    assert bool((after > 0.005).all())  # no dead ones left
    moved = (sp.params["means"][:10] - before["means"][:10]).norm(dim=1) > 0
    assert bool(moved.all())  # each dead slot now sits on a live Gaussian's centre
    live_means = before["means"][10:]
    for m in sp.params["means"][:10]:
        assert bool(((live_means - m).norm(dim=1) < 1e-6).any())
    m1 = sp.optimizers["means"].state[sp.params["means"]]["exp_avg"]
    assert bool((m1[:10] == 0).all())  # new Gaussians start with no momentum
    untouched = (before["opacity_logits"][10:] == sp.params["opacity_logits"][10:].detach())
    assert bool((m1[10:][untouched] != 0).all())  # rows not drawn keep theirs
    # a drawn source and its copies share the opacity the relocation set (lower than 0.6)
    assert float(after[:10].detach().max()) < 0.6


def test_copies_are_drawn_from_their_source_gaussian():
    """With `spread` (the default), each copy sits at a draw from its source Gaussian (after
    the relocation's scale): spread along the long axis, not along the short ones, and
    no two copies on one spot."""
    op = torch.full((401,), 0.001)  # 400 dead, one live source
    op[0] = 0.9
    s = _strategy(cap=401, noise_lr=0.0)
    assert s.config.spread == 1.0
    sp = _splats(401, op)
    with torch.no_grad():
        sp.params["quats"][0] = torch.tensor([1.0, 0.0, 0.0, 0.0])  # axes = world axes
        sp.params["log_scales"][0] = torch.log(torch.tensor([0.5, 0.01, 0.01]))
    centre = sp.params["means"][0].detach().clone()
    s.step_post_backward(sp, s.initial_state(401, torch.device("cpu")), 100, _info(401))
    new_s = sp.params["log_scales"][0].detach().exp()  # the source's scale after relocation, copies share it
    torch.testing.assert_close(sp.params["log_scales"][1:].detach().exp(), new_s.expand(400, 3))
    _, s_eq9 = relocation(torch.tensor([0.9]), torch.tensor([[0.5, 0.01, 0.01]]), torch.tensor([401]), s.config.max_ratio)
    # eq. 9's scale, then shrunk; rtol: the strategy starts from sigmoid(logit(0.9)) in float32
    torch.testing.assert_close(new_s * s.config.shrink, s_eq9[0], rtol=1e-3, atol=0)
    off = sp.params["means"][1:].detach() - centre  # [400, 3]
    std = off.std(dim=0)
    # 400 draws from the Gaussian before it shrank by `shrink`: the sample std is within 15%
    # of the true one with overwhelming probability (~6 sigma)
    torch.testing.assert_close(std / (new_s * s.config.shrink), torch.ones(3), atol=0.15, rtol=0)
    assert float(std[0] / std[1]) > 20  # anisotropic, as the source
    assert torch.cdist(off, off).add(torch.eye(400)).min() > 0  # no two on one spot
    torch.testing.assert_close(sp.params["means"][0].detach(), centre)  # the source stays put


def test_a_gaussian_no_view_draws_for_a_sweep_is_moved_onto_live_ones():
    """Off every view, nothing brings a Gaussian back or lets it die: one that no view (of any
    rank) drew over a sweep (SWEEP_EPOCHS epochs of the views) is relocated like a dead one;
    one drawn once stays, and a new row is judged from the next sweep on."""
    op = torch.full((50,), 0.6)
    s = MCMCStrategy(MCMCStrategyConfig(max_gaussians=50, refine_start=0, refine_stop=10_000, refine_every=10,
                                        noise_lr=0.0, spread=0.0, shrink=1.0), views=5)
    assert s.sweep == 10
    sp = _splats(50, op)
    st = s.initial_state(50, torch.device("cpu"))
    sp.states = [st]  # edited with the parameters (ops)
    before = sp.params["means"].detach().clone()
    shown = torch.ones(50, dtype=torch.bool)
    shown[:8] = False  # rows 0-7 off every view of this rank ...
    other_rank = torch.zeros(50)
    other_rank[7] = 1.0  # ... but another rank's view drew row 7

    def info(step: int) -> StepInfo:
        i = _info(50, shown | (torch.arange(50) == 6) if step == 3 else shown)  # row 6 drawn once, at step 3
        i.combine = lambda state: state.drawn.add_(other_rank)
        return i

    for step in range(1, 11):
        stats = s.step_post_backward(sp, st, step, info(step))
    assert stats.pruned == 6  # rows 0-5 at the sweep's end, step 10
    after = sp.params["means"].detach()
    assert not bool(torch.isclose(after[:6], before[:6]).all(dim=1).any())
    for m in after[:6]:  # each now on a live Gaussian's centre (spread 0)
        assert bool(((before[8:] - m).norm(dim=1) < 1e-6).any())
    torch.testing.assert_close(after[6:8], before[6:8])  # drawn once, or by the other rank: kept
    other_rank.zero_()
    for step in range(11, 31):
        stats = s.step_post_backward(sp, st, step, _info(50, shown))
        if step == 20:  # rows 0-5 were new at the sweep's start, 6-7 were there: judged now
            assert stats.pruned == 2
    assert stats.pruned == 6  # step 30: the rows relocated at 10, still off every view (those of 20 are new to it)
    unswept = _strategy(cap=50, noise_lr=0.0)  # views not given: nothing is looked for
    sp2 = _splats(50, op)
    st2 = unswept.initial_state(50, torch.device("cpu"))
    assert unswept.step_post_backward(sp2, st2, 100, _info(50, shown)).pruned == 0


def test_relocation_goes_on_after_growth_stops():
    """Growth ends with the refinement window; dead Gaussians are still moved until
    `relocate_stop` (the late deaths are reused instead of wasting the budget)."""
    op = torch.full((50,), 0.6)
    s = MCMCStrategy(MCMCStrategyConfig(noise_lr=0.0, max_gaussians=80, refine_start=0, refine_stop=500,
                                        refine_every=100), relocate_stop=1000)
    sp = _splats(50, op)
    st = s.initial_state(50, torch.device("cpu"))
    for step, dead in ((600, 8), (1000, 5)):
        with torch.no_grad():
            sp.params["opacity_logits"][:dead] = -10.0
        stats = s.step_post_backward(sp, st, step, _info(len(sp)))
        assert len(sp) == 50  # no growth after refine_stop
        assert stats.pruned == (dead if step < 1000 else 0)
    assert int((torch.sigmoid(sp.params["opacity_logits"]) < 0.005).sum()) == 5  # left alone at relocate_stop


def test_noise_moves_transparent_gaussians_only():
    op = torch.tensor([0.001, 0.002, 0.9, 0.99])
    s = _strategy(cap=4)
    sp = _splats(4, op)
    sp.optimizers["means"].param_groups[0]["lr"] = 1e-3
    st = s.initial_state(4, torch.device("cpu"))
    before = sp.params["means"].detach().clone()
    s._noise(sp, st)
    d = (sp.params["means"].detach() - before).norm(dim=1)
    assert bool((d[:2] > 1e-4).all()) and bool((d[2:] < 1e-9).all()), d


def _assert_penalty_grads(sp: Splats, drawn: torch.Tensor) -> None:
    """The opacity and scale penalties' gradients (weights 0.5, 0.25, means over the whole model) on `drawn` only."""
    o = torch.sigmoid(sp.params["opacity_logits"].detach())
    torch.testing.assert_close(sp.params["opacity_logits"].grad, torch.where(drawn, 0.5 * o * (1 - o) / 10, 0.0))
    scales = sp.params["log_scales"].detach().exp()
    torch.testing.assert_close(sp.params["log_scales"].grad, torch.where(drawn[:, None], 0.25 * scales / 30, 0.0))


@pytest.mark.parametrize("drawn", [torch.ones(10, dtype=torch.bool), torch.arange(10) % 3 == 0],
                         ids=["every-one-drawn", "a-third-drawn"])
def test_penalties_are_a_term_of_the_loss_on_the_gaussians_the_view_draws_alone(drawn):
    """A Gaussian the step's view does not draw gets no penalty (Adam would turn it, its only
    gradient then, into a full step down); the drawn ones get the same gradient as when every
    one is drawn: the mean is still over the whole model."""
    s = _strategy(cap=10, opacity_reg=0.5, scale_reg=0.25)
    sp = _splats(10)
    s.step_pre_backward(sp, s.initial_state(10, torch.device("cpu")), 1, _info(10, drawn)).backward()
    _assert_penalty_grads(sp, drawn)


def test_penalties_stop_at_reg_stop():
    """After `reg_stop` the penalties no longer pull opacities and scales down: the fixed set
    fits the photos alone (lego: +0.27 dB at the fast preset)."""
    s = MCMCStrategy(MCMCStrategyConfig(opacity_reg=0.5, scale_reg=0.25, max_gaussians=10, refine_start=0,
                                        refine_stop=500, refine_every=100), reg_stop=600)
    sp = _splats(10)
    st = s.initial_state(10, torch.device("cpu"))
    s.step_pre_backward(sp, st, 599, _info(10)).backward()
    assert bool((sp.params["opacity_logits"].grad > 0).all())
    assert s.step_pre_backward(sp, st, 600, _info(10)) is None


@pytest.mark.slow
def test_train_with_mcmc_holds_the_budget_and_the_loop_knows_nothing_of_it(tmp_path):
    proj = make_tiny_project(tmp_path / "p", trained=False)
    r = run_cli("train", proj.root, "--strategy", "mcmc", "--max-gaussians", "500", "--iterations", "600",
                "--eval-every", "300", "--json", "-q")
    assert r.exit_code == 0, r.output
    s = json.loads(r.stdout.strip().splitlines()[-1])
    assert s["num_gaussians"] <= 500  # the tiny scene starts at its cap: relocation and noise only
    assert s["psnr"] > 12  # it trains (the default strategy reaches 16.1 dB here, MCMC 14.0)
    stored = json.loads((proj.root / "splatcli.json").read_text())["steps"]["train"]["config"]
    assert stored["strategy"] == "mcmc"
    loop = (REPO / "splatcli" / "train" / "loop.py").read_text().lower()
    assert "mcmc" not in loop  # a new strategy never edits the loop


def test_mcmc_options_are_checked(tmp_path):
    proj = make_tiny_project(tmp_path / "p", trained=False, photos=False)
    assert_user_error(run_cli("train", proj.root, "--strategy", "mcmc", "--iterations", "10"), "--max-gaussians")
    assert_user_error(run_cli("train", proj.root, "--strategy", "annealing"), "--strategy 'annealing'", "mcmc")
    assert_user_error(run_cli("train", proj.root, "--strategy", "mcmc", "--max-gaussians", "9", "--opacity-reset", "9",
                              "--iterations", "9"),
                      "--opacity-reset does not apply to --strategy mcmc")
    mcmc = {"strategy": "mcmc", "max_gaussians": 1000}
    for name, bad in (("mcmc_min_opacity", 0.0), ("mcmc_relocate_until", 1.5), ("mcmc_spread", -1.0),
                      ("mcmc_reg_until", -0.5), ("mcmc_grow_until", 2.0), ("mcmc_shrink", 0.5)):
        with pytest.raises(Exception, match=f"{name} {bad}"):  # a damaged stored config: one line naming the key
            make_config("fast", **mcmc, **{name: bad})
    make_config("fast", **mcmc, mcmc_min_opacity=0.005, mcmc_relocate_until=0.0, mcmc_spread=0.0,
                mcmc_reg_until=1.0, mcmc_shrink=1.0)  # the paper's settings
    with pytest.raises(Exception, match="mcmc_shrink does not apply to --strategy default"):
        make_config("fast", mcmc_shrink=1.0)


def test_a_config_stored_before_mcmc_shrink_resumes_without_shrinking():
    """Checkpoints written before `mcmc_shrink` existed trained with unshrunk copies: a
    resume goes on that way, and a stored value is kept."""
    d = json.loads((REPO / "tests" / "data" / "train_config_dced6d2.json").read_text())["mcmc_run"]
    assert TrainConfig.from_dict(d).mcmc.shrink == 1.6
    del d["mcmc"]["shrink"]
    assert TrainConfig.from_dict(d).mcmc.shrink == 1.0


def test_opacity_and_scale_reg_are_a_step_of_their_own_for_the_default_strategy():
    """--opacity-reg / --scale-reg add the same penalties to a default-strategy run (a
    RegularizeStep after density control), and none when they are 0 (the default)."""
    ctx = context()
    assert not any(isinstance(s, RegularizeStep) for s in make_strategies(make_config("fast"), 1.0, ctx))
    strategies = make_strategies(make_config("fast", opacity_reg=0.5, scale_reg=0.25), 1.0, ctx)
    (step,) = [s for s in strategies if isinstance(s, RegularizeStep)]
    sp = _splats(10)
    step.step_pre_backward(sp, step.initial_state(10, torch.device("cpu"), 0), 1, _info(10)).backward()
    _assert_penalty_grads(sp, torch.ones(10, dtype=torch.bool))
    with pytest.raises(Exception, match="--opacity-reg -1"):
        make_config("fast", opacity_reg=-1.0)
