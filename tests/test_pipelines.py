"""The batch Makefile in docs/pipelines.md really runs: two tiny captures, make -j2."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from support import make_scene

REPO = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.slow  # make and snakemake run whole captures through every command


def doc_makefile() -> str:
    text = (REPO / "docs" / "pipelines.md").read_text()
    blocks = re.findall(r"```make\n(.*?)```", text, flags=re.S)
    assert len(blocks) == 1, "docs/pipelines.md must hold exactly one ```make block"
    return blocks[0]


def _two_captures(tmp_path: Path) -> None:
    """captures/alpha and captures/beta: 12 rendered views each, 160x120."""
    scene = make_scene()
    for i, name in enumerate(["alpha", "beta"]):
        scene.render_scene(tmp_path / "captures" / name, num_views=12, width=160, height=120, seed=i)


def _check_built(tmp_path: Path) -> None:
    """Both captures exported and evaluated after 40 training steps."""
    for name in ("alpha", "beta"):
        proj = tmp_path / "projects" / name
        assert (proj / "exports" / "scene.ply").stat().st_size > 1000
        report = json.loads((proj / "reports" / "eval.json").read_text())
        assert report["train_steps"] == 40 and report["psnr"] > 8


@pytest.mark.skipif(shutil.which("make") is None, reason="needs GNU make")
def test_pipeline_makefile_on_two_captures(tmp_path):
    (tmp_path / "Makefile").write_text(doc_makefile())
    _two_captures(tmp_path)
    splatcli = Path(sys.executable).with_name("splatcli")
    args = ["make", "-j2", f"SPLATCLI={splatcli}", "TRAIN_FLAGS=--preset demo --iterations 40 --eval-every 0"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    r = subprocess.run(args, cwd=tmp_path, capture_output=True, text=True, env=env, timeout=900)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    _check_built(tmp_path)
    # Every target is up to date now: a second make has nothing to do.
    q = subprocess.run(["make", "-q", f"SPLATCLI={splatcli}"], cwd=tmp_path, env=env)
    assert q.returncode == 0


@pytest.mark.skipif(shutil.which("make") is None, reason="needs GNU make")
def test_batch_with_a_corrupt_frame_a_duplicate_job_and_a_scene_too_big(tmp_path):
    """Issue 17's batch: `make -k` builds every good capture; a corrupt photo is skipped
    with a warning; a scene that cannot fit in memory and a second `make` started on
    the same projects while the first runs each fail in one line, never a traceback;
    afterwards every good capture is up to date."""
    (tmp_path / "Makefile").write_text(
        doc_makefile()
        # the documented per-capture override, here asking far more memory than any machine has
        + "\n$(OUT)/huge/reports/train.json: override TRAIN_FLAGS += --max-gaussians 100000000000\n")
    scene = make_scene()
    for i, name in enumerate(["alpha", "beta", "huge"]):
        scene.render_scene(tmp_path / "captures" / name, num_views=12, width=160, height=120, seed=i)
    shot = tmp_path / "captures" / "beta" / "images" / "003.jpg"
    shot.write_bytes(shot.read_bytes()[:300])  # a photo cut short
    splatcli = Path(sys.executable).with_name("splatcli")
    args = ["make", "-k", f"SPLATCLI={splatcli}", "TRAIN_FLAGS=--preset demo --iterations 40 --eval-every 0"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    first = subprocess.Popen(args, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    lock = tmp_path / "projects" / "alpha" / ".splatcli.lock"
    deadline = time.monotonic() + 120
    while not (lock.is_file() and lock.read_text()):  # the first make is processing alpha
        assert first.poll() is None and time.monotonic() < deadline
        time.sleep(0.05)
    second = subprocess.run(args, cwd=tmp_path, capture_output=True, text=True, env=env, timeout=900)
    _, err1 = first.communicate(timeout=900)
    err = err1 + second.stderr
    assert first.returncode != 0 and second.returncode != 0  # "huge" fails; make -k built the rest
    assert "Traceback" not in err and "internal error" not in err
    busy = [ln for ln in second.stderr.splitlines() if "in use by PID" in ln]
    assert busy and all(ln.startswith("error: ") and "(splatcli " in ln for ln in busy)
    too_big = [ln for ln in err.splitlines() if ln.startswith("error: training needs about")]
    assert too_big and all("--max-gaussians" in ln for ln in too_big)
    for name in ("alpha", "beta"):
        proj = tmp_path / "projects" / name
        assert (proj / "exports" / "scene.ply").stat().st_size > 1000
        assert json.loads((proj / "reports" / "eval.json").read_text())["train_steps"] == 40
    skipped = json.loads((tmp_path / "projects" / "beta" / "reports" / "process.json").read_text())["skipped"]
    assert len(skipped) == 1 and skipped[0].startswith("003.jpg")
    assert not (tmp_path / "projects" / "huge" / "exports" / "scene.ply").exists()
    good = [f"projects/{n}/exports/scene.ply" for n in ("alpha", "beta")]
    assert subprocess.run(["make", "-q", f"SPLATCLI={splatcli}", *good], cwd=tmp_path, env=env).returncode == 0


SNAKEMAKE = shutil.which("snakemake") or (str(Path(sys.executable).with_name("snakemake"))
                                          if Path(sys.executable).with_name("snakemake").exists() else None)


@pytest.mark.skipif(SNAKEMAKE is None, reason="needs snakemake (pip install -e '.[dev]' installs it)")
def test_snakefile_builds_two_captures_and_a_second_run_does_nothing(tmp_path):
    _two_captures(tmp_path)
    splatcli = Path(sys.executable).with_name("splatcli")
    args = [SNAKEMAKE, "-s", str(REPO / "pipelines" / "Snakefile"), "--cores", "2", "--directory", str(tmp_path),
            "--config", f"splatcli={splatcli}", f"captures={tmp_path / 'captures'}", f"out={tmp_path / 'projects'}",
            "train_flags=--preset demo --iterations 40 --eval-every 0"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    r = subprocess.run(args, capture_output=True, text=True, env=env, timeout=900)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    _check_built(tmp_path)
    again = subprocess.run(args, capture_output=True, text=True, env=env, timeout=300)
    assert again.returncode == 0 and "Nothing to be done" in again.stdout + again.stderr, again.stderr[-2000:]
    assert "rule train" not in again.stdout + again.stderr
