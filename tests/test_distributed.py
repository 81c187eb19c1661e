"""Data-parallel training (`train --nproc K`, torch.distributed over gloo on loopback).

The end-to-end tests run the real launcher in a subprocess on the tiny project; the
unit tests run the collectives of distributed.py in two spawned ranks.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
import torch.multiprocessing as mp

from splatcli.cli.train_config import make_config
from splatcli.eval.curve import read_log
from splatcli.files.checkpoint import load_checkpoint
from splatcli.strategy.default import DefaultStrategyState
from splatcli.train import distributed
from splatcli.train.distributed import SHM_DIR, Comm
from splatcli.train.launch import RankDied, _report
from support.tiny_project import make_tiny_project

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
pytestmark = pytest.mark.skipif(sys.platform == "win32" or not torch.distributed.is_available()
                                or not torch.distributed.is_gloo_available(), reason="needs gloo (POSIX)")
# A few hundred views with growth and pruning, in seconds on 2 cores.
FAST = ("--preset", "demo", "--max-gaussians", "1500", "--eval-every", "0", "--device", "cpu")


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "splatcli", *args]


def _run(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(_cli(*args), cwd=REPO, capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})


def _project(tmp_path: Path):
    proj = make_tiny_project(tmp_path / "p", trained=False)
    proj.update_manifest(scene={**proj.manifest()["scene"], "bounds_min": [-1.0] * 3, "bounds_max": [1.0] * 3})
    return proj


def _summary(r: subprocess.CompletedProcess) -> dict:
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_two_processes_train_end_to_end_with_identical_parameters(tmp_path):
    proj = _project(tmp_path)
    s = _summary(_run("train", str(proj.root), *FAST, "--iterations", "600", "--nproc", "2", "--json"))
    # 600 views seen in 300 steps of two views; densification ran (growth and pruning)
    # and at each checkpoint (500, 600) every parameter of rank 1 equalled rank 0's bitwise.
    assert s["steps"] == 600 and s["nproc"] == 2 and s["rank_checks"] == 2
    log = read_log(proj.train_log_path)
    assert [r["step"] for r in log][-1] == 600 and sum(r.get("split", 0) + r.get("cloned", 0) for r in log) > 0
    assert sum(r.get("pruned", 0) for r in log) > 0
    assert 0 < s["comm_seconds"] < s["train_seconds"]
    ck = load_checkpoint(proj.latest_checkpoint())
    assert ck.step == 600 and torch.isfinite(ck.gaussians.means).all()
    assert not list(proj.root.glob("*.json.tmp*")) and not list((proj.root / "checkpoints").glob("*.tmp*"))


@pytest.mark.slow
def test_one_process_through_the_launcher_matches_a_plain_run(tmp_path):
    a, b = _project(tmp_path / "a"), _project(tmp_path / "b")
    fixed = ("--block", "model")  # compared bit for bit: a measured block follows the clock
    _summary(_run("train", str(a.root), *FAST, *fixed, "--iterations", "120", "--json"))
    _summary(_run("train", str(b.root), *FAST, *fixed, "--iterations", "120", "--nproc", "1", "--json"))
    ga, gb = load_checkpoint(a.latest_checkpoint()).gaussians, load_checkpoint(b.latest_checkpoint()).gaussians
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        assert torch.equal(getattr(ga, name), getattr(gb, name)), name


@pytest.mark.slow
def test_resume_with_another_number_of_processes(tmp_path):
    proj = _project(tmp_path)
    _summary(_run("train", str(proj.root), *FAST, "--iterations", "400", "--nproc", "2", "--json"))
    s = _summary(_run("train", str(proj.root), *FAST, "--iterations", "500", "--resume", "--nproc", "1", "--json"))
    assert s["resumed_from"] == 400 and s["steps"] == 500 and s["nproc"] == 1
    s = _summary(_run("train", str(proj.root), *FAST, "--iterations", "600", "--resume", "--nproc", "2", "--json"))
    assert s["resumed_from"] == 500 and s["steps"] == 600 and s["nproc"] == 2
    # without --nproc, a run goes on with as many processes as trained it last
    s = _summary(_run("train", str(proj.root), *FAST, "--iterations", "620", "--resume", "--json"))
    assert s["resumed_from"] == 600 and s["steps"] == 620 and s["nproc"] == 2
    assert {"option": "nproc", "value": 2, "why": "the run's own; --nproc 1 for one"} in s["chosen"]
    steps = [r["step"] for r in read_log(proj.train_log_path)]
    assert steps == sorted(steps) and steps[-1] == 620  # one log, counted in views, in order


def _children(pid: int) -> dict[int, int]:
    """rank -> pid of the launcher's worker processes."""
    out = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            env = (d / "environ").read_bytes().split(b"\0")
        except (OSError, IndexError, ValueError):
            continue
        if ppid == pid:
            rank = next((int(e[5:]) for e in env if e.startswith(b"RANK=")), None)
            if rank is not None:
                out[rank] = int(d.name)
    return out


def _start_long_run(proj) -> subprocess.Popen:
    p = subprocess.Popen(_cli("train", str(proj.root), *FAST, "--iterations", "100000", "--nproc", "2", "--quiet"),
                         cwd=REPO, env={**os.environ, "OMP_NUM_THREADS": "1"}, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 180
    while proj.latest_checkpoint() is None:  # the first checkpoint (500 views)
        assert p.poll() is None, p.communicate()
        assert time.monotonic() < deadline, "no checkpoint within 180 s"
        time.sleep(0.2)
    return p


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/environ").exists(), reason="finds the ranks through /proc")
def test_a_killed_rank_ends_the_run_in_one_line_and_the_checkpoint_stays_whole(tmp_path):
    proj = _project(tmp_path)
    p = _start_long_run(proj)
    try:
        ranks = _children(p.pid)
        assert set(ranks) == {0, 1}, ranks
        os.kill(ranks[1], signal.SIGKILL)
        out, err = p.communicate(timeout=90)  # never hangs
    finally:
        if p.poll() is None:
            p.kill()
    lines = err.strip().splitlines()
    assert p.returncode == 1 and len(lines) == 1, err
    assert "rank 1 was killed by SIGKILL" in lines[0] and "the last checkpoint is" in lines[0], err
    last = proj.latest_checkpoint()
    assert str(last) in lines[0] or last.name in lines[0]
    assert load_checkpoint(last).step % 500 == 0  # whole, and loadable
    assert not _children(p.pid)


def test_the_rank_that_died_is_named_not_the_ones_the_launcher_stopped(tmp_path):
    """Once a rank dies the launcher sends SIGTERM to the others: the report names the
    first cause (a rank that aborted at exit, in a CI run), not rank 0's SIGTERM."""
    (tmp_path / "errors").mkdir()
    root = _project(tmp_path).root
    err = _report(tmp_path / "errors", {0: -signal.SIGTERM, 1: -signal.SIGABRT}, root)
    assert isinstance(err, RankDied) and "rank 1 was killed by SIGABRT" in str(err), err
    err = _report(tmp_path / "errors", {0: -signal.SIGTERM, 1: -signal.SIGTERM}, root)
    assert "rank 0 was killed by SIGTERM" in str(err)  # stopped from outside: the lowest rank
    # Rank 0 wrote its user error and exited 2; rank 1 was stopped before it wrote its own (a CI run
    # under load): rank 0's error is the report, not rank 1's SIGTERM.
    (tmp_path / "errors" / "rank0.json").write_text(json.dumps({"exit_code": 2, "error": "nowhere.ply: no such file"}))
    err = _report(tmp_path / "errors", {0: 2, 1: -signal.SIGTERM}, root)
    assert not isinstance(err, RankDied) and str(err) == "nowhere.ply: no such file" and err.exit_code == 2, err


@pytest.mark.slow
def test_sigterm_to_the_launcher_checkpoints_once_and_exits_130(tmp_path):
    proj = _project(tmp_path)
    p = _start_long_run(proj)
    try:
        p.send_signal(signal.SIGTERM)
        out, err = p.communicate(timeout=90)
    finally:
        if p.poll() is None:
            p.kill()
    lines = err.strip().splitlines()
    assert p.returncode == 130 and len(lines) == 1 and "interrupted at step" in lines[0], err
    ck = load_checkpoint(proj.latest_checkpoint())
    assert f"step {ck.step};" in lines[0] and ck.step % 2 == 0  # the agreed step, in views seen
    s = _summary(_run("train", str(proj.root), *FAST, "--iterations", str(ck.step + 20), "--resume", "--json"))
    assert s["resumed_from"] == ck.step


def test_a_sigterm_once_pycolmap_is_imported_ends_the_process_without_a_word():
    """The launcher stops the other workers with SIGTERM when one reports a one-line error; one that
    has imported pycolmap must end as quietly as before it did (pycolmap's glog handler printed a
    30-line stack trace)."""
    code = ("import os, signal, time\n"
            "from splatcli.sfm import colmap\n"
            "colmap.load()\n"
            "os.kill(os.getpid(), signal.SIGTERM)\n"
            "time.sleep(60)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == -signal.SIGTERM and r.stderr == "", r.stderr


@pytest.mark.slow
def test_a_port_in_use_and_a_bad_option_are_one_line_errors(tmp_path):
    proj = _project(tmp_path)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        r = _run("train", str(proj.root), *FAST, "--iterations", "10", "--nproc", "2", "--port", str(port))
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and f"--port {port}" in r.stderr, r.stderr
    # A user error inside the workers (every rank raises it) is reported once.
    r = _run("train", str(proj.root), *FAST, "--iterations", "10", "--nproc", "2", "--init-ply", "nowhere.ply")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "nowhere.ply" in r.stderr
    r = _run("train", str(proj.root), *FAST, "--nproc", "0")
    assert r.returncode == 2 and "--nproc 0" in r.stderr


def test_a_time_budget_plans_with_every_process_counted(tmp_path):
    """--time-budget with --nproc: the ranks plan from one clock (they agree on every
    plan, so their parameters stay equal) and the run ends near the budget; with --compact, each
    prices the cuts' scoring at the same share of the training views (8 here)."""
    proj = _project(tmp_path)
    s = _summary(_run("train", str(proj.root), *FAST, "--nproc", "2", "--time-budget", "8", "--checkpoint-every", "50",
                      "--compact", "--json"))
    plan = s["plan"]
    assert s["nproc"] == 2 and s["rank_checks"] >= 1 and len(plan["history"]) >= 2 and plan["scored"] == 4
    it = plan["history"][-1]["iterations"] + plan["history"][-1].get("compact_finetune", 0)  # main steps + fine-tune
    assert abs(s["steps"] - it) <= 2  # views seen, as one process counts them (2 a step; an ended fine-tune: the next)
    assert s["train_seconds"] <= 8 * 1.25


def test_the_scaling_rule_sees_as_many_images_and_keeps_one_process_unchanged():
    cfg = make_config("fast")
    assert cfg.for_world(1) is cfg
    c2 = cfg.for_world(2)
    assert c2.iterations * 2 == cfg.iterations and c2.default.refine_every * 2 == cfg.default.refine_every
    assert c2.default.refine_stop * 2 == cfg.default.refine_stop and c2.sh_degree_interval * 2 == cfg.sh_degree_interval
    assert c2.lr_sh0 == pytest.approx(cfg.lr_sh0 * 2 ** 0.5) and c2.adam_eps == pytest.approx(cfg.adam_eps / 2 ** 0.5)
    assert c2.adam_beta2 == pytest.approx(cfg.adam_beta2 ** 2) and c2.coarse_until == cfg.coarse_until
    assert cfg.for_world(3).eval_every == round(cfg.eval_every / 3)
    assert c2.exposure == cfg.exposure  # the transforms step per view trained (appearance.py)


# ---- the collectives, in two spawned ranks --------------------------------------


def _ranks(rank: int, world: int, store: str, out: str) -> None:
    torch.distributed.init_process_group("gloo", init_method=f"file://{store}", rank=rank, world_size=world)
    comm = Comm(rank=rank, world=world)
    results = {}
    # combine: sums and maxima of every rank's rows, the same on every rank
    st = DefaultStrategyState(torch.tensor([1.0, 2.0]) * (rank + 1), torch.ones(2), torch.tensor([0.1 * (rank + 1), 0.5]),
                              torch.Generator())
    comm.combine_rows(st)
    results["combined"] = [st.grad2d.tolist(), st.count.tolist(), st.radii.tolist()]
    # fold: rank 0 keeps the totals, the others none, so a later combine counts once
    st = DefaultStrategyState(torch.tensor([1.0, 2.0]), torch.ones(2), torch.tensor([0.2, 0.1 * rank]), torch.Generator())
    comm.fold_rows([st])
    results["folded"] = [st.grad2d.tolist(), st.count.tolist()]
    st.grad2d += 1.0  # each rank's next view
    comm.combine_rows(st)
    results["refolded"] = st.grad2d.tolist()
    # gradients: averaged, the loss too; the stop flag of one rank stops both
    p = torch.nn.Parameter(torch.zeros(3))
    p.grad = torch.full((3,), float(rank + 1))
    loss, stop = comm.reduce_step({"p": p}, torch.tensor(float(rank)), stop=rank == 1)
    results["grad"], results["loss"], results["stop"] = p.grad.tolist(), float(loss), stop
    # the same through shared memory (ranks on one machine), as the model grows: the same bits as gloo's
    shm = Comm(rank=rank, world=world, shared=True)
    gen = torch.Generator().manual_seed(rank)
    results["shared"] = []
    for n in (3, 3, 700, 5, 700, 2000):
        p = torch.nn.Parameter(torch.zeros(n))
        g = torch.randn(n, generator=gen) * 10 ** rank
        p.grad, q = g.clone(), torch.nn.Parameter(torch.zeros(n))
        q.grad = g.clone()
        got = shm.reduce_step({"p": p}, torch.tensor(float(rank)), stop=False)
        ref = comm.reduce_step({"p": q}, torch.tensor(float(rank)), stop=False)
        results["shared"].append([torch.equal(p.grad, q.grad), float(got[0]), got[1], float(ref[0]), p.grad[:3].tolist()])
    results["shared_files"] = sorted(f for f in os.listdir(SHM_DIR) if f.startswith(f"splatcli-{shm._slots.tag}-"))
    # no room in shared memory (a container's small /dev/shm): gloo, on every rank alike
    distributed._shm_free = (lambda: 0) if rank == 1 else distributed._shm_free
    full = Comm(rank=rank, world=world, shared=True)
    p, q = torch.nn.Parameter(torch.zeros(4)), torch.nn.Parameter(torch.zeros(4))
    p.grad, q.grad = torch.full((4,), float(rank)), torch.full((4,), float(rank))
    full.reduce_step({"p": p}, torch.tensor(0.0), stop=False)
    comm.reduce_step({"p": q}, torch.tensor(0.0), stop=False)
    results["full"] = [full.shared, torch.equal(p.grad, q.grad), p.grad.tolist()]
    # agreement: equal parameters pass; one flipped bit on one rank fails on every rank
    q = {"p": torch.nn.Parameter(torch.linspace(0, 1, 5))}
    comm.check_agree(q)
    if rank == 1:
        q["p"].data[2] = torch.nextafter(q["p"].data[2], torch.tensor(2.0))
    try:
        comm.check_agree(q)
        results["caught"] = False
    except RuntimeError:
        results["caught"] = True
    Path(out, f"{rank}.json").write_text(json.dumps(results))
    torch.distributed.destroy_process_group()


def test_collectives_merge_rows_average_gradients_and_catch_a_one_bit_difference(tmp_path):
    mp.spawn(_ranks, args=(2, str(tmp_path / "store"), str(tmp_path)), nprocs=2, join=True)
    r = [json.loads((tmp_path / f"{i}.json").read_text()) for i in range(2)]
    for x in r:
        assert x["combined"] == [[3.0, 6.0], [2.0, 2.0], [pytest.approx(0.2), 0.5]]
        assert x["grad"] == [1.5] * 3 and x["loss"] == 0.5 and x["stop"] is True and x["caught"] is True
        assert x["refolded"] == [4.0, 6.0]  # the folded totals once, plus each rank's new view
    assert r[0]["folded"] == [[2.0, 4.0], [2.0, 2.0]] and r[1]["folded"] == [[0.0, 0.0], [0.0, 0.0]]
    assert r[0]["shared"] == r[1]["shared"] and len(r[0]["shared"]) == 6  # every rank the same gradients
    assert all(same and loss == 0.5 == ref and not stop for same, loss, stop, ref, _ in r[0]["shared"])
    assert r[0]["shared_files"] == r[1]["shared_files"] == []  # unlinked once mapped
    assert r[0]["full"] == r[1]["full"] == [False, True, [0.5] * 4]
