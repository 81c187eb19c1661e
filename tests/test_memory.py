"""Memory (issue 17): a run that cannot fit stops before loading anything, in one
line naming a setting that fits; an allocation failure mid-run keeps the last whole
step as a checkpoint and exits 2 with the same advice, never a traceback."""

from __future__ import annotations

import os
import platform
import re
import subprocess
import sys

import pytest
from typer.testing import CliRunner

import splatcli.train.trainer as trainer
from splatcli.cli.main import app
from splatcli.device import tune_allocator
from splatcli.errors import SplatError
from splatcli.files.checkpoint import load_checkpoint
from splatcli.render.composite import WORK_BYTES
from splatcli.train.memory import (
    ADVISE_SHARE,
    BYTES_PER_GAUSSIAN,
    MemoryPlan,
    check_memory,
    is_out_of_memory,
    plan_memory,
)
from support.tiny_project import make_tiny_project, ring_cameras

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _project(tmp_path):
    proj = make_tiny_project(tmp_path / "p", trained=False, photos=False)
    proj.update_manifest(scene={**proj.manifest()["scene"], "bounds_min": [-1.0] * 3, "bounds_max": [1.0] * 3})
    return proj


def _one_error_line(stderr: str) -> str:
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), stderr
    return lines[0]


def test_plan_counts_images_and_gaussians():
    cams = ring_cameras()
    p = plan_memory(cams, 300, 5000)
    assert p.budgeted and p.gaussians == 5000
    assert p.images == int(1.8 * 3 * sum(c.width * c.height for c in cams))
    assert p.need == p.images + 5000 * BYTES_PER_GAUSSIAN + WORK_BYTES  # and what a render holds for its backward
    assert not plan_memory(cams, 300, None).budgeted  # no budget: an estimate from the image size


def test_a_run_that_cannot_fit_stops_at_once_naming_a_budget_that_fits(tmp_path):
    proj = _project(tmp_path)
    args = ["train", str(proj.root), "--iterations", "2", "--eval-every", "0", "--quiet", "--device", "cpu"]
    r = CliRunner().invoke(app, [*args, "--max-gaussians", "100000000000"])  # 350 TB
    assert r.exit_code == 2
    line = _one_error_line(r.stderr)
    assert "training needs about" in line and "--max-gaussians" in line
    assert proj.latest_checkpoint() is None and not proj.train_log_path.exists()  # nothing started
    fits = re.search(r"--max-gaussians (\d+)", line).group(1)
    r = CliRunner().invoke(app, [*args, "--max-gaussians", fits])  # the advice is a setting that fits
    assert r.exit_code == 0, r.stderr


def test_the_advice_leaves_room_for_free_memory_to_move():
    free = 4 << 30
    plan = MemoryPlan(need=2 * free, images=free // 10, gaussians=10**9, budgeted=True, free=free,
                      limit="available RAM", longest=800, copies=1)
    with pytest.raises(SplatError) as e:
        check_memory(plan, 800)
    advised = int(re.search(r"--max-gaussians (\d+)", str(e.value)).group(1))
    used = plan.images + advised * BYTES_PER_GAUSSIAN + WORK_BYTES
    assert 0.7 * free < used <= ADVISE_SHARE * free < free


@pytest.mark.skipif(sys.platform != "linux", reason="RLIMIT_AS and /proc are Linux")
def test_under_rlimit_as_the_limit_is_named(tmp_path):
    proj = _project(tmp_path)
    code = (
        "import resource, sys\n"
        "import torch\n"  # torch's own address space first, then a limit 512 MB above it
        "vm = next(int(l.split()[1]) * 1024 for l in open('/proc/self/status') if l.startswith('VmSize:'))\n"
        "resource.setrlimit(resource.RLIMIT_AS, (vm + (512 << 20), resource.RLIM_INFINITY))\n"
        "from splatcli.cli.main import main\n"
        "sys.argv = ['splatcli'] + sys.argv[1:]\n"
        "main()\n"
    )
    r = subprocess.run([sys.executable, "-c", code, "train", str(proj.root), "--iterations", "2",
                        "--max-gaussians", "2000000", "--device", "cpu", "--quiet"],
                       cwd=REPO, capture_output=True, text=True, timeout=300,
                       env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert r.returncode == 2, r.stderr
    line = _one_error_line(r.stderr)
    assert "RLIMIT_AS" in line and "--max-gaussians" in line


def test_out_of_memory_mid_run_keeps_the_last_whole_step(tmp_path, monkeypatch):
    proj = _project(tmp_path)
    real, calls = trainer.render_view, []

    def render(*a, **k):
        calls.append(1)
        if len(calls) == 7:
            raise RuntimeError("DefaultCPUAllocator: can't allocate memory: you tried to allocate 123456789 bytes")
        return real(*a, **k)

    monkeypatch.setattr(trainer, "render_view", render)  # the training step's render
    r = CliRunner().invoke(app, ["train", str(proj.root), "--iterations", "50", "--max-gaussians", "150",
                                 "--eval-every", "0", "--quiet", "--device", "cpu"])
    assert r.exit_code == 2
    line = _one_error_line(r.stderr)
    assert "out of memory at step 7" in line and "--resume" in line and "step-000000006.pt" in line
    assert load_checkpoint(proj.checkpoint_path(6)).step == 6
    assert "Traceback" not in r.output


def test_only_allocation_failures_count_as_out_of_memory():
    assert is_out_of_memory(MemoryError())
    assert is_out_of_memory(RuntimeError("CUDA out of memory. Tried to allocate 2.00 GiB"))
    assert not is_out_of_memory(RuntimeError("shape mismatch"))
    assert not is_out_of_memory(ValueError("can't allocate memory"))


def test_the_allocator_keeps_freed_memory_where_the_c_library_is_glibc():
    """Every command calls tune_allocator (cli/main.py); on glibc both thresholds are set, elsewhere nothing is."""
    glibc = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"
    assert tune_allocator() is glibc
