"""Disk full while writing (issue 17): every write we publish (checkpoint, manifest,
report, render) ends in one line with exit 2, keeps the previous file whole and
leaves no temporary file behind. ENOSPC is injected where a real full disk reports
it last: the fsync of the finished temporary file."""

from __future__ import annotations

import errno
import os

import pytest
from typer.testing import CliRunner

from splatcli.cli.main import app
from splatcli.files.checkpoint import load_checkpoint
from support.tiny_project import make_tiny_project


@pytest.fixture
def full_disk_for(monkeypatch):
    """full_disk_for("name"): fsync of any open file whose name contains `name` fails."""
    real = os.fsync

    def arm(fragment: str) -> None:
        def fsync(fd: int) -> None:
            try:
                name = os.readlink(f"/proc/self/fd/{fd}")
            except OSError:
                name = ""
            if fragment in os.path.basename(name):
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            real(fd)

        monkeypatch.setattr(os, "fsync", fsync)

    return arm


def _fails_in_one_line(r, name: str) -> None:
    assert r.exit_code == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), r.stderr
    assert "No space left on device" in lines[0] and name in lines[0]


def _no_temp_files(root) -> None:
    debris = [p for p in root.rglob("*") if p.name.endswith(".tmp")]
    assert not debris, debris


pytestmark = pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs /proc to name file descriptors")


def test_checkpoint_write_keeps_the_previous_checkpoint(tmp_path, full_disk_for):
    proj = make_tiny_project(tmp_path / "p", trained=False, photos=False)
    proj.update_manifest(scene={**proj.manifest()["scene"], "bounds_min": [-1.0] * 3, "bounds_max": [1.0] * 3})
    args = ["train", str(proj.root), "--max-gaussians", "150", "--eval-every", "0", "--quiet", "--device", "cpu"]
    assert CliRunner().invoke(app, [*args, "--iterations", "10"]).exit_code == 0
    before = proj.latest_checkpoint()
    data = before.read_bytes()
    full_disk_for("step-000000020.pt")
    r = CliRunner().invoke(app, [*args, "--resume", "--iterations", "20"])
    _fails_in_one_line(r, "step-000000020.pt")
    assert proj.latest_checkpoint() == before and before.read_bytes() == data
    assert load_checkpoint(before).step == 10
    _no_temp_files(proj.root)


@pytest.mark.parametrize("name", ["splatcli.json", "eval.json", "eval.md"])
def test_manifest_and_report_writes_keep_the_previous_file(tmp_path, full_disk_for, name):
    proj = make_tiny_project(tmp_path / "p")
    assert CliRunner().invoke(app, ["eval", str(proj.root), "--quiet", "--no-plots"]).exit_code == 0
    path = {"splatcli.json": proj.manifest_path, "eval.json": proj.eval_json_path, "eval.md": proj.eval_md_path}[name]
    data = path.read_bytes()
    full_disk_for(name)
    r = CliRunner().invoke(app, ["eval", str(proj.root), "--quiet", "--no-plots"])
    _fails_in_one_line(r, name)
    assert path.read_bytes() == data
    _no_temp_files(proj.root)


def test_render_write_fails_in_one_line(tmp_path, full_disk_for):
    proj = make_tiny_project(tmp_path / "p")
    out = tmp_path / "frames"
    assert CliRunner().invoke(app, ["render", str(proj.root), "-o", str(out), "--quiet"]).exit_code == 0
    first = sorted(out.glob("*.png"))[0]
    data = first.read_bytes()
    full_disk_for(first.name)
    r = CliRunner().invoke(app, ["render", str(proj.root), "-o", str(out), "--quiet"])
    _fails_in_one_line(r, first.name)
    assert first.read_bytes() == data
    _no_temp_files(out)
