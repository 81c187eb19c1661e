"""Density control: parameter and Adam-state edits stay aligned; clone / split /
prune / reset / budget do what 3DGS specifies."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from splatcli.render.output import RenderOutput
from splatcli.strategy import DefaultStrategy, DefaultStrategyConfig, Splats, StepInfo, ops


def _params(n: int = 6, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    p = {
        "means": torch.randn(n, 3, generator=g),
        "quats": torch.randn(n, 4, generator=g),
        "log_scales": torch.full((n, 3), math.log(0.01)),
        "opacity_logits": torch.zeros(n),
        "sh0": torch.randn(n, 1, 3, generator=g),
        "shN": torch.randn(n, 3, 3, generator=g),
    }
    params = {k: nn.Parameter(v) for k, v in p.items()}
    optims = {k: torch.optim.Adam([v], lr=1e-2, eps=1e-15) for k, v in params.items()}
    return params, optims


def _adam_step(params, optims, seed: int = 1):
    g = torch.Generator().manual_seed(seed)
    for k, p in params.items():
        p.grad = torch.randn(p.shape, generator=g)
        optims[k].step()
        optims[k].zero_grad()


def _moment(optims, params, name, key="exp_avg"):
    return optims[name].state[params[name]][key]


def test_keep_and_append_move_moments_with_rows():
    params, optims = _params()
    _adam_step(params, optims)
    before = {k: (p.detach().clone(), _moment(optims, params, k).clone()) for k, p in params.items()}
    mask = torch.tensor([True, False, True, True, False, True])
    ops.keep(Splats(params, optims), mask)
    for k, (v, m) in before.items():
        assert torch.equal(params[k].detach(), v[mask])
        assert torch.equal(_moment(optims, params, k), m[mask])
        assert optims[k].param_groups[0]["params"][0] is params[k]
    ops.append(Splats(params, optims), {k: torch.ones(2, *p.shape[1:]) for k, p in params.items()})
    for k, p in params.items():
        assert p.shape[0] == 6
        assert torch.equal(_moment(optims, params, k)[4:], torch.zeros(2, *p.shape[1:]))
        assert torch.equal(_moment(optims, params, k, "exp_avg_sq")[4:], torch.zeros(2, *p.shape[1:]))
    _adam_step(params, optims, seed=2)  # the optimiser still works on the new tensors
    assert all(torch.isfinite(p).all() for p in params.values())


def test_edit_matches_an_optimizer_built_on_the_subset():
    """Pruning then stepping == stepping an Adam that only ever saw the kept rows."""
    params, optims = _params()
    _adam_step(params, optims)
    mask = torch.tensor([True, True, False, True, False, True])
    ref = {k: nn.Parameter(p.detach()[mask].clone()) for k, p in params.items()}
    ref_opt = {}
    for k, p in ref.items():
        o = torch.optim.Adam([p], lr=1e-2, eps=1e-15)
        st = optims[k].state[params[k]]
        o.state[p] = {"step": st["step"].clone(), "exp_avg": st["exp_avg"][mask].clone(),
                      "exp_avg_sq": st["exp_avg_sq"][mask].clone()}
        ref_opt[k] = o
    ops.keep(Splats(params, optims), mask)
    _adam_step(params, optims, seed=5)
    _adam_step(ref, ref_opt, seed=5)
    for k in params:
        torch.testing.assert_close(params[k].detach(), ref[k].detach(), rtol=0, atol=0)


def test_split_samples_inside_and_shrinks():
    params, optims = _params(n=4)
    sel = torch.tensor([False, True, False, True])
    old_means = params["means"].detach()[sel]
    gen = torch.Generator().manual_seed(3)
    ops.split(Splats(params, optims), sel, gen)
    assert params["means"].shape[0] == 2 + 4
    new = params["means"].detach()[2:].reshape(2, 2, 3)
    assert (new - old_means[None]).norm(dim=-1).max() < 0.01 * 6  # within ~6 sigma of the parent
    torch.testing.assert_close(params["log_scales"].detach()[2:], torch.full((4, 3), math.log(0.01 / 1.6)))


def _info(n: int, grad: torch.Tensor, radii=None, visible=None, w=32, h=32) -> StepInfo:
    means2d = torch.zeros(n, 2, requires_grad=True)
    means2d.grad = grad
    r = RenderOutput(
        image=torch.zeros(h, w, 3), alpha=torch.zeros(h, w), depth=torch.zeros(h, w), means2d=means2d,
        radii=torch.full((n,), 2, dtype=torch.int32) if radii is None else radii,
        visible=torch.ones(n, dtype=torch.bool) if visible is None else visible, depths=torch.ones(n),
    )
    return StepInfo(render=r, width=w, height=h)


def test_refine_clones_small_splits_large_prunes_transparent():
    params, optims = _params(n=5)
    with torch.no_grad():
        params["log_scales"][3] = math.log(0.5)  # large: > 1% of extent 1
        params["opacity_logits"][4] = -10.0  # transparent: pruned
    cfg = DefaultStrategyConfig(refine_start=0, refine_every=1, opacity_reset=1000)
    s = DefaultStrategy(cfg, scene_extent=1.0)
    state = s.initial_state(5, torch.device("cpu"))
    grad = torch.zeros(5, 2)
    grad[[0, 3]] = 1e-3  # x16 px -> NDC: well above 2e-4
    stats = s.step_post_backward(Splats(params, optims, [state]), state, 1, _info(5, grad))
    assert (stats.cloned, stats.split, stats.pruned) == (1, 1, 1)
    assert stats.after == 5 - 1 - 1 + 1 + 2 == params["means"].shape[0]
    assert state.grad2d.shape[0] == stats.after and state.grad2d.abs().sum() == 0  # restarted


def test_accumulates_only_visible_and_in_ndc_units():
    params, optims = _params(n=3)
    s = DefaultStrategy(DefaultStrategyConfig(), scene_extent=1.0)
    state = s.initial_state(3, torch.device("cpu"))
    grad = torch.tensor([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    vis = torch.tensor([True, True, False])
    s.step_post_backward(Splats(params, optims, [state]), state, 1, _info(3, grad, visible=vis, w=40, h=20))
    torch.testing.assert_close(state.grad2d, torch.tensor([20.0, 10.0, 0.0]))
    torch.testing.assert_close(state.count, torch.tensor([1.0, 1.0, 0.0]))


def test_budget_is_never_exceeded_and_takes_highest_gradients():
    n, budget = 10, 13
    params, optims = _params(n=n)
    cfg = DefaultStrategyConfig(refine_start=0, refine_every=1, opacity_reset=1000, max_gaussians=budget)
    s = DefaultStrategy(cfg, scene_extent=1.0)
    state = s.initial_state(n, torch.device("cpu"))
    grad = torch.zeros(n, 2)
    grad[:, 0] = torch.linspace(1e-3, 2e-3, n)  # every one is a candidate; the last three are highest
    stats = s.step_post_backward(Splats(params, optims, [state]), state, 1, _info(n, grad))
    assert stats.after == budget and stats.cloned == 3 and stats.held_by_budget == 7
    clones = params["means"].detach()[n:]
    assert torch.equal(clones, params["means"].detach()[n - 3:n])  # copies of the top three


def test_opacity_reset_clamps_and_zeroes_moments():
    params, optims = _params(n=4)
    with torch.no_grad():
        params["opacity_logits"].copy_(torch.tensor([-8.0, 0.0, 3.0, -4.0]))
    _adam_step(params, optims)
    s = DefaultStrategy(DefaultStrategyConfig(opacity_reset=7), scene_extent=1.0)
    state = s.initial_state(4, torch.device("cpu"))
    stats = s.step_post_backward(Splats(params, optims, [state]), state, 7, _info(4, torch.zeros(4, 2)))
    assert stats.reset_opacity
    op = torch.sigmoid(params["opacity_logits"].detach())
    assert op.max() <= 0.01 + 1e-6 and op[0] < 0.001  # low ones stay low
    assert _moment(optims, params, "opacity_logits").abs().sum() == 0


def test_opacity_reset_zero_never_resets_nor_prunes_by_size():
    params, optims = _params(n=4)
    with torch.no_grad():
        params["opacity_logits"].copy_(torch.tensor([0.0, 1.0, 3.0, 2.0]))
        params["log_scales"][0] = 5.0  # far larger than prune_scale3d x extent
    before = params["opacity_logits"].detach().clone()
    s = DefaultStrategy(DefaultStrategyConfig(opacity_reset=0, refine_start=0, refine_every=100), scene_extent=1.0)
    state = s.initial_state(4, torch.device("cpu"))
    for step in (100, 3000, 6000):
        stats = s.step_post_backward(Splats(params, optims, [state]), state, step, _info(4, torch.zeros(4, 2)))
        assert not stats.reset_opacity and stats.pruned == 0
    assert torch.equal(params["opacity_logits"].detach(), before)


def test_state_dict_round_trip():
    s = DefaultStrategy(DefaultStrategyConfig(), scene_extent=2.0)
    a = s.initial_state(3, torch.device("cpu"), seed=4)
    a.grad2d += 1
    torch.randn(2, generator=a.generator)
    b = s.initial_state(3, torch.device("cpu"), seed=9)
    b.load_state_dict(a.state_dict())
    assert torch.equal(b.grad2d, a.grad2d)
    assert torch.equal(torch.randn(3, generator=a.generator), torch.randn(3, generator=b.generator))


@pytest.mark.parametrize("step", [1, 15_000, 20_000])
def test_nothing_happens_outside_the_refine_window(step):
    params, optims = _params(n=4)
    s = DefaultStrategy(DefaultStrategyConfig(), scene_extent=1.0)
    state = s.initial_state(4, torch.device("cpu"))
    stats = s.step_post_backward(Splats(params, optims, [state]), state, step, _info(4, torch.full((4, 2), 1.0)))
    assert not stats.changed and params["means"].shape[0] == 4


def test_ops_keep_every_strategy_row_in_step():
    """A prune or an append edits the strategies' per-Gaussian rows in the same call:
    no caller resets or slices accumulators by hand."""
    params, optims = _params(n=5)
    s = DefaultStrategy(DefaultStrategyConfig(), scene_extent=1.0)
    state = s.initial_state(5, torch.device("cpu"))
    state.grad2d += torch.arange(5.0)
    splats = Splats(params, optims, [state])
    ops.keep(splats, torch.tensor([True, False, True, False, True]))
    assert torch.equal(state.grad2d, torch.tensor([0.0, 2.0, 4.0]))
    assert state.count.shape == state.radii.shape == (3,)
    ops.append(splats, {k: torch.ones(2, *p.shape[1:]) for k, p in params.items()})
    assert torch.equal(state.grad2d, torch.tensor([0.0, 2.0, 4.0, 0.0, 0.0]))


def test_generator_state_from_another_kind_of_device_reseeds_deterministically():
    """A CUDA run resumed on the CPU: its 16-byte Philox state cannot drive a CPU
    generator; the strategy's stream is seeded from it instead, the same way each time."""
    s = DefaultStrategy(DefaultStrategyConfig(), 1.0)
    cuda_like = torch.arange(16, dtype=torch.uint8)  # the size of a CUDA generator's state
    draws = []
    for _ in range(2):
        st = s.initial_state(5, torch.device("cpu"))
        st.load_state_dict({"generator": cuda_like})
        draws.append(torch.rand(4, generator=st.generator))
    assert torch.equal(draws[0], draws[1])
    fresh = torch.rand(4, generator=s.initial_state(5, torch.device("cpu")).generator)
    assert not torch.equal(draws[0], fresh)
