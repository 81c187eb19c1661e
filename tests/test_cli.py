"""The CLI's shell: help, version, exit codes and the one-line error policy."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from splatcli import __version__
from splatcli.cli.main import app

COMMANDS = ["process", "train", "render", "export", "eval"]


@pytest.fixture
def runner() -> CliRunner:
    return CliRunner()


def test_version(runner):
    r = runner.invoke(app, ["--version"])
    assert r.exit_code == 0
    assert __version__ in r.stdout


def test_top_level_help_lists_every_command(runner):
    r = runner.invoke(app, ["--help"])
    assert r.exit_code == 0
    for c in COMMANDS:
        assert c in r.stdout


@pytest.mark.parametrize("cmd", COMMANDS)
def test_each_command_has_explaining_help(runner, cmd):
    r = runner.invoke(app, [cmd, "--help"])
    assert r.exit_code == 0, r.output
    text = " ".join(r.stdout.split())
    assert "Usage" in text
    assert "--json" in text  # every command, export included, can print one JSON summary
    assert len(text) > 300  # more than a bare usage line: it explains


def _assert_one_line_usage_error(r) -> None:
    assert r.exit_code == 2, r.output
    assert r.stderr.startswith("error: ")
    assert len(r.stderr.strip().splitlines()) == 1


def _make_open_raise(monkeypatch, exc: BaseException) -> None:
    import splatcli.project as project

    def fail(cls, root):
        raise exc

    monkeypatch.setattr(project.Project, "open", classmethod(fail))


def test_unknown_command_is_usage_error(runner):
    r = runner.invoke(app, ["frobnicate"])
    _assert_one_line_usage_error(r)
    assert "Traceback" not in r.output


@pytest.mark.parametrize("cmd", COMMANDS)
def test_unknown_option_is_one_line_usage_error(runner, cmd):
    _assert_one_line_usage_error(runner.invoke(app, [cmd, "--no-such-option"]))


@pytest.mark.parametrize("cmd", ["train", "render", "eval", "export"])
def test_not_a_project_exits_2_with_one_line(runner, cmd, tmp_path):
    r = runner.invoke(app, [cmd, str(tmp_path / "nowhere")])
    _assert_one_line_usage_error(r)
    assert "splatcli process" in r.stderr
    assert "Traceback" not in r.output


def test_internal_error_exits_1_without_traceback(monkeypatch, runner, tmp_path):
    _make_open_raise(monkeypatch, RuntimeError("kaboom"))
    r = runner.invoke(app, ["train", str(tmp_path)])
    assert r.exit_code == 1
    assert "internal error" in r.stderr and "kaboom" in r.stderr
    assert "Traceback" not in r.stderr
    r = runner.invoke(app, ["train", str(tmp_path), "--debug"])
    assert r.exit_code == 1
    assert "Traceback" in r.stderr


def test_keyboard_interrupt_exits_130(monkeypatch, runner, tmp_path):
    _make_open_raise(monkeypatch, KeyboardInterrupt())
    r = runner.invoke(app, ["train", str(tmp_path)])
    assert r.exit_code == 130


def test_device_cuda_without_gpu_is_one_line_error():
    import torch

    from splatcli.device import resolve_device
    from splatcli.errors import SplatError

    assert resolve_device("cpu").type == "cpu"
    with pytest.raises(SplatError, match="allowed values: auto, cpu, cuda"):
        resolve_device("tpu")
    if not torch.cuda.is_available():
        with pytest.raises(SplatError, match="no CUDA GPU"):
            resolve_device("cuda")


def test_the_cpu_name_tells_generations_apart_where_the_model_name_does_not(tmp_path):
    """Timings are recorded with the CPU's name: a virtual machine's bare "AMD EPYC" gets the family
    and model numbers (a Zen 3 and a Zen 4 rank the same code differently), a named model does not."""
    from splatcli.device import cpu_name

    def name(model: str, flags: str, family: str = "25", number: str = "1") -> str:
        p = tmp_path / f"cpuinfo-{len(list(tmp_path.iterdir()))}"
        block = f"processor\t: {{i}}\ncpu family\t: {family}\nmodel\t\t: {number}\nmodel name\t: {model}\nflags\t\t: {flags}\n\n"
        p.write_text(block.format(i=0) + block.format(i=1).replace(model, "other"))
        return cpu_name(str(p))

    assert name("AMD EPYC", "sse2 avx avx2 fma") == "AMD EPYC (family 25 model 1; avx2, fma)"
    assert name("AMD EPYC", "avx2 fma avx512f avx512_bf16", number="17") == "AMD EPYC (family 25 model 17; avx512f, avx512_bf16)"
    assert name("AMD EPYC 7B13 64-Core Processor", "avx2 fma") == "AMD EPYC 7B13 64-Core Processor (avx2, fma)"
    assert cpu_name(str(tmp_path / "absent")) != ""  # no /proc/cpuinfo: the platform's word for it


def test_json_is_one_object_on_stdout(capsys):
    from splatcli.cli.common import Ui

    Ui(json_out=True).summary({"a": 1, "b": [1.5]})
    out = capsys.readouterr().out
    assert json.loads(out) == {"a": 1, "b": [1.5]}
    assert out.count("\n") == 1


def test_a_stage_without_a_count_shows_no_count(capsys):
    """`eval`'s "rank Gaussians" has no units to count: its bar said 0/0."""
    from splatcli.cli.common import Ui
    from splatcli.events import Progress, Stage, StageDone

    with Ui().progress() as sink:
        sink(Stage("rank", total=None))
        sink(StageDone("rank", 0.1))
        sink(Stage("eval", total=4))
        sink(Progress("eval", 4, 4))
        sink(StageDone("eval", 0.1))
    err = capsys.readouterr().err
    rank = next(line for line in err.splitlines() if "rank" in line)
    assert "/" not in rank, rank  # no count at all (it said 0/0)
    assert "4/4" in next(line for line in err.splitlines() if "eval" in line)


def _json_error(r) -> dict:
    lines = r.stdout.strip().splitlines()
    assert len(lines) == 1, r.stdout  # one object, nothing else on stdout
    return json.loads(lines[0])


def test_json_failures_are_one_object_with_code_and_hint(monkeypatch, runner, tmp_path):
    # bad input: exit 2, the same line as stderr, and the hint alone
    r = runner.invoke(app, ["train", str(tmp_path / "nowhere"), "--json"])
    assert r.exit_code == 2
    d = _json_error(r)
    assert set(d) == {"error", "exit_code", "hint"} and d["exit_code"] == 2
    assert r.stderr.strip() == f"error: {d['error']}"
    # a missing earlier step names the command to run
    from support.tiny_project import make_tiny_project

    proj = make_tiny_project(tmp_path / "p", trained=False, photos=False)
    r = runner.invoke(app, ["export", str(proj.root), "--json"])
    assert r.exit_code == 2 and _json_error(r)["hint"] == "run `splatcli train` first"
    # usage errors too
    r = runner.invoke(app, ["eval", str(proj.root), "--json", "--no-such-option"])
    assert r.exit_code == 2 and _json_error(r)["exit_code"] == 2
    # a crash is 1, never 2: scripts tell them apart by the code
    _make_open_raise(monkeypatch, RuntimeError("x"))
    r = runner.invoke(app, ["train", str(tmp_path), "--json"])
    assert r.exit_code == 1
    d = _json_error(r)
    assert d["exit_code"] == 1 and "--debug" in d["hint"]
    # without --json, stdout stays empty on failure
    r = runner.invoke(app, ["train", str(tmp_path)])
    assert r.stdout == ""


def test_off_a_terminal_a_long_stage_prints_a_line_now_and_then_with_its_eta(capsys, monkeypatch):
    """CI and Make logs: the bars are drawn once at the end, so a long stage prints a plain line every
    LOG_PERIOD_S (with count, elapsed time and ETA), and a quick one none."""
    from splatcli.cli import common
    from splatcli.events import Progress, Stage, StageDone

    now = [1000.0]
    monkeypatch.setattr(common.time, "monotonic", lambda: now[0])
    with common.Ui().progress() as sink:
        sink(Stage("quick", total=3))
        sink(Progress("quick", 3, 3))
        sink(StageDone("quick", 0.1))
        sink(Stage("train", total=1000))
        for step in range(1, 1001):
            now[0] += 0.1  # 100 s in all: about ten lines
            sink(Progress("train", step, 1000, {"loss": 0.5}))
        sink(StageDone("train", 100.0))
    err = capsys.readouterr().err.splitlines()
    logged = [line for line in err if line.startswith("train: ")]
    assert 8 <= len(logged) <= 10, err
    assert logged[0] == "train: 100/1,000 (10%), 0:10 elapsed, ETA 1:30  loss 0.5", logged[0]
    assert not any(line.startswith("quick: ") for line in err)


def _train_log_lines(capsys, monkeypatch, steps: int, progress) -> list[str]:
    """The `train: ` log lines of a 1,000-step stage whose step i (0.1 s each) sends progress(i, now)."""
    from splatcli.cli import common
    from splatcli.events import Stage, StageDone

    now = [1000.0]
    monkeypatch.setattr(common.time, "monotonic", lambda: now[0])
    with common.Ui().progress() as sink:
        sink(Stage("train", total=1000))
        for step in range(1, steps + 1):
            now[0] += 0.1
            sink(progress(step, now[0]))
        sink(StageDone("train", steps / 10))
    return [line for line in capsys.readouterr().err.splitlines() if line.startswith("train: ")]


def test_a_stage_that_knows_its_time_left_prints_it_rather_than_the_counts_extrapolation(capsys, monkeypatch):
    """Training's steps slow down as the model grows and the resolution rises: its events carry the
    time left (Progress.eta_s: the time plan's), which the log line prints instead of elapsed / done x left."""
    from splatcli.events import Progress

    logged = _train_log_lines(capsys, monkeypatch, 200,
                              lambda step, now: Progress("train", step, 1000, {}, eta_s=600.0 - now + 1000.0))
    assert logged[0] == "train: 100/1,000 (10%), 0:10 elapsed, ETA 9:50", logged  # not 1:30


def test_a_planned_stage_prints_its_clocks_share_and_its_total_as_an_estimate(capsys, monkeypatch):
    """A planned run's step total moves each time it plans again (fox: 4,120, 5,540, 4,480 ...); its
    share of the budget does not. The line gives the total as an estimate and the share of the clock,
    and the bar fills by that share, never backwards."""
    from rich.console import Console

    from splatcli.cli import common
    from splatcli.events import Progress

    total = lambda step: 1000 if step < 150 else 1400  # noqa: E731 (a plan at step 150 finds time for more)
    logged = _train_log_lines(capsys, monkeypatch, 250, lambda step, now: Progress(
        "train", step, total(step), {}, eta_s=200.0 - (now - 1000.0), eta_own=True, share=(now - 1000.0) / 200.0))
    assert logged[0] == "train: 100/~1,000 (5%), 0:10 elapsed, ETA 3:10", logged
    assert logged[1] == "train: 200/~1,400 (10%), 0:20 elapsed, ETA 3:00", logged

    bars = common.RichProgress(common._Bar(), common._Count(), console=Console(file=None, width=80))
    task = bars.add_task("train", total=1000)
    bars.update(task, completed=100, share=0.05)
    assert str(common._Count().render(bars.tasks[0])) == " 100/~1000"
    assert common._Bar().render(bars.tasks[0]).completed == 0.05
    bars.update(task, completed=200, total=1400, share=0.10)  # the total moved; the bar goes on
    assert common._Bar().render(bars.tasks[0]).completed == 0.10
    bars.update(task, completed=300, share=None)  # no share: the count's own fraction, as before
    assert common._Bar().render(bars.tasks[0]).completed == 300
    assert str(common._Count().render(bars.tasks[0])) == " 300/1400"


def test_a_stage_that_gives_its_own_time_left_prints_none_until_it_has_measured_it(capsys, monkeypatch):
    """Training's first step loads kernels and memory; the count's extrapolation would price that into
    every step left (the full preset's first line: hours too many), so a stage that gives its own ETA
    (Progress.eta_own) prints none until it has measured one."""
    from splatcli.events import Progress

    logged = _train_log_lines(capsys, monkeypatch, 300, lambda step, now: Progress(
        "train", step, 1000, {}, eta_s=None if step < 150 else 100.0, eta_own=True))
    assert logged[0] == "train: 100/1,000 (10%), 0:10 elapsed", logged  # not "ETA 1:30"
    assert logged[1] == "train: 200/1,000 (20%), 0:20 elapsed, ETA 1:40", logged
