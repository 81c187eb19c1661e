"""`splatcli export`: the 3DGS .ply round trip and the .splat, through the CLI."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import plyfile
import pytest
import torch

from splatcli.files.checkpoint import load_gaussians, save_checkpoint
from splatcli.formats.ply import ply_bytes, read_ply
from splatcli.formats.splat import SPLAT_ROW_BYTES, read_splat
from support.tiny_project import assert_user_error, make_tiny_project, run_cli, run_ok, snapshot, tiny_gaussians

EXPECTED_SH1 = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(9)]
                + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


@pytest.fixture(scope="module")
def proj(tmp_path_factory):
    return make_tiny_project(tmp_path_factory.mktemp("export") / "p")


def test_export_ply_layout_and_same_pixels(proj, tmp_path: Path) -> None:
    r = run_ok("export", proj.root, "--json")
    summary = json.loads(r.stdout)
    path = proj.export_path("ply")
    assert summary["path"] == str(path) and summary["num_gaussians"] == 300 and summary["sh_degree"] == 1
    assert path.stat().st_size == summary["bytes"] == ply_bytes(300, 1)
    # the standard layout, read by plyfile
    ply = plyfile.PlyData.read(str(path))
    assert [p.name for p in ply["vertex"].properties] == EXPECTED_SH1
    assert all(ply["vertex"].data.dtype[n] == np.dtype("<f4") for n in EXPECTED_SH1)
    assert ply.byte_order == "<" and ply["vertex"].count == 300
    # the parameters come back bit for bit
    ck = load_gaussians(proj.latest_checkpoint())
    back = read_ply(path).gaussians
    for k, v in ck.as_dict().items():
        torch.testing.assert_close(getattr(back, k), v, rtol=0, atol=0)
    # and render to the same pixels as the checkpoint
    a = run_cli("render", proj.root, "--out", tmp_path / "ck", "-q")
    b = run_cli("render", path, "--project", proj.root, "--out", tmp_path / "ply", "-q")
    assert a.exit_code == 0 and b.exit_code == 0, (a.output, b.output)
    names = sorted(p.name for p in (tmp_path / "ck").glob("*.png"))
    assert names == ["img_000.png", "img_008.png"] == sorted(p.name for p in (tmp_path / "ply").glob("*.png"))
    for n in names:
        np.testing.assert_array_equal(cv2.imread(str(tmp_path / "ck" / n)), cv2.imread(str(tmp_path / "ply" / n)))


def test_export_splat(proj, tmp_path: Path) -> None:
    out = tmp_path / "m.splat"
    r = run_ok("export", proj.root, "--format", "splat", "-o", out)
    assert "SH degree 0" in r.stderr  # the loss is said
    assert out.stat().st_size == 300 * SPLAT_ROW_BYTES
    t = read_splat(out)
    g = load_gaussians(proj.latest_checkpoint())
    assert set(map(tuple, t["position"].tolist())) == set(map(tuple, g.means.numpy().tolist()))


def test_export_errors(proj, tmp_path: Path) -> None:
    before = snapshot(proj.root)
    assert_user_error(run_cli("export", proj.root, "--format", "obj"), "--format 'obj'", "ply, compressed-ply, spz, sog, splat")
    assert_user_error(run_cli("export", tmp_path / "nope"), str(tmp_path / "nope"))
    (tmp_path / "plain").mkdir()
    assert_user_error(run_cli("export", tmp_path / "plain"), "not a splatcli project")
    assert_user_error(run_cli("export", proj.root, "-o", tmp_path), "is a directory")
    assert snapshot(proj.root) == before
    untrained = make_tiny_project(tmp_path / "u", trained=False, photos=False)
    before = snapshot(untrained.root)
    assert_user_error(run_cli("export", untrained.root), "no trained model", "splatcli train")
    assert snapshot(untrained.root) == before


def test_export_drops_non_finite_rows(tmp_path: Path) -> None:
    p = make_tiny_project(tmp_path / "p", trained=False, photos=False)
    g = tiny_gaussians(20)
    g.means[3, 1] = float("nan")
    g.log_scales[11, 0] = float("inf")
    save_checkpoint(p.checkpoint_path(10), step=10, gaussians=g, sh_degree=1)
    for fmt, size in (("ply", ply_bytes(18, 1)), ("splat", 18 * SPLAT_ROW_BYTES)):
        r = run_ok("export", p.root, "-f", fmt, "--json")
        s = json.loads(r.stdout)
        assert (s["num_gaussians"], s["num_dropped"]) == (18, 2)
        assert p.export_path(fmt).stat().st_size == size
    assert "dropped 2 Gaussians" in run_cli("export", p.root).stderr
