"""What `train` chooses when it is not told (splatcli/train/planning.py): on a CPU with no
schedule given, a time-budgeted run sized to the capture and the machine; every choice
yields to its option; on CUDA and with a step schedule, nothing is chosen. The choices are
typed, applied to the config's fields; the processes of `train --nproc` are sent the config."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from splatcli import options
from splatcli.camera import SceneData
from splatcli.cli import planning
from splatcli.cli.train_config import make_config
from splatcli.errors import SplatError
from splatcli.project import holdout_split
from splatcli.train.config import TrainConfig
from support.tiny_project import make_tiny_project, run_ok

CPU = torch.device("cpu")


@pytest.fixture
def proj(tmp_path):
    return make_tiny_project(tmp_path / "p", trained=False, photos=False)


def _chosen(c: planning.Chosen) -> dict:
    return {x.option: x.value for x in c.choices}


def _choose(proj, given: dict, nproc=None, device=CPU, resume=False) -> planning.Chosen:
    return planning.choose(proj, options.parse(TrainConfig, given), nproc, device, resume)


def test_a_default_cpu_run_is_planned_into_minutes(proj, monkeypatch):
    monkeypatch.setattr(planning, "free_cores", lambda: 1)
    c = _choose(proj, {})
    got = _chosen(c)
    assert got["preset"] == "fast" and got["time_budget"] == planning.BUDGET_S and got["strategy"] == "mcmc"
    assert got["max_gaussians"] == planning.MIN_GAUSSIANS  # 48x40 px: the smallest budget
    assert "max_size" not in got  # the images are smaller than 480 px already
    assert c.nproc is None and all(x.why for x in c.choices)
    assert (c.preset, c.time_budget, c.strategy, c.max_gaussians) == ("fast", planning.BUDGET_S, "mcmc",
                                                                       planning.MIN_GAUSSIANS)  # typed, as recorded
    cfg = make_config(chosen=c)  # the choices make a valid config
    assert cfg.time_budget == planning.BUDGET_S and cfg.mcmc.max_gaussians == planning.MIN_GAUSSIANS
    line = planning.summary_line(c, cfg.time_budget)
    assert "trains for 10 min" in line and "--time-budget" in line and "max-gaussians 5000 (0.225 per pixel" in line
    assert "--compact" not in line
    assert "then --compact keeps 25% of them (1,250)" in planning.summary_line(c, cfg.time_budget, keep=0.25)
    assert "sooner" not in planning.summary_line(c, 20.0)  # (it offered 30 s for a 20 s run)


def test_every_choice_yields_to_its_option(proj, monkeypatch):
    monkeypatch.setattr(planning, "free_cores", lambda: 1)
    given = {"strategy": "default", "max_size": 300}
    c = _choose(proj, given)
    got = _chosen(c)
    assert "strategy" not in got and "max_gaussians" not in got and "max_size" not in got
    assert c.strategy is None and c.max_size is None and c.preset == "fast"
    cfg = make_config(**given, chosen=c)
    assert cfg.strategy == "default" and cfg.max_size == 300 and cfg.iterations == 7000
    # A step schedule is the user's: nothing is chosen, one process.
    c = _choose(proj, {"iterations": 50})
    assert c.choices == [] and c.nproc is None and c == planning.Chosen()
    # An option of the default strategy keeps it: mcmc is not chosen over what was asked.
    got = _chosen(_choose(proj, {"opacity_reset": 500}))
    assert "strategy" not in got and "max_gaussians" not in got and got["time_budget"] == planning.BUDGET_S
    with pytest.raises(SplatError, match="--max-size 0"):  # what was given is checked first
        _choose(proj, {"max_size": 0})
    # A time budget alone gets the rest of a planned run (the photos are smaller than any size it picks).
    got = _chosen(_choose(proj, {"time_budget": 30.0}))
    assert set(got) == {"preset", "strategy", "max_gaussians"}


def test_the_training_size_follows_the_time_budget(proj, monkeypatch):
    """480 px up to the default budget, then the side grows with the square root of the time
    (the default's step count, on views with proportionally more pixels); the photos' own
    size is never exceeded: a budget whose size is above it picks none."""
    assert planning.train_size(90) == planning.train_size(planning.BUDGET_S) == planning.MAX_SIZE == 480
    assert planning.train_size(4 * planning.BUDGET_S) == 960 and planning.train_size(3 * planning.BUDGET_S) == 830
    big = planning.read_project_scene(proj).cameras
    monkeypatch.setattr(planning, "read_project_scene", lambda p: SceneData([c.scaled(40.0) for c in big], np.zeros((0, 3)),
                                                                        np.zeros((0, 3), np.uint8)))  # 40x: 1920x1600 photos
    monkeypatch.setattr(planning, "free_cores", lambda: 1)
    for budget, size in ((180.0, 480), (2400.0, 960), (None, 480)):
        given = {} if budget is None else {"time_budget": budget}
        got = _chosen(_choose(proj, given))
        assert got["max_size"] == size, (budget, got)


def test_a_capture_of_many_views_and_points_gets_more_time_and_gaussians(proj, monkeypatch):
    """Past VIEWS_AT_BUDGET training views the default run grows with the square root of their
    count (capped), at the default training size; the Gaussian budget leaves room for 2.9 per
    SfM point where that is more than one view's pixels suggest, and the pixels' budget grows with
    the views' worth of surface the capture shows (n views / SfM track length). A given budget is kept."""
    assert planning.default_budget(10) == planning.default_budget(100) == planning.BUDGET_S
    assert planning.default_budget(218) == 890.0 and planning.default_budget(10_000) == planning.MAX_BUDGET_FACTOR * planning.BUDGET_S
    cam = planning.read_project_scene(proj).cameras[0]
    many = [replace(cam.scaled(20.0), name=f"{i:04d}.png") for i in range(250)]  # 960x800 photos
    proj.update_manifest(splits=holdout_split([c.name for c in many]))  # as process records it: 32 held out
    points = np.zeros((34_000, 3))
    monkeypatch.setattr(planning, "read_project_scene", lambda p: SceneData(many, points, np.zeros((34_000, 3), np.uint8)))
    monkeypatch.setattr(planning, "free_cores", lambda: 1)
    c = _choose(proj, {})
    got = _chosen(c)
    assert got["time_budget"] == planning.default_budget(218) > planning.BUDGET_S  # 250 views, every 8th held out
    assert got["max_size"] == planning.MAX_SIZE  # the time goes to seeing the views, not to a larger size
    assert got["max_gaussians"] == 99_000 and "SfM point" in next(x.why for x in c.choices if x.option == "max_gaussians")
    assert "218 training views" in next(x.why for x in c.choices if x.option == "time_budget")
    assert "time_budget" not in _chosen(_choose(proj, {"time_budget": 300.0}))
    assert _chosen(_choose(proj, {"max_gaussians": 7_000})).get("max_gaussians") is None
    for t, grown in ((250 / 13.5, 99_000), (250 / 27, 173_000), (1.0, 173_000)):  # x 2.25: under 2.9 per point; x 4
        monkeypatch.setattr(planning, "read_project_scene", lambda p, t=t: SceneData(many, points, 0 * points, t))
        got = [(x.value, f"seen by {t:.1f} of 250 views" in x.why) for x in _choose(proj, {}).choices]
        assert (grown, grown > 99_000) in got, got


def test_sfm_tracks_choose_the_depth_term(proj, monkeypatch):
    """Where structure from motion left tracks in photographs, a planned run (no options, or a time
    budget) holds their surfaces at their points' depth; a step schedule, the option given, or a
    rendered scene (alpha masks) does not."""
    monkeypatch.setattr(planning, "free_cores", lambda: 1)
    scene = planning.read_project_scene(proj)
    assert "depth_weight" not in _chosen(_choose(proj, {}))  # no tracks in the tiny project
    seen = {c.name: np.arange(3) for c in scene.cameras}
    monkeypatch.setattr(planning, "read_project_scene", lambda p: replace(scene, observed=seen))
    for given in ({}, {"time_budget": 30.0}):
        c = _choose(proj, given)
        assert _chosen(c)["depth_weight"] == planning.DEPTH_WEIGHT > 0
        assert make_config(**given, chosen=c).depth_weight == planning.DEPTH_WEIGHT
    c = _choose(proj, {"depth_weight": 0.0})
    assert "depth_weight" not in _chosen(c) and make_config(depth_weight=0.0, chosen=c).depth_weight == 0.0
    assert _choose(proj, {"iterations": 50}).choices == [] and TrainConfig().depth_weight == 0.0
    monkeypatch.setattr(type(proj), "mask_source", lambda self: "alpha")  # a rendered scene: its pixels suffice
    assert "depth_weight" not in _chosen(_choose(proj, {}))


def test_a_capture_seen_all_round_grows_then_keeps_what_it_needs(proj, monkeypatch):
    """The model kept is a view's pixels' or the SfM points' worth; a capture that shows k views'
    worth of surface grows to k^2 times the pixels' (at most MAX_GROWTH) first, and where that is at
    least COMPACT_FROM times the model kept and the run has the default budget or more, --compact
    keeps that share (fox: k = 1, trained at its size; lego: k = 2.1, 207,000 grown, 25% kept).
    --compact, --compact-keep or --max-gaussians given, or a shorter budget: no compaction chosen,
    and a shorter budget keeps 2k times the pixels' count."""
    cam = planning.read_project_scene(proj).cameras[0]
    views = [replace(cam.scaled(10.0), name=f"{i:04d}.png") for i in range(100)]  # 480x400 photos
    points = np.zeros((5_000, 3))

    def scene(t: float) -> None:
        monkeypatch.setattr(planning, "read_project_scene", lambda p: SceneData(views, points, 0 * points, t))

    monkeypatch.setattr(planning, "free_cores", lambda: 1)
    scene(100 / 9 / 2.1)  # lego's coverage
    c = _choose(proj, {})
    got = _chosen(c)
    assert got["max_gaussians"] == 173_000 and got["compact_keep"] == round(43_000 / 173_000, 6)
    cfg = make_config(chosen=c)
    assert cfg.compact.enabled and cfg.compact.keep == got["compact_keep"] and cfg.mcmc.max_gaussians == 173_000
    line = planning.chosen_line(c, cfg, False)
    assert "then --compact keeps 25% of them (43,000)" in line and "compact-keep" not in line
    for given in ({"compact": False}, {"compact": True}, {"max_gaussians": 50_000}, {"time_budget": 300.0}):
        got = _chosen(_choose(proj, given))
        assert "compact_keep" not in got, given
    assert make_config(compact=True, chosen=_choose(proj, {"compact": True})).compact.keep == 1 / 3  # the option's own
    # A shorter run has no time to cut: it keeps 2k times the pixels' count (lego's 90 s and fox's 300 s trained best so),
    # which its plan may raise to 2 min(MAX_GROWTH, k^2) times it where the CPU trains the steps for more (said, and sent
    # in the config); not where the count was given, nor for a run of the default budget.
    c = _choose(proj, {"time_budget": 300.0})
    assert _chosen(c)["max_gaussians"] == round(2 * 2.1 * 43_200, -3) and c.time_budget_gaussians == round(2 * 4 * 43_200, -3)
    assert make_config(time_budget=300.0, chosen=c).time_budget_gaussians == 346_000
    assert "up to 346,000 where this CPU trains the steps for more" in planning.chosen_line(c, make_config(chosen=c), False)
    assert _choose(proj, {"time_budget": 300.0, "max_gaussians": 50_000}).time_budget_gaussians is None
    assert _choose(proj, {}).time_budget_gaussians is None
    scene(100 / 9)  # fox's: one view's worth
    got = _chosen(_choose(proj, {}))
    assert got["max_gaussians"] == 43_000 and "compact_keep" not in got
    c = _choose(proj, {"time_budget": 300.0})
    assert _chosen(c)["max_gaussians"] == 86_000 and c.time_budget_gaussians is None  # (nothing more to grow into)


def test_cuda_and_resume_choose_nothing(proj):
    assert _choose(proj, {}, device=torch.device("cuda")).choices == []  # the paper's schedule
    assert _choose(proj, {}, resume=True).choices == []  # the stored run's settings


def test_free_cores_become_processes_sent_the_config(proj, monkeypatch):
    monkeypatch.setattr(planning, "free_cores", lambda: 4)
    c = _choose(proj, {})
    assert c.nproc == 1 or c.nproc is None  # 10 views: one process per 8 views at most
    monkeypatch.setattr(planning, "MAX_PROCESSES", 8)
    c = _choose(proj, {}, 3)
    assert c.nproc == 3 and "nproc" not in _chosen(c)  # --nproc given
    monkeypatch.delenv(planning.CHOSEN_ENV, raising=False)
    monkeypatch.delenv(planning.CONFIG_ENV, raising=False)
    back, cfg = planning.inherited()  # under a plain torchrun: nothing sent, each process builds its own
    assert back.choices == [] and back.nproc is None and cfg is None
    sent = make_config(chosen=c, device="cpu")
    env = c.env(sent)
    assert "nproc" not in env[planning.CONFIG_ENV] and "OMP_NUM_THREADS" not in env
    for k in (planning.CHOSEN_ENV, planning.CONFIG_ENV):
        monkeypatch.setenv(k, env[k])
    back, cfg = planning.inherited()  # a launched process: the launcher's record, and the config it trains
    assert [x.option for x in back.choices] == [x.option for x in c.choices] and back.record() == c.record()
    assert cfg == sent and cfg.mcmc.max_gaussians == c.max_gaussians and cfg.preset == "fast"
    monkeypatch.setenv(planning.CONFIG_ENV, json.dumps({**sent.to_dict(), "iterations": 0}))
    with pytest.raises(SplatError, match="SPLATCLI_CONFIG: --iterations 0"):
        planning.inherited()


def test_cores_left_over_become_threads_of_the_processes(proj, monkeypatch):
    """50 views make at most 6 processes; the cores left over give each a second torch
    thread (measured on 16 cores: 27% more steps), never more than MAX_THREADS, and never
    over an OMP_NUM_THREADS the user gave (torch already runs more than one thread)."""
    cams = planning.read_project_scene(proj).cameras
    monkeypatch.setattr(planning, "read_project_scene",
                        lambda p: SceneData(cams * 5, np.zeros((0, 3)), np.zeros((0, 3), np.uint8)))
    monkeypatch.setattr(planning.torch, "get_num_threads", lambda: 1)
    for free, k, threads in ((2, 2, None), (4, 4, None), (11, 6, None), (12, 6, 2), (16, 6, 2), (64, 6, 2)):
        monkeypatch.setattr(planning, "free_cores", lambda free=free: free)
        c = _choose(proj, {})
        assert c.nproc == k and _chosen(c).get("threads") == threads == c.threads, (free, _chosen(c))
        env = c.env(make_config(chosen=c))
        assert env.get("OMP_NUM_THREADS") == (threads and str(threads))  # what the processes inherit
        assert "thread" not in env[planning.CONFIG_ENV]  # not a train option
    assert "threads 2" in planning.summary_line(c, 600.0)
    assert "threads" not in _chosen(_choose(proj, {}, 3))  # --nproc given: its processes as asked
    monkeypatch.setattr(planning.torch, "get_num_threads", lambda: 3)  # OMP_NUM_THREADS=3 given
    assert "threads" not in _chosen(_choose(proj, {}))
    # Busy cores leave one process, and the line says so (a run that takes twice as long, explained)
    monkeypatch.setattr(planning, "free_cores", lambda: 1)
    monkeypatch.setattr(planning, "usable_cores", lambda: 4)
    c = _choose(proj, {})
    assert c.nproc is None and _chosen(c)["nproc"] == 1
    assert "nproc 1 (3 of 4 cores busy: one training process; --nproc 4 to use more)" in planning.summary_line(c, 600.0)
    monkeypatch.setattr(planning, "usable_cores", lambda: 1)  # a one-core machine: nothing to say
    assert "nproc" not in _chosen(_choose(proj, {}))


def test_free_cores_leave_busy_cores_alone(monkeypatch):
    assert 0 <= planning._busy_cores(0.05) <= planning.usable_cores()  # this machine's, a count of its CPUs
    monkeypatch.setattr(planning.os, "sched_getaffinity", lambda pid: {0, 1, 2, 3})
    monkeypatch.setattr(planning.time, "sleep", lambda s: None)
    for busy, free in ((2.6, 1), (4.0, 1), (0.08, 4), (2.0, 2)):  # never fewer than one
        monkeypatch.setattr(planning, "_busy_cores", lambda w, busy=busy: busy)
        assert planning.free_cores() == free, busy
    monkeypatch.setattr(planning, "_busy_cores", lambda w: None)  # no /proc/stat: the load average
    monkeypatch.setattr(planning.os, "getloadavg", lambda: (2.6, 0.0, 0.0))
    assert planning.free_cores() == 1


def _stat(path, busy_cpus, ticks, per_cpu=True):
    """A /proc/stat of 4 CPUs after `ticks` ticks each, `busy_cpus` busy all the while."""
    rows = {c: (ticks, 0, 0, 0, 0) if c in busy_cpus else (0, 0, 0, ticks, 0) for c in range(4)}
    total = [sum(r[i] for r in rows.values()) for i in range(5)]
    lines = ["cpu  " + " ".join(map(str, total)) + " 0 0 0 0 0"]
    lines += [f"cpu{c} " + " ".join(map(str, r)) + " 0 0 0 0 0" for c, r in rows.items()] if per_cpu else []
    path.write_text("\n".join(lines + ["intr 1 2 3", "ctxt 4"]) + "\n")


def test_busy_cpus_outside_the_affinity_mask_leave_its_cores_free(monkeypatch, tmp_path):
    stat = tmp_path / "stat"
    monkeypatch.setattr(planning, "PROC_STAT", str(stat))
    monkeypatch.setattr(planning.os, "cpu_count", lambda: 4)
    for mask, per_cpu, free in (({0, 1}, True, 2),  # CPUs 2 and 3 busy with another job: ours are idle
                                ({2, 3}, True, 1),  # ours are the busy ones
                                ({0, 2}, True, 1),
                                ({0, 1}, False, 1)):  # no per-CPU lines: the machine's share (2 of 4 busy)
        monkeypatch.setattr(planning.os, "sched_getaffinity", lambda pid, mask=mask: mask)
        _stat(stat, {2, 3}, 100, per_cpu)
        monkeypatch.setattr(planning.time, "sleep", lambda s, per_cpu=per_cpu: _stat(stat, {2, 3}, 200, per_cpu))
        assert planning.free_cores(settle_s=0) == free, (mask, per_cpu)


def test_a_burst_of_load_at_the_start_does_not_take_a_process(monkeypatch):
    monkeypatch.setattr(planning.os, "sched_getaffinity", lambda pid: {0, 1})
    slept = []
    monkeypatch.setattr(planning.time, "sleep", slept.append)
    for counts, free, waits in (([1.0, 0.06], 2, 1),  # one core busy for a moment: both are free
                                ([1.0, 1.0], 1, 1),  # busy in both windows: it stays busy
                                ([0.06], 2, 0)):  # all idle: no second window
        seq, slept[:] = iter(counts), []
        monkeypatch.setattr(planning, "_busy_cores", lambda w, seq=seq: next(seq))
        assert planning.free_cores() == free, counts
        assert len(slept) == waits, counts  # the gap before a second window (the mocked windows do not sleep)


def test_train_with_no_options_says_what_it_chose_and_records_it(proj, monkeypatch):
    monkeypatch.setattr(planning, "free_cores", lambda: 1)
    monkeypatch.setattr(planning, "BUDGET_S", 4.0)
    r = run_ok("train", proj.root, "--json")
    assert "trains for 4 s" in r.stderr and "strategy mcmc" in r.stderr
    s = json.loads(r.stdout.strip().splitlines()[-1])
    assert [c["option"] for c in s["chosen"]] == ["preset", "time_budget", "appearance", "strategy",
                                                  "max_gaussians"]
    assert s["plan"]["budget_s"] == 4.0 and s["train_seconds"] <= 4.0 * 1.5
    assert s["protocol"] == "compensated"  # photos, each one's light learnt: held out as eval's headline scores them
    stored = json.loads((proj.root / "splatcli.json").read_text())["steps"]["train"]["config"]
    assert stored["strategy"] == "mcmc" and stored["time_budget"] == 4.0

