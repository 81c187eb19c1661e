"""Training end to end on a tiny project (48x40 views): outputs, bitwise resume,
the non-finite guard, the budget, --compact and --sh-degree auto, the CLI."""

from __future__ import annotations

import functools
import json
import math
import os
import signal
import time
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

import splatcli.train.loop as train_mod
from splatcli.cli.main import app
from splatcli.cli.planning import resumed
from splatcli.cli.train_config import make_config
from splatcli.errors import Interrupted, SplatError, TrainingDiverged
from splatcli.eval.evaluate import EvalConfig, plan_eval, run_eval
from splatcli.eval.score import REPORTED
from splatcli.events import Note, Progress
from splatcli.files.checkpoint import load_checkpoint, load_gaussians, save_checkpoint
from splatcli.formats.ply import ply_bytes
from splatcli.options import parse
from splatcli.project import Project
from splatcli.render import rasterize
from splatcli.strategy import cut_steps
from splatcli.train import log
from splatcli.train.config import TrainConfig, TrainSummary
from splatcli.train.log import read_log
from splatcli.train.loop import train
from splatcli.train.plan import (
    LR_HOLD,
    LR_SCALE,
    MEANS_LR,
    OVERHEAD,
    RAISE_AT,
    SCORE_COST,
    SHN_DIV,
    SHN_DIV_FLAT,
    TimePlan,
    step_costs,
)
from splatcli.train.state import learning_rates, means_lr, time_plan
from support.tiny_project import make_tiny_project

CPU = torch.device("cpu")
# Every feature inside 50 steps: SH growth, refinement, an opacity reset, a
# checkpoint, evaluation, then --sh-degree auto, --compact and its fine-tune.
# block="model": the runs here are compared bit for bit, and a measured block (--block auto) follows the clock
SMALL = dict(block="model", iterations=30, init_random_points=300, max_gaussians=600, eval_every=15, log_every=10,
             refine_start=4, refine_every=4, opacity_reset=16, sh_degree_interval=8, checkpoint_every=10,
             grow_grad2d=2e-5)


def tiny(tmp_path, name="p", **kw) -> Project:
    proj = make_tiny_project(tmp_path / name, trained=False, **kw)
    proj.update_manifest(scene={**proj.manifest()["scene"], "bounds_min": [-1.0] * 3, "bounds_max": [1.0] * 3})
    return proj


def _same_params(a: Project, b: Project):
    """Asserts the latest checkpoints of `a` and `b` hold the same parameters, bit for bit; returns both."""
    cka, ckb = load_checkpoint(a.latest_checkpoint(), CPU), load_checkpoint(b.latest_checkpoint(), CPU)
    pa, pb = cka.gaussians.as_dict(), ckb.gaussians.as_dict()
    for k in pa:
        assert torch.equal(pa[k], pb[k]), k  # bitwise, not merely close
    return cka, ckb


def test_train_writes_checkpoint_log_report_and_summary(tmp_path):
    proj = tiny(tmp_path)
    events = []
    s = train(proj.root, make_config(**SMALL), CPU, on_event=events.append)
    assert s.steps == 30 and 0 < s.num_gaussians <= 600 and s.device == "cpu"
    assert s.ply_bytes == ply_bytes(s.num_gaussians, s.sh_degree)
    assert s.psnr is not None and math.isfinite(s.psnr) and s.bad_steps == 0
    rows = read_log(proj.train_log_path)
    assert [r["step"] for r in rows] == [10, 15, 20, 30]
    assert all({"step", "elapsed_s", "loss", "num_gaussians"} <= set(r) for r in rows)
    assert [r["step"] for r in rows if "psnr" in r] == [15, 30]
    # training views are measured beside the held-out ones, at the same points (the gap is overfitting)
    assert [r["step"] for r in rows if "train_psnr" in r] == [15, 30]
    assert all(math.isfinite(r["train_psnr"]) and 0 < r["train_ssim"] <= 1 for r in rows if "train_psnr" in r)
    assert rows[-1]["train_psnr"] != rows[-1]["psnr"]
    assert all(b["elapsed_s"] > a["elapsed_s"] for a, b in zip(rows, rows[1:]))
    # refinement is visible: each line's clone / split / prune counts explain the change in count
    # (a split replaces one Gaussian by two)
    assert sum(r["cloned"] + r["split"] for r in rows) > 0
    for a, b in zip(rows, rows[1:]):
        assert b["num_gaussians"] == a["num_gaussians"] + b["cloned"] + b["split"] - b["pruned"]
    summary = proj.step("train")["summary"]
    assert {"steps", "train_seconds", "num_gaussians", "sh_degree", "ply_bytes", "device", "final_loss"} <= set(summary)
    report = json.loads(proj.train_report_path.read_text())
    assert sum(report["opacity_hist"]["counts"]) == s.num_gaussians
    assert len(report["scale_hist"]["edges"]) == len(report["scale_hist"]["counts"]) + 1
    assert [p.name for _, p in proj.checkpoints()] == ["step-000000020.pt", "step-000000030.pt"]  # keeps 2
    g = load_gaussians(proj.latest_checkpoint(), CPU)
    assert len(g) == s.num_gaussians and g.sh_degree == s.sh_degree == 3
    assert bool(g.finite_mask().all())
    assert any(isinstance(e, Progress) and "gaussians" in e.info for e in events)


def _interrupt_at(step: int):
    def sink(ev):
        if isinstance(ev, Progress) and ev.done == step:
            os.kill(os.getpid(), signal.SIGINT)  # a real signal through the real handler
    return sink


def _at(step: int, elapsed_s: float, world: int = 1) -> SimpleNamespace:
    """The run's progress that log.Eta reads."""
    return SimpleNamespace(step=step, elapsed_s=elapsed_s, world=world)


RESUME_CFG = dict(SMALL, compact=True, compact_finetune=8, sh_degree="auto")


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    a = tiny(tmp_path_factory.mktemp("uninterrupted"), "a")
    return a, train(a.root, make_config(**RESUME_CFG), CPU)


@pytest.mark.parametrize("stop", [13, 34], ids=["while-densifying", "during-compact-finetune"])
def test_interrupt_and_resume_is_bitwise_identical(tmp_path, stop, uninterrupted):
    cfg = make_config(**RESUME_CFG)
    a, sa = uninterrupted
    b = tiny(tmp_path, "b")
    before = signal.getsignal(signal.SIGINT)  # Python's handler, or SIG_IGN under a shell's background `&`
    with pytest.raises(Interrupted):
        train(b.root, cfg, CPU, on_event=_interrupt_at(stop))
    assert b.latest_checkpoint().name == f"step-{stop:09d}.pt"
    assert signal.getsignal(signal.SIGINT) is before  # handler restored
    sb = train(b.root, cfg, CPU, resume=True)
    assert sb.resumed_from == stop and sb.steps == sa.steps == 38
    cka, ckb = _same_params(a, b)
    assert ckb.sh_degree == cka.sh_degree
    for name, st in cka.optimizer.items():
        for key in ("exp_avg", "exp_avg_sq"):
            assert torch.equal(st["state"][0][key], ckb.optimizer[name]["state"][0][key])
    la, lb = read_log(a.train_log_path), read_log(b.train_log_path)
    assert [(r["step"], r["loss"], r["num_gaussians"], r.get("psnr")) for r in la] == \
           [(r["step"], r["loss"], r["num_gaussians"], r.get("psnr")) for r in lb]
    assert sa.compact is not None and sa.compact.after_count < sa.compact.before_count
    assert f"; --compact kept these of {sa.compact.before_count:,} (" in sa.model_line()


def _nan_on(steps: set[int] | None):
    real = rasterize
    calls = {"n": 0}

    def fake(*args, **kw):
        out = real(*args, **kw)
        if torch.is_grad_enabled() and args[0].requires_grad:  # a training step, not evaluation
            calls["n"] += 1
            if steps is None or calls["n"] in steps:
                out.image = out.image * float("nan")
        return out
    return fake


def test_non_finite_steps_are_skipped_and_counted(tmp_path, monkeypatch):
    proj = tiny(tmp_path)
    monkeypatch.setattr(train_mod, "rasterizer", lambda name, f=_nan_on({3, 4, 11}): f)
    s = train(proj.root, make_config(**{**SMALL, "iterations": 12}), CPU)
    assert s.bad_steps == 3 and s.steps == 12
    assert read_log(proj.train_log_path)[-1]["bad_steps"] == 3
    assert bool(load_gaussians(proj.latest_checkpoint(), CPU).finite_mask().all())


def test_divergence_stops_with_a_usable_checkpoint(tmp_path, monkeypatch):
    proj = tiny(tmp_path)
    monkeypatch.setattr(train_mod, "rasterizer", lambda name, f=_nan_on(None): f)
    with pytest.raises(TrainingDiverged) as ei:
        train(proj.root, make_config(**{**SMALL, "max_bad_steps": 4}), CPU)
    msg = str(ei.value)
    assert "4 consecutive" in msg and "step-000000004.pt" in msg and "\n" not in msg
    ck = load_checkpoint(proj.latest_checkpoint(), CPU)
    assert ck.step == 4 and bool(ck.gaussians.finite_mask().all())


def test_budget_is_never_exceeded_and_no_opacity_reset_on_the_last_step(tmp_path):
    proj = tiny(tmp_path)
    s = train(proj.root, make_config(**{**SMALL, "iterations": 16, "max_gaussians": 350, "grow_grad2d": 1e-9,
                                        "log_every": 1, "opacity_reset": 16, "refine_stop": 1000}), CPU)
    counts = [r["num_gaussians"] for r in read_log(proj.train_log_path)]
    assert max(counts) == 350 and s.num_gaussians <= 350  # it grew up to the budget, never past it
    g = load_gaussians(proj.latest_checkpoint(), CPU)
    assert float(torch.sigmoid(g.opacity_logits).max()) > 0.05  # a reset would have clamped all to 0.01


def test_init_respects_budget_and_sh_degree_zero_stores_no_bands(tmp_path):
    proj = tiny(tmp_path)
    s = train(proj.root, make_config(**{**SMALL, "iterations": 6, "max_gaussians": 100, "sh_degree": "0"}), CPU)
    ck = load_checkpoint(proj.latest_checkpoint(), CPU)
    assert ck.gaussians.sh.shape[1] == 1 and s.sh_degree == 0 and len(ck.gaussians) <= 100


def test_cli_train_json_and_resume(tmp_path):
    proj = tiny(tmp_path)
    r = CliRunner().invoke(app, ["train", str(proj.root), "--iterations", "8", "--max-gaussians", "200",
                                 "--eval-every", "4", "--device", "cpu", "--json"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.stdout)
    assert out["steps"] == 8 and out["num_gaussians"] <= 200 and out["psnr"] is not None
    # --block auto (the default): every step drew with the block a BlockTuner measured, and the record says which
    assert sum(out["blocks"]["used"].values()) == 8 and out["blocks"]["ns_per_cost"]
    r = CliRunner().invoke(app, ["train", str(proj.root), "--resume", "--iterations", "12", "--json", "--device", "cpu"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.stdout)
    assert out["resumed_from"] == 8 and out["steps"] == 12


@pytest.mark.parametrize("args,needle", [
    (["--sh-degree", "5"], "--sh-degree"),
    (["--iterations", "0"], "--iterations"),
    (["--preset", "turbo"], "--preset"),
    (["--max-gaussians", "0"], "--max-gaussians"),
    (["--block", "5"], "--block"),
])
def test_cli_bad_options_are_one_line_errors(tmp_path, args, needle):
    proj = tiny(tmp_path)
    r = CliRunner().invoke(app, ["train", str(proj.root), *args])
    assert r.exit_code == 2 and needle in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_cli_refuses_unprocessed_and_unsafe_checkpoint(tmp_path):
    r = CliRunner().invoke(app, ["train", str(tmp_path / "nothing")])
    assert r.exit_code == 2 and r.stderr.startswith("error: ")
    proj = tiny(tmp_path)
    proj.checkpoints_dir.mkdir()

    class Evil:
        def __reduce__(self):
            return (print, ("pwned",))

    torch.save({"x": Evil()}, proj.checkpoint_path(5))
    r = CliRunner().invoke(app, ["train", str(proj.root), "--resume"])
    assert r.exit_code == 2 and "refused" in r.stderr and "pwned" not in r.output


def test_finished_run_resumed_with_compact_equals_a_compact_run(tmp_path, uninterrupted):
    a, sa = uninterrupted  # trained with --compact --sh-degree auto from the start
    b = tiny(tmp_path, "b")
    train(b.root, make_config(**SMALL), CPU)  # a plain run ...
    # ... compacted afterwards. The stored config holds the default compact_finetune;
    # --compact given on resume brings the resuming invocation's setting (8) with it.
    assert make_config(**SMALL).compact.finetune != 8
    sb = train(b.root, resumed(b, make_config(**SMALL, compact_finetune=8), parse(TrainConfig, {"compact": True, "sh_degree": "auto"})),
               CPU, resume=True)
    assert sb.steps == sa.steps and sb.compact.before_count == sa.compact.before_count
    _same_params(a, b)


@pytest.mark.parametrize("quantisation", ["8-bit", "none"])
def test_final_heldout_scores_are_evals(tmp_path, monkeypatch, quantisation):
    """train.json's held-out PSNR / SSIM and eval's of the final model are one figure when
    scored with the same quantisation (eval/score.py), and differ under the other."""
    if quantisation != REPORTED:
        monkeypatch.setattr(train_mod, "evaluate_views",
                            functools.partial(train_mod.evaluate_views, quantisation=quantisation))
    proj = tiny(tmp_path)
    s = train(proj.root, make_config(**SMALL), CPU)
    assert json.loads(proj.train_report_path.read_text())["summary"]["quantisation"] == REPORTED

    def evaluated(q: str):
        return run_eval(plan_eval(proj.root, EvalConfig(budgets=(1.0,), plots=False, write=False, quantisation=q), CPU))

    same = evaluated(quantisation)
    assert [x.name for x in same.per_image] == proj.splits()["test"] and same.quantisation == quantisation
    assert abs(s.psnr - same.psnr) <= 5e-5 and abs(s.ssim - same.ssim) <= 5e-6  # the log's 4 and 5 decimals
    other = evaluated("none" if quantisation == "8-bit" else "8-bit")
    assert abs(same.psnr - other.psnr) > 1e-6  # (at 11 dB, 8 bits move PSNR by only ~1e-4: the log's last digit)


def test_compact_prunes_in_rounds_to_a_third(tmp_path):
    proj = tiny(tmp_path)
    s = train(proj.root, make_config(**SMALL, compact=True, compact_finetune=12, compact_rounds=3), CPU)
    c = s.compact
    # a third to the nearest (gaussians.kept_count, eval's budgets' rule too) of what the default
    # strategy grew (its --max-gaussians is only a ceiling)
    assert c.after_count == math.floor(c.before_count / 3 + 0.5) and s.num_gaussians == c.after_count
    counts = {r["step"]: r["num_gaussians"] for r in read_log(proj.train_log_path)}
    assert counts[30] == round(c.before_count * (1 / 3) ** (1 / 3))  # round 1 of 3 right after training
    assert c.before_psnr is not None and c.after_psnr is not None
    assert s.ply_bytes == ply_bytes(c.after_count, s.sh_degree) == c.after_bytes


def test_coarse_to_fine_trains_and_resumes_bitwise(tmp_path):
    """Steps before `coarse_until` render at a fraction of the resolution; an interrupted
    coarse run resumes to the same bits."""
    cfg = make_config(**{**SMALL, "iterations": 20, "coarse_scale": 0.5, "coarse_until": 0.5})
    a = tiny(tmp_path, "a")
    sa = train(a.root, cfg, CPU)
    assert sa.steps == 20 and sa.psnr is not None and math.isfinite(sa.psnr)
    b = tiny(tmp_path, "b")
    with pytest.raises(Interrupted):
        train(b.root, cfg, CPU, on_event=_interrupt_at(6))
    train(b.root, cfg, CPU, resume=True)
    _same_params(a, b)


def test_time_budget_plans_a_compressed_schedule(tmp_path):
    """--time-budget: the preset's schedule scaled to what fits; the plan is recorded and the
    training seconds end near the budget."""
    proj = tiny(tmp_path)
    budget = 3.0
    # a preset-shaped template far longer than the budget allows
    template = {**SMALL, "iterations": 3000, "refine_start": 300, "refine_every": 100, "opacity_reset": 1500,
                "refine_stop": 2000, "sh_degree_interval": 600}
    events: list = []
    s = train(proj.root, make_config(**template, time_budget=budget), CPU, on_event=events.append)
    plan = s.plan
    assert plan is not None and plan["budget_s"] == budget and plan["template"]["iterations"] == 3000
    etas = [e.eta_s for e in events if isinstance(e, Progress) and e.name == "train"]
    assert etas and all(e is not None and 0.0 <= e <= budget for e in etas)  # the plan's time left
    assert etas[0] > etas[-1] and etas[-1] <= 0.25 * budget
    # The share of the clock, for the bar and the log lines: rising, below 1, and with it the ETA's budget
    shares = [(e.share, e.eta_s) for e in events if isinstance(e, Progress) and e.name == "train" and e.share is not None]
    assert shares and all(0.0 <= sh < 1.0 for sh, _ in shares)
    assert all(a[0] <= b[0] for a, b in zip(shares, shares[1:]))
    assert all(sh * budget + left == pytest.approx(budget) for sh, left in shares)
    assert len(plan["history"]) >= 2 and all(h["steps_per_s"] > 0 for h in plan["history"])
    assert s.steps == plan["history"][-1]["iterations"] < 3000
    assert s.train_seconds <= 1.25 * budget  # a tiny scene: plans are coarse at this scale
    cfg = proj.step("train")["config"]
    ratio = cfg["iterations"] / 3000
    assert cfg["default"]["refine_every"] == max(25, round(100 * ratio))  # never below 25 steps
    assert cfg["default"]["refine_stop"] == max(1, round(2000 * ratio))
    assert cfg["sh_degree_interval"] == max(1, round(600 * ratio))
    assert cfg["appearance"] == "none"  # a --time-budget run keeps none
    assert cfg["lr_scale"] == LR_SCALE and cfg["lr_shN_div"] == SHN_DIV_FLAT  # a planned run's rates, recorded
    groups = {k: o["param_groups"][0]["lr"] for k, o in load_checkpoint(proj.latest_checkpoint()).optimizer.items()}
    assert groups["sh0"] == pytest.approx(LR_SCALE * cfg["lr_sh0"])  # ... and the ones its optimisers ran
    assert groups["shN"] == pytest.approx(groups["sh0"] / SHN_DIV_FLAT)


def test_a_planned_run_learns_at_the_planned_rates_and_a_replan_keeps_them():
    """A budget buys a few thousand steps: every rate x LR_SCALE, the means' x MEANS_LR as well, the
    higher SH bands at 1/SHN_DIV_FLAT of the DC's, or 1/SHN_DIV with an appearance model. Tuning is
    idempotent (plans re-plan their own configs) and leaves a user's higher setting alone (and a lower
    means' share)."""
    cfg = make_config("fast", time_budget=60.0)
    tuned = TimePlan.tuned(cfg)
    assert TimePlan.tuned(tuned) == tuned and TimePlan.start(cfg).scaled(tuned, 700).lr_scale == LR_SCALE
    assert (tuned.lr_hold, tuned.lr_scale, tuned.lr_shN_div) == (LR_HOLD, LR_SCALE, SHN_DIV_FLAT)
    lit = TimePlan.tuned(make_config("fast", time_budget=60.0, appearance="exposure"))
    assert TimePlan.tuned(lit) == lit and lit.lr_shN_div == SHN_DIV > SHN_DIV_FLAT
    base, fast = learning_rates(cfg, 2.0), learning_rates(tuned, 2.0)
    assert all(fast[k] == pytest.approx(LR_SCALE * base[k]) for k in base if k not in ("shN", "means"))
    assert fast["means"] == pytest.approx(LR_SCALE * MEANS_LR * base["means"]) and tuned.lr_means_scale == MEANS_LR
    assert means_lr(tuned, 0, 2.0) == pytest.approx(fast["means"])  # the schedule starts where Adam does
    assert fast["shN"] == pytest.approx(fast["sh0"] / SHN_DIV_FLAT) and fast["shN"] > 2 * base["shN"]
    own = TimePlan.tuned(make_config("fast", time_budget=60.0, lr_scale=2.0, lr_shN_div=5.0, lr_means_scale=0.25))
    assert (own.lr_scale, own.lr_shN_div, own.lr_means_scale) == (2.0, 5.0, 0.25)


def test_a_finished_planned_run_resumed_with_more_time_trains_on_to_the_new_budget(tmp_path):
    """`--resume --time-budget S` on a finished planned run: the schedule reopens and is planned to
    the new total at the speed the run last had; the same budget again has nothing left to do."""
    proj = tiny(tmp_path)
    template = {**SMALL, "iterations": 3000, "refine_start": 300, "refine_every": 100, "refine_stop": 2000}
    first = train(proj.root, make_config(**template, time_budget=2.0), CPU)
    notes = []

    def four_seconds():
        return resumed(proj, make_config(**template, time_budget=4.0), parse(TrainConfig, {"time_budget": 4.0}))

    more = train(proj.root, four_seconds(), CPU, resume=True, on_event=notes.append)
    assert more.steps > first.steps and 2.0 < more.train_seconds <= 1.25 * 4.0
    assert any("extending the run to 4 s" in getattr(n, "message", "") for n in notes)
    assert train(proj.root, four_seconds(), CPU, resume=True).steps == more.steps


def test_a_plan_prices_each_step_by_its_resolution():
    """The speed measured on cheap coarse steps is not promised for the whole run: each
    remaining step costs OVERHEAD + its scale^2 (plan.step_costs), and the plan is the longest
    run whose remaining cost fits the budget. Without coarse steps it is the measured rate
    times the time left, as before."""
    cfg = make_config("fast", time_budget=600.0)
    plan = TimePlan.start(cfg)
    start = plan.scaled(cfg, 7000)
    n = plan.replan(start, 170, 5.0).iterations  # 34 views/s, all at 1/4 size
    unit = 5.0 / step_costs(start, 7000, 0, 170).sum()
    assert step_costs(cfg, n, 170, n).sum() * unit <= 595.0 < step_costs(cfg, n + 1, 170, n + 1).sum() * unit
    assert n < 0.4 * 170 / 5.0 * 600  # extrapolating the coarse speed would plan 20k steps
    flat = make_config("fast", time_budget=600.0, coarse_scale=1.0)
    plan = TimePlan.start(flat)
    assert abs(plan.replan(plan.scaled(flat, 7000), 170, 5.0).iterations - (170 + 170 / 5.0 * 595.0)) <= 1


def test_a_plan_raises_the_gaussian_budget_by_the_steps_it_affords():
    """A short run's count may rise (time_budget_gaussians, chosen for a capture seen all round): once,
    at the first plan from RAISE_AT of the budget, the cap becomes cap x (steps planned / RAISE_STEPS), in
    thousands, at least as it was and at most the count allowed; later plans keep it; never with --compact
    (its cuts keep a share of the cap). The decision is in the plan's record, which a resumed run reads,
    and in the model's line. Without coarse steps, a plan is the measured rate times the time left."""
    def plan_at(rate: float, **over) -> tuple[TimePlan, TrainConfig]:
        cfg = make_config("fast", time_budget=100.0, strategy="mcmc", max_gaussians=39_000, coarse_scale=1.0,
                          time_budget_gaussians=72_000, **over)
        plan = TimePlan.start(cfg)
        run = plan.replan(plan.scaled(cfg, 7000), int(rate * 5), 5.0)  # the probe's plan: before RAISE_AT
        assert plan.cap == 39_000 and run.refine.max_gaussians == 39_000 and plan.budget_s * RAISE_AT == 20.0
        assert plan.replan(run, int(rate * 15), 15.0).refine.max_gaussians == 39_000  # (nor a plan before RAISE_AT)
        return plan, plan.replan(run, int(rate * 20), 20.0) or run

    for rate, cap in ((20.0, 72_000), (14.0, 55_000), (8.0, 39_000)):  # 2,000, 1,400 and 800 steps planned
        plan, run = plan_at(rate)
        steps = plan.history[-1]["iterations"]
        assert plan.history[-1]["raised"] == {"from": 39_000, "to": cap, "steps": steps}, rate
        assert plan.cap == run.refine.max_gaussians == cap and abs(steps - int(rate * 100)) <= 1
        later = plan.replan(run, int(rate * 40), 40.0)
        assert plan.cap == later.refine.max_gaussians == cap and "raised" not in plan.history[-1]
        assert TimePlan.from_record(json.loads(json.dumps(plan.record()))).record() == plan.record()
        said = TrainSummary(1, 1.0, cap, 3, 1, "cpu", 0.0, plan=plan.record()).model_line()
        assert (f"raised max-gaussians from 39,000 to {cap:,}" if cap > 39_000 else "kept max-gaussians at 39,000") in said
        assert said.endswith(f"(time for {steps:,} steps, planned at 20 s of 100)"), said
        if cap > 39_000:  # growth ends at a share of the steps: a run that trained fewer grew short of the cap
            short = TrainSummary(steps - 300, 1.0, cap - 6_000, 3, 1, "cpu", 0.0, plan=plan.record()).model_line()
            assert short.endswith(f", and growth ended at {(cap - 6_000) / cap:.0%} of it: the run trained "
                                  f"{steps - 300:,} steps"), short
    plan, run = plan_at(20.0, compact=True)
    assert plan.cap == 39_000 and "raised" not in plan.history[-1]
    cfg = make_config("fast", time_budget=100.0, strategy="mcmc", max_gaussians=39_000)
    assert TimePlan.start(cfg).up_to is None


def test_the_summary_says_why_the_model_has_its_count():
    """A count `train` chose, neither raised by a plan nor cut by --compact: the summary's model
    line gives the reason the plan line gave before the first step."""
    why = "0.225 per pixel of a 129,600-pixel training view"
    chosen = [{"option": "max_gaussians", "value": 29_000, "why": why}]
    line = TrainSummary(1, 1.0, 29_000, 3, 1, "cpu", 0.0, chosen=chosen).model_line()
    assert line.endswith(f"; the count chosen for the capture: {why}"), line
    assert "chosen" not in TrainSummary(1, 1.0, 29_000, 3, 1, "cpu", 0.0).model_line()  # a count given: nothing to say


def test_a_plan_with_compact_fits_the_fine_tune_into_the_budget():
    """--compact in a planned run: the main steps and the fine-tune a run of that length ends with
    (the template's, scaled with it) fit the time left together, the fine-tune's steps priced at
    full size; once the main steps are over, the fine-tune is lengthened to the time left at the
    speed it runs (its cuts make its steps cheaper). Simulated, planned every tenth of the budget,
    fine-tune steps at half the price: the run ends at the budget (a share of the time left,
    planned again and again, had pushed the fine-tune past it: lego's 600 s run was 69% through
    its steps when the budget was spent)."""
    cfg = make_config("fast", time_budget=600.0, compact=True)
    plan = TimePlan.start(cfg)
    run, views, elapsed, unit = plan.scaled(cfg, 7000), 0, 0.0, 0.02  # seconds per unit of cost

    def costs(c, a, b):  # the fine-tune's steps (past c.iterations) at half the price of a full one
        full = step_costs(c, c.iterations, a, b)
        return np.where(np.arange(a, b) >= c.iterations, 0.5 * full, full) * unit

    first, main = True, None
    while views < run.total_steps:
        t = elapsed + (5.0 if first else 60.0)
        nxt = min(run.total_steps, views + int(np.searchsorted(np.cumsum(costs(run, views, run.total_steps)),
                                                               t - elapsed, side="right")))
        elapsed += float(costs(run, views, nxt).sum())
        views, first = nxt, False
        if views < run.total_steps and (plan.due(elapsed) or plan.finetune_due(run, views, elapsed)):
            if views >= run.iterations and main is None:
                main = run  # the plan as the main steps ended
            run = plan.replan(run, views, elapsed) or run
    assert main is not None and main.compact.finetune == round(3000 * main.iterations / 7000) > 0
    assert run.iterations == main.iterations and run.compact.finetune > main.compact.finetune  # lengthened
    assert 0.95 * 600.0 <= elapsed <= 600.0 * 1.01, (run.iterations, run.compact.finetune, elapsed)


def _compacted_run(scored: int, priced: bool, unit: float) -> float:
    """A planned --compact run simulated step by step (`unit` seconds per unit of cost, fine-tune steps
    at half the price), each cut scoring `scored` views at SCORE_COST of a full-size step on the model
    it cuts (strategy.cut_steps: the first when the main steps end, the others spread over the
    fine-tune's first half); planned with the cuts priced, or not. Returns the training seconds."""
    cfg = make_config("fast", time_budget=600.0, compact=True)
    plan = TimePlan.start(cfg, scored if priced else 0)
    run, views, elapsed, cuts = plan.scaled(cfg, 7000), 0, 0.0, 0
    rounds, keep = cfg.compact.rounds, cfg.compact.keep
    while views < run.total_steps:
        full = float(step_costs(run, run.iterations, views, views + 1)[0])
        elapsed += (0.5 if views >= run.iterations else 1.0) * full * unit
        views += 1
        if cuts < rounds and views == cut_steps(run.compact, run.iterations)[cuts]:
            elapsed += scored * SCORE_COST * (OVERHEAD + 1.0) * keep ** (cuts / rounds) * unit
            cuts += 1
        if views < run.total_steps and (plan.due(elapsed) or plan.finetune_due(run, views, elapsed)):
            run = plan.replan(run, views, elapsed) or run
    assert cuts == rounds
    return elapsed


def test_every_rank_prices_the_cuts_at_the_largest_share_of_the_views():
    cfg = make_config("fast", time_budget=600.0, compact=True)
    assert [time_plan(cfg, None, 87, k).scored for k in (1, 2, 3)] == [87, 44, 29]
    resumed = time_plan(cfg, time_plan(cfg, None, 87, 1).record(), 87, 2)  # (a resume on another count)
    assert resumed is not None and resumed.scored == 44


def test_a_plan_leaves_the_compaction_cuts_their_scoring_time():
    """Each --compact cut scores every training view (CompactStep, render/weights.py). On a host slow
    enough that the cuts cost a quarter to a half of the budget: priced, the main steps end early
    enough for them, the fine-tune is lengthened to the time its cuts leave, and the run ends at its
    budget; unpriced (as before), the cuts overran it by 20-66% (lego grown to 207,000 on a loaded
    2-core host: 857 s of a 600 s budget)."""
    for scored, unit in ((200, 1.2), (400, 0.6), (400, 1.2), (87, 0.6)):
        assert 0.97 * 600.0 <= _compacted_run(scored, priced=True, unit=unit) <= 600.0 * 1.01, (scored, unit)
    assert _compacted_run(200, priced=False, unit=1.2) > 600.0 * 1.15
    assert _compacted_run(400, priced=False, unit=0.6) > 600.0 * 1.15


def test_a_fine_tune_still_going_when_the_budget_is_spent_ends_there():
    """Lengthened at a speed it then falls short of, the fine-tune ends with the step after the one
    that spends the budget once past its first half (where the cuts are), in one plan (it had planned
    again at every step); before its half, it goes on."""
    cfg = make_config("fast", time_budget=600.0, compact=True)
    plan = TimePlan.start(cfg)
    run = plan.scaled(cfg, 2000)
    plan.history = [{"step": 1900, "elapsed_s": 500.0, "steps_per_s": 6.0, "iterations": 2000, "compact_finetune": 1200}]
    run = replace(run, compact=replace(run.compact, finetune=1200))
    assert plan.replan(run, 2500, 600.5) is None  # 500 of 1,200 done: its cuts are not all made
    ended = plan.replan(run, 2700, 601.0)
    assert ended is not None and ended.total_steps == 2701 and plan.history[-1]["fine_tune"] == "ended"
    assert ended.for_world(2).total_steps == 1350  # two ranks at step 1,350: it ends there (or one step later)
    assert plan.replan(ended, 2701, 601.2) is None and len(plan.history) == 3  # planned once


def test_a_compacted_run_given_more_time_fine_tunes_on():
    """--resume --time-budget on a finished compacted run lengthens its fine-tune at its last speed:
    reopening the main steps would grow the kept model back to the cap with no cut after it."""
    cfg = make_config("fast", time_budget=600.0, compact=True)
    plan = TimePlan.start(cfg)
    run = plan.scaled(cfg, 2000)
    run = replace(run, compact=replace(run.compact, finetune=1201))
    plan.history = [{"step": 3000, "elapsed_s": 590.0, "steps_per_s": 7.0, "iterations": 2000, "compact_finetune": 1200},
                    {"step": 3200, "elapsed_s": 600.2, "fine_tune": "ended", "iterations": 2000, "compact_finetune": 1201}]
    plan.budget_s = 900.0
    more = plan.extend(run, 3201, 600.2)
    assert more is not None and more.iterations == 2000 and more.compact.finetune == 1201 + int(7.0 * 299.8)
    ended = plan.replan(more, 5200, 900.5)  # and ends at the new budget as before (the old end no longer holds it)
    assert ended is not None and ended.total_steps == 5201 and plan.history[-1]["fine_tune"] == "ended"


def test_a_planned_run_past_its_budget_says_the_views_left_at_its_last_speed():
    """The ETA of a planned run is the budget left; past it (the step that ends a run once its budget is
    spent, which a loaded machine can leave well past; a finished run resumed with --compact) it is the
    views left at the last speed measured, never unknown once a plan has measured one."""
    plan = TimePlan.start(make_config("fast", time_budget=3.0))
    assert plan.seconds_left(10, 50, 1.0) == 2.0
    assert plan.seconds_left(60, 61, 3.2) is None  # nothing measured yet
    plan.history = [{"step": 40, "elapsed_s": 1.0, "steps_per_s": 20.0, "iterations": 61}]
    assert plan.seconds_left(60, 61, 3.2) == pytest.approx(1 / 20.0)
    assert plan.seconds_left(61, 61, 3.3) == 0.0
    assert plan.seconds_left(1061, 2061, 30.0) == pytest.approx(50.0)  # a fine-tune added on resume


def test_the_eta_of_a_step_schedule_prices_the_steps_left_by_their_resolution():
    """A run without a time budget says once, after ETA_AFTER_S training seconds, how long is left:
    the steps left at the measured speed, each priced by its coarse-to-fine scale as plans price
    them (the fast preset's first steps are 1/8 of a full step's pixels), and said as a lower bound."""
    def told(cfg, step, elapsed, world=1):
        notes = []
        eta = log.Eta(_at(0, 0.0, world), cfg)
        eta.tell(_at(step, log.ETA_AFTER_S / 2, world), 0, notes.append)
        assert notes == []  # too soon
        eta.tell(_at(step, elapsed, world), 0, notes.append)
        eta.tell(_at(step + 1, elapsed + 1, world), 0, notes.append)
        assert len(notes) == 1 and isinstance(notes[0], Note)  # once
        return notes[0].message

    fast = make_config("fast", iterations=7000)
    left = 20.0 * step_costs(fast, 7000, 100, 7000).sum() / step_costs(fast, 7000, 0, 100).sum()
    assert left > 3 * (6900 / 100 * 20.0)  # the coarse speed alone would promise a third of it
    msg = told(fast, 100, 20.0)
    assert msg.startswith(f"at least {log.duration(left)} of training left at 5.00 steps/s"), msg
    flat = make_config("demo")  # no coarse steps: the measured rate times the steps left
    msg = told(flat, 200, 20.0, world=2)
    assert msg.startswith(f"at least {log.duration(1300 / 10.0)} of training left at 20.00 steps/s"), msg


def test_the_progress_eta_is_the_plans_time_left_or_the_priced_steps_left():
    """The time left that the progress bar and the log lines show: a planned run's budget less its
    training seconds; a run without a plan, its steps left priced by resolution (as the note says),
    None until ETA_AFTER_S seconds are measured, estimated again at most once a second."""
    fast = make_config("fast", iterations=7000)
    eta = log.Eta(_at(0, 0.0), fast)
    assert eta.left(_at(50, log.ETA_AFTER_S / 2)) is None
    left = 20.0 * step_costs(fast, 7000, 100, 7000).sum() / step_costs(fast, 7000, 0, 100).sum()
    assert eta.left(_at(100, 20.0)) == pytest.approx(left)
    assert eta.left(_at(200, 20.5)) == pytest.approx(left)  # (within the second)


def test_the_eta_is_measured_from_the_end_of_the_first_step(tmp_path, monkeypatch):
    """A run's first step carries one-off costs (kernels loaded from the cache, first allocations:
    11 s of the full preset's first 20 on lego, where its first note then said 17 h and a minute
    later 12 h). The ETA measures the steps after it."""
    from splatcli.train.trainer import Trainer

    step = Trainer.step

    def slow_first(self, i, *a, **kw):
        if i == 1:
            time.sleep(1.0)
        return step(self, i, *a, **kw)

    monkeypatch.setattr(Trainer, "step", slow_first)
    monkeypatch.setattr(log, "ETA_AFTER_S", 0.3)
    notes = []
    train(tiny(tmp_path).root, make_config(**dict(SMALL, eval_every=0, iterations=60)), CPU,
          on_event=lambda e: notes.append(e.message) if isinstance(e, Note) else None)
    said = next(m for m in notes if m.startswith("at least"))
    rate = float(said.split(" steps/s")[0].split(" at ")[-1])
    assert rate > 3.0, said  # measured from the start, about 1 step a second


def test_a_second_eta_comes_once_the_model_has_stopped_growing():
    """The first estimate is a lower bound (the model grows after it); once the strategy stops
    refining (the demo preset: step 900 of 1,500), the speed of the grown model is measured again
    for ETA_AFTER_S seconds and the time left said once more, as "about"."""
    demo, notes = make_config("demo"), []
    eta = log.Eta(_at(0, 0.0), demo)
    for step, elapsed in ((200, 20.0), (899, 90.0), (950, 100.0), (990, 100.0 + log.ETA_AFTER_S / 2),
                          (1000, 100.0 + log.ETA_AFTER_S), (1100, 200.0)):
        eta.tell(_at(step, elapsed), 20_000, notes.append)
    said = [n.message for n in notes]
    assert len(said) == 2 and said[0].startswith("at least "), said
    rate = 50 / log.ETA_AFTER_S  # steps 950..1000 in ETA_AFTER_S seconds
    assert said[1] == (f"the model has stopped growing (20,000 Gaussians): about {log.duration(500 / rate)} of "
                       f"training left at {rate:.2f} steps/s"), said[1]


def test_plan_keeps_a_switched_off_reset_off():
    cfg = make_config("fast", opacity_reset=0, time_budget=60.0)
    scaled = TimePlan.start(cfg).scaled(cfg, 700)
    assert scaled.default.opacity_reset == 0 and scaled.default.refine_stop == 400
    assert make_config("demo").default.opacity_reset == 0
    with pytest.raises(SplatError, match="--opacity-reset -1"):
        make_config(opacity_reset=-1)


@pytest.mark.parametrize("key,value", [("refine_every", 0), ("iterations", "many"), ("sh_degree", "seven"),
                                       ("checkpoint_every", -1), ("lr_means", float("nan"))])
def test_resume_from_a_checkpoint_with_a_garbled_config_is_one_line(tmp_path, key, value):
    """The stored train config is read like any other input: exit 2 naming the file and key."""
    proj = tiny(tmp_path, photos=False)
    args = ["train", str(proj.root), "--max-gaussians", "150", "--eval-every", "0", "--quiet", "--device", "cpu"]
    assert CliRunner().invoke(app, [*args, "--iterations", "3"]).exit_code == 0
    path = proj.latest_checkpoint()
    ck = load_checkpoint(path)
    cfg = dict(ck.config)
    if key in cfg:
        cfg[key] = value
    else:
        cfg["default"] = {**cfg["default"], key: value}
    save_checkpoint(path, step=ck.step, gaussians=ck.gaussians, sh_degree=ck.sh_degree, optimizer=ck.optimizer,
                    strategy=ck.strategy, rng=ck.rng, config=cfg, extra=ck.extra)
    r = CliRunner().invoke(app, [*args, "--resume", "--iterations", "5"])
    assert r.exit_code == 2, r.output
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and str(path) in lines[0], r.stderr
    assert key in lines[0] or key.replace("_", "-") in lines[0], r.stderr

