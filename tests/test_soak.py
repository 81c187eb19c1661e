"""Soak (issue 17): a 20k-step run on a tiny scene keeps its resident memory and its
open file descriptors flat once densification stops (checkpoints, logs and
evaluations come and go all along)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from splatcli.train.log import read_log
from support.tiny_project import make_tiny_project

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
STEPS = 20_000
REFINE_STOP = 4_000  # --preset fast


@pytest.mark.slow
@pytest.mark.first  # about 3.5 minutes: started first (tests/conftest.py)
@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="RSS and descriptors are read from /proc")
def test_20k_steps_keep_memory_and_descriptors_flat(tmp_path):
    proj = make_tiny_project(tmp_path / "p", trained=False)
    proj.update_manifest(scene={**proj.manifest()["scene"], "bounds_min": [-1.0] * 3, "bounds_max": [1.0] * 3})
    r = subprocess.run([sys.executable, "-m", "splatcli.cli.main", "train", str(proj.root),
                        "--preset", "fast", "--max-gaussians", "500",
                        "--iterations", str(STEPS), "--device", "cpu", "--quiet"],
                       cwd=REPO, capture_output=True, text=True, timeout=1800, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert r.returncode == 0, r.stderr
    log = [x for x in read_log(proj.train_log_path) if x["step"] % 500 == 0]
    assert log[-1]["step"] == STEPS
    # after densification stops, and one log period for the allocator to settle
    late = [x for x in log if x["step"] >= REFINE_STOP + 1000]
    rss = [x["rss_mb"] for x in late]
    fds = {x["open_fds"] for x in late}
    assert max(rss) - min(rss) <= 16, rss  # MiB: flat within allocator noise
    assert len(fds) == 1, fds  # no descriptor leaks: checkpoints, logs and evaluations close theirs
    assert len({x["num_gaussians"] for x in late}) == 1  # and the model no longer changes size
