"""Train options are declared once, at the config's fields (splatcli/options.py): the
command line, make_config, stored configs and the schedule scalers all read that table."""

from __future__ import annotations

import json
from dataclasses import fields
from pathlib import Path

import pytest
from typer.testing import CliRunner

from splatcli.cli.main import app
from splatcli.errors import SplatError
from splatcli.options import GROUPS, table
from splatcli.train.config import PRESETS, TrainConfig, make_config
from splatcli.train.state import make_strategies

REPO = Path(__file__).resolve().parents[1]
STORED = json.loads((REPO / "tests" / "data" / "train_config_dced6d2.json").read_text())


def test_every_command_line_option_comes_from_a_config_field():
    """`train --help` lists each option of the table that has a heading, under it, and
    cli/train_cmd.py declares none of them itself."""
    r = CliRunner().invoke(app, ["train", "--help"], env={"COLUMNS": "200"})
    assert r.exit_code == 0
    on_cli = [alts[0] for alts in table(TrainConfig).values() if alts[0].on_cli]
    assert len(on_cli) >= 20
    for o in on_cli:
        assert o.flag in r.stdout, o.flag
    for group in GROUPS:
        assert group in r.stdout, group
    source = (REPO / "splatcli" / "cli" / "train_cmd.py").read_text()
    assert len(source.splitlines()) <= 60
    for o in on_cli:
        assert f'"{o.flag}"' not in source, o.flag


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
    assert m.value("refine_stop") == 4000 and m.refine is m.mcmc


def test_an_option_of_the_other_strategy_is_a_one_line_error():
    with pytest.raises(SplatError, match="--opacity-reset does not apply to --strategy mcmc") as e:
        make_config(strategy="mcmc", max_gaussians=10, opacity_reset=100)
    assert "\n" not in str(e.value)
    make_config("fast", strategy="mcmc", max_gaussians=10)  # the preset's opacity_reset is left out silently


def test_opacity_reg_with_mcmc_sets_its_own_penalty():
    from splatcli.strategy import MCMCStrategy, RegularizeStep

    strategies = make_strategies(make_config("fast", strategy="mcmc", max_gaussians=100, opacity_reg=0.05), 1.0,
                                 _ctx())
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
    for preset in PRESETS.values():
        assert set(preset) <= set(table(TrainConfig))


def _ctx():
    import torch

    from splatcli.strategy import Context

    return Context(score=lambda *a: None, weights=lambda: torch.zeros(0), note=lambda m: None)
