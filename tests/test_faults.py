"""Faults from outside: a real `splatcli train` process receives SIGINT or SIGTERM.

It must exit 130 with a one-line message, leave a consistent checkpoint of a
whole step (and the log up to it), and `--resume` must continue from exactly
that step.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest
import torch

from splatcli.files.checkpoint import load_checkpoint
from splatcli.project import Project
from splatcli.train.log import read_log
from support.tiny_project import make_tiny_project

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _project(tmp_path) -> Project:
    proj = make_tiny_project(tmp_path / "p", trained=False)
    proj.update_manifest(scene={**proj.manifest()["scene"], "bounds_min": [-1.0] * 3, "bounds_max": [1.0] * 3})
    return proj


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "splatcli.cli.main", *args]


TRAIN_ARGS = ["--iterations", "100000", "--max-gaussians", "150", "--eval-every", "0", "--device", "cpu", "--quiet"]
ENV = {**os.environ, "OMP_NUM_THREADS": "1"}


def _interrupt_after_first_log(proj, sig) -> str:
    """Start a long training run, send `sig` once a step is logged; its stderr."""
    proc = subprocess.Popen(_cli("train", str(proj.root), *TRAIN_ARGS), cwd=REPO, env=ENV,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not (proj.train_log_path.exists() and read_log(proj.train_log_path)):  # step 100 is done
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "no training progress within 120 s"
            time.sleep(0.05)
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    return err


def _resume(proj, iterations: int) -> dict:
    r = subprocess.run(_cli("train", str(proj.root), "--resume", "--iterations", str(iterations), "--json", "--quiet"),
                       cwd=REPO, env=ENV, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_signal_checkpoints_exits_130_and_resumes(tmp_path, sig):
    proj = _project(tmp_path)
    err = _interrupt_after_first_log(proj, sig)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: interrupted at step "), err
    step = int(lines[0].split("interrupted at step ")[1].split(";")[0])
    ck_path = proj.latest_checkpoint()
    assert ck_path == proj.checkpoint_path(step)
    ck = load_checkpoint(ck_path, torch.device("cpu"))
    assert ck.step == step >= 100 and bool(ck.gaussians.finite_mask().all())
    assert not list(proj.checkpoints_dir.glob(".*.tmp"))  # no torn temp file left behind
    assert max(r["step"] for r in read_log(proj.train_log_path)) <= step
    summary = _resume(proj, step + 3)
    assert summary["resumed_from"] == step and summary["steps"] == step + 3


@pytest.mark.slow
@pytest.mark.parametrize("delay", [0.0, 0.7, 1.9], ids=["at-once", "early", "later"])
def test_kill_9_leaves_previous_checkpoint_and_manifest_intact(tmp_path, delay):
    """SIGKILL cannot be caught: only atomic writes protect the files. After a first
    run is interrupted cleanly, a resumed run is killed -9 at some moment (seeded
    delays: at once, while loading, while stepping/writing); the old checkpoint and
    the manifest must still load, and a further --resume must work."""
    proj = _project(tmp_path)
    _interrupt_after_first_log(proj, signal.SIGINT)
    first = proj.latest_checkpoint()
    assert first is not None

    proc = subprocess.Popen(_cli("train", str(proj.root), "--resume", *TRAIN_ARGS), cwd=REPO, env=ENV,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(delay)
    proc.send_signal(signal.SIGKILL)
    proc.communicate(timeout=60)
    assert proc.returncode == -signal.SIGKILL

    json.loads(proj.manifest_path.read_text())  # parses: never half-written
    Project.open(proj.root).require_trained()
    ck = load_checkpoint(first, torch.device("cpu"))  # the previous checkpoint is whole
    assert bool(ck.gaussians.finite_mask().all())
    latest = load_checkpoint(proj.latest_checkpoint(), torch.device("cpu"))  # so is any newer one
    assert latest.step >= ck.step
    assert _resume(proj, latest.step + 2)["resumed_from"] == latest.step


def test_disk_full_during_export_is_one_line_and_keeps_the_old_file(tmp_path, monkeypatch):
    """A write error (ENOSPC) while publishing a file: exit 2, one line that says so,
    the previous export byte-for-byte as it was and no temp debris."""
    import errno

    from typer.testing import CliRunner

    from splatcli.cli.main import app

    proj = make_tiny_project(tmp_path / "p")
    r = CliRunner().invoke(app, ["export", str(proj.root), "--quiet"])
    assert r.exit_code == 0, r.stderr
    before = proj.export_path().read_bytes()

    def full(src, dst):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "replace", full)
    r = CliRunner().invoke(app, ["export", str(proj.root), "--quiet"])
    assert r.exit_code == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "No space left on device" in lines[0]
    assert "scene.ply" in lines[0]
    assert proj.export_path().read_bytes() == before
    assert not [p for p in proj.exports_dir.iterdir() if p.name.endswith(".tmp")]
