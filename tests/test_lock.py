"""One writer per project (issue 17): a command that writes a project holds an
exclusive flock on it; a second writer is refused at once with exit 2 and one line
naming the holder; the lock dies with its process (kill -9 leaves nothing stale)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from splatcli.errors import ProjectBusy
from splatcli.formats.export import ExportConfig
from splatcli.model import export_project
from splatcli.project import writer_lock
from splatcli.train.log import read_log
from support.tiny_project import make_tiny_project

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="flock is POSIX")


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "splatcli.cli.main", *args]


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(_cli(*args), cwd=REPO, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})


def test_a_second_writer_is_refused_in_one_line_naming_the_holder(tmp_path):
    proj = make_tiny_project(tmp_path / "p")
    with writer_lock(proj.root, "train"):
        r = _run("export", str(proj.root))
        assert r.returncode == 2, r.stderr
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and f"in use by PID {os.getpid()} (splatcli train)" in lines[0], r.stderr
        assert not proj.export_path("ply").exists()  # refused before writing anything
        # in-process too (a library caller sees the typed error)
        with pytest.raises(ProjectBusy, match="in use by PID"):
            export_project(proj.root, ExportConfig())
    r = _run("export", str(proj.root))  # released: the same command now works
    assert r.returncode == 0, r.stderr
    assert proj.export_path("ply").is_file()


def test_export_and_eval_share_but_never_with_train(tmp_path):
    """A Makefile's -j runs export and eval of one project together: they only add
    files derived from the model. Neither may run beside train, nor train beside them."""
    proj = make_tiny_project(tmp_path / "p")
    with writer_lock(proj.root, "eval", shared=True):
        r = _run("export", str(proj.root))
        assert r.returncode == 0, r.stderr
        r = _run("train", str(proj.root), "--iterations", "2", "--device", "cpu")
        assert r.returncode == 2 and f"in use by PID {os.getpid()} (splatcli eval)" in r.stderr, r.stderr


def test_readers_run_alongside_a_writer(tmp_path):
    proj = make_tiny_project(tmp_path / "p")
    with writer_lock(proj.root, "train"):
        r = _run("render", str(proj.root), "-o", str(tmp_path / "frames"), "--split", "test")
        assert r.returncode == 0, r.stderr
    assert any((tmp_path / "frames").iterdir())


@pytest.mark.slow
def test_two_trains_then_kill_9_holder_then_a_new_run(tmp_path):
    proj = make_tiny_project(tmp_path / "p", trained=False)
    proj.update_manifest(scene={**proj.manifest()["scene"], "bounds_min": [-1.0] * 3, "bounds_max": [1.0] * 3})
    first = subprocess.Popen(
        _cli("train", str(proj.root), "--iterations", "100000", "--max-gaussians", "150", "--eval-every", "0",
             "--device", "cpu", "--quiet"),
        cwd=REPO, env={**os.environ, "OMP_NUM_THREADS": "1"}, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True)
    try:
        deadline = time.monotonic() + 120
        while not (proj.train_log_path.exists() and read_log(proj.train_log_path)):
            assert first.poll() is None, first.communicate()
            assert time.monotonic() < deadline, "no training progress within 120 s"
            time.sleep(0.1)
        second = _run("train", str(proj.root), "--iterations", "10", "--device", "cpu")
        assert second.returncode == 2, second.stderr
        assert f"PID {first.pid} (splatcli train)" in second.stderr and len(second.stderr.strip().splitlines()) == 1
        first.send_signal(signal.SIGKILL)
        first.wait(timeout=60)
    finally:
        if first.poll() is None:
            first.kill()
    third = _run("train", str(proj.root), "--iterations", "5", "--max-gaussians", "150", "--eval-every", "0",
                 "--device", "cpu", "--quiet")
    assert third.returncode == 0, third.stderr  # the dead holder's lock went with it
