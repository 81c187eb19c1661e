"""The batch Makefile in docs/pipelines.md really runs: two tiny captures, make -j2."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from test_end_to_end import load_make_scene

REPO = Path(__file__).resolve().parents[1]


def doc_makefile() -> str:
    text = (REPO / "docs" / "pipelines.md").read_text()
    blocks = re.findall(r"```make\n(.*?)```", text, flags=re.S)
    assert len(blocks) == 1, "docs/pipelines.md must hold exactly one ```make block"
    return blocks[0]


@pytest.mark.skipif(shutil.which("make") is None, reason="needs GNU make")
def test_pipeline_makefile_on_two_captures(tmp_path):
    (tmp_path / "Makefile").write_text(doc_makefile())
    make_scene = load_make_scene()
    for i, name in enumerate(["alpha", "beta"]):
        make_scene.render_scene(tmp_path / "captures" / name, num_views=12, width=160, height=120, seed=i)
    splatcli = Path(sys.executable).with_name("splatcli")
    args = ["make", "-j2", f"SPLATCLI={splatcli}", "TRAIN_FLAGS=--preset demo --iterations 40 --eval-every 0"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    r = subprocess.run(args, cwd=tmp_path, capture_output=True, text=True, env=env, timeout=900)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    for name in ("alpha", "beta"):
        proj = tmp_path / "projects" / name
        assert (proj / "exports" / "scene.ply").stat().st_size > 1000
        report = json.loads((proj / "reports" / "eval.json").read_text())
        assert report["train_steps"] == 40 and report["psnr"] > 8
    # Every target is up to date now: a second make has nothing to do.
    q = subprocess.run(["make", "-q", f"SPLATCLI={splatcli}"], cwd=tmp_path, env=env)
    assert q.returncode == 0
