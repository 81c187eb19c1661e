"""Train options are declared once, at the config's fields (splatcli/options.py): the
command line, make_config and stored configs read that table; the typed code that scales
the schedule is held to it here."""

from __future__ import annotations

import json
from dataclasses import fields
from pathlib import Path

import pytest
from typer.testing import CliRunner

from splatcli.cli.main import app
from splatcli.cli.train_config import make_config, preset_options
from splatcli.errors import SplatError
from splatcli.options import GROUPS, check, resolve, steps_options, table, value
from splatcli.train.config import PRESETS, TrainConfig, preset_config
from splatcli.train.plan import Schedule
from splatcli.train.state import make_strategies
from support.context import context

REPO = Path(__file__).resolve().parents[1]
STORED = json.loads((REPO / "tests" / "data" / "train_config_dced6d2.json").read_text())


def test_every_command_line_option_comes_from_a_config_field():
    """`train --help` lists each option of the table that has a heading, under it, and
    cli/train_cmd.py declares none of them itself."""
    r = CliRunner().invoke(app, ["train", "--help"], env={"COLUMNS": "200"})
    assert r.exit_code == 0
    on_cli = [alts[0] for alts in table(TrainConfig).values() if alts[0].on_cli]
    assert len(on_cli) >= 20
    for group in GROUPS:
        assert group in r.stdout, group
    source = (REPO / "splatcli" / "cli" / "train_cmd.py").read_text()
    assert len(source.splitlines()) <= 60
    for o in on_cli:
        assert o.flag in r.stdout and f'"{o.flag}"' not in source, o.flag


def test_help_shows_the_defaults_the_config_and_presets_give():
    r = CliRunner().invoke(app, ["train", "--help"], env={"COLUMNS": "400"})
    text = " ".join(r.stdout.split())
    assert "(default: 30000; --preset fast 7000, demo 1500)" in text
    assert "(default: 0; --strategy mcmc: 0.01)" in text  # --opacity-reg: each strategy has its own


def test_shared_options_go_to_the_chosen_strategy():
    d = make_config("fast", max_gaussians=500, refine_stop=3000)
    assert d.default.max_gaussians == 500 and d.default.refine_stop == 3000 and d.mcmc.max_gaussians is None
    m = make_config("fast", strategy="mcmc", max_gaussians=500, opacity_reg=0.02)
    assert m.mcmc.max_gaussians == 500 and m.mcmc.opacity_reg == 0.02 and m.default.max_gaussians is None
    assert m.mcmc.refine_stop == 4000  # the preset's schedule, in mcmc's own section
    assert m.default.opacity_reg == 0.0  # no second penalty on top of mcmc's
    assert value(m, "refine_stop") == 4000 and m.refine is m.mcmc
    assert m.with_refine(max_gaussians=7).mcmc.max_gaussians == 7 and d.with_refine(max_gaussians=7).default.max_gaussians == 7


def test_an_option_of_the_other_strategy_is_a_one_line_error():
    with pytest.raises(SplatError, match="--opacity-reset does not apply to --strategy mcmc") as e:
        make_config(strategy="mcmc", max_gaussians=10, opacity_reset=100)
    assert "\n" not in str(e.value)
    make_config("fast", strategy="mcmc", max_gaussians=10)  # the preset's opacity_reset is left out silently


def test_opacity_reg_with_mcmc_sets_its_own_penalty():
    from splatcli.strategy import MCMCStrategy, RegularizeStep

    cfg = make_config("fast", strategy="mcmc", max_gaussians=100, opacity_reg=0.05)
    strategies = make_strategies(cfg, 1.0, context())
    assert not any(isinstance(s, RegularizeStep) for s in strategies)
    (m,) = [s for s in strategies if isinstance(s, MCMCStrategy)]
    assert m.config.opacity_reg == 0.05 and m.cap == 100


@pytest.mark.parametrize("run", ["mcmc_run", "default_run"])
def test_a_config_stored_by_dced6d2_loads_as_it_trained(run):
    """The stored form before the strategies had their own sections (written by that
    version's TrainConfig.to_dict, tests/data): every value lands where it acts now."""
    old = STORED[run]
    cfg = TrainConfig.from_dict(old)
    assert cfg.strategy == old["density"]
    assert cfg.refine.refine_stop == old["strategy"]["refine_stop"]
    assert cfg.refine.max_gaussians == old["strategy"]["max_gaussians"]
    assert cfg.iterations == old["iterations"] and cfg.appearance == old["appearance"]
    if run == "mcmc_run":
        assert cfg.mcmc.shrink == old["mcmc"]["shrink"] and cfg.mcmc.max_gaussians == 60000
        assert cfg.mcmc.opacity_reg == pytest.approx(old["mcmc"]["opacity_reg"] + old["reg"]["opacity_reg"])
    else:
        assert cfg.default.opacity_reset == old["strategy"]["reset_every"] == 700
        assert cfg.default.scale_reg == old["reg"]["scale_reg"] and cfg.support.prune_views == 2
        assert cfg.compact.enabled and cfg.sh_degree == "auto" and cfg.time_budget == 120.0
    assert TrainConfig.from_dict(cfg.to_dict()) == cfg  # and today's form round-trips


def test_every_field_has_its_option():
    """A field without `opt` metadata would be a value no option names (device and renderer,
    resolved from options every command shares, are the record-only fields)."""
    names = {o.path for alts in table(TrainConfig).values() for o in alts}
    for f in fields(TrainConfig):
        if "section" not in f.metadata and f.name not in ("device", "renderer"):
            assert (f.name,) in names, f.name
    for preset in preset_options().values():
        assert set(preset) <= set(table(TrainConfig))


@pytest.mark.parametrize("strategy", ["default", "mcmc"])
def test_the_typed_schedule_code_covers_every_count_of_steps(strategy):
    """TrainConfig.for_world and the time plan's Schedule name their fields in code (no option
    names past the command line): each count of steps an option declares (`steps=`) is in
    them, scaled as the table would scale it, in the chosen strategy's section alone."""
    cfg = make_config("demo", strategy=strategy, compact=True, eval_every=300, log_every=7)
    names = [n for n in steps_options(TrainConfig, "schedule") if resolve(cfg, n) is not None]
    assert list(Schedule.of(cfg).record()) == names
    assert Schedule.of(cfg).record() == {n: value(cfg, n) for n in names}
    for k in (2, 3):
        world = cfg.for_world(k)
        for n in steps_options(TrainConfig):
            if resolve(cfg, n) is None:
                continue
            v = value(cfg, n)
            assert value(world, n) == (round(v / k) if n == "refine_stop" else max(1, round(v / k)) if v > 0 else v), n
        other = "mcmc" if strategy == "default" else "default"
        assert getattr(world, other) == getattr(cfg, other)  # the strategy not chosen is left as it is
    # a template stored by a run of the other strategy sets what the chosen one has
    stored = Schedule.of(make_config("fast", strategy="default" if strategy == "mcmc" else "mcmc", max_gaussians=9))
    planned = stored.scaled(0.5).applied(cfg)
    assert planned.refine.refine_stop == 2000 and planned.iterations == 3500
    assert planned.default.opacity_reset == cfg.default.opacity_reset  # not in the template, or not this strategy's


def test_presets_are_typed_and_leave_out_what_the_strategy_lacks():
    for name, preset in PRESETS.items():
        for strategy in ("default", "mcmc"):
            check(preset(TrainConfig(preset=name, strategy=strategy)))
    assert preset_config("fast", "mcmc").default == TrainConfig().default  # the opacity reset is the default strategy's
    assert preset_config("fast", "mcmc").mcmc.refine_stop == 4000 == preset_config("fast").default.refine_stop
    assert preset_options()["demo"]["max_gaussians"] == 20_000 and "coarse_until" not in preset_options()["fast"]
