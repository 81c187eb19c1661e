"""`splatcli eval`: the report's keys and numbers, the budget curve, plots with
and without matplotlib, folder comparison, and refusals."""

from __future__ import annotations

import dataclasses
import importlib
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from splatcli.device import resolve_device
from splatcli.errors import SplatError
from splatcli.eval.budgets import contributions, prune_to
from splatcli.eval.evaluate import EvalConfig, check_eval_config
from splatcli.eval.report import used_sh_degree
from splatcli.files.checkpoint import load_gaussians
from splatcli.formats.ply import ply_bytes
from splatcli.gaussians import SH_C0
from splatcli.project import Project
from splatcli.render import rasterize
from support.tiny_project import (
    assert_user_error,
    make_tiny_project,
    ring_cameras,
    run_cli,
    run_ok,
    snapshot,
    tiny_gaussians,
)

AUTO_DEVICE = resolve_device("auto").type  # "cpu", or "cuda" where a GPU is

REQUIRED = ["psnr", "ssim", "per_image", "num_gaussians", "sh_degree", "ply_bytes", "train_seconds", "train_steps",
            "render_fps", "device", "split"]


@pytest.fixture(scope="module")
def proj(tmp_path_factory) -> Project:
    return make_tiny_project(tmp_path_factory.mktemp("eval") / "p")


@pytest.fixture(scope="module")
def evaluated(proj: Project):
    r = run_ok("eval", proj.root, "--json")
    return proj, json.loads(r.stdout)


def _independent_scores(proj: Project, name: str) -> tuple[float, float]:
    """Render one view with the rasterizer, quantise, and score with numpy / scikit-image."""
    g = load_gaussians(proj.latest_checkpoint())
    cam = next(c for c in ring_cameras() if c.name == name)
    vm, K = cam.torch(torch.device("cpu"))
    with torch.no_grad():
        img = rasterize(g.means, g.quats, g.log_scales, g.opacity_logits, g.sh, vm, K, cam.width, cam.height,
                        torch.zeros(3)).image
    pred = np.round(img.clamp(0, 1).numpy().astype(np.float64) * 255) / 255
    gt = cv2.imread(str(proj.images_dir / name))[..., ::-1].astype(np.float64) / 255
    p = 10 * np.log10(1 / np.mean((pred - gt) ** 2))
    s = structural_similarity(pred, gt, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                              data_range=1.0, channel_axis=-1)
    return float(p), float(s)


def test_eval_report_keys_and_numbers(evaluated) -> None:
    proj, summary = evaluated
    data = json.loads(proj.eval_json_path.read_text())
    for k in REQUIRED:
        assert k in data, k
    assert {k: summary[k] for k in REQUIRED if k != "per_image"} == {k: data[k] for k in REQUIRED if k != "per_image"}
    assert data["split"] == "test" and data["num_gaussians"] == 300 and data["sh_degree"] == 1
    assert data["ply_bytes"] == ply_bytes(300, 1) and data["train_seconds"] == 12.5 and data["train_steps"] == 200
    assert data["render_fps"] > 0 and data["device"].startswith(AUTO_DEVICE)
    assert [x["name"] for x in data["per_image"]] == ["img_000.png", "img_008.png"]
    for x in data["per_image"]:
        p, s = _independent_scores(proj, x["name"])
        assert x["psnr"] == pytest.approx(p, abs=1e-6)
        assert x["ssim"] == pytest.approx(s, abs=1e-4)  # the bound against scikit-image
    assert data["psnr"] == pytest.approx(np.mean([x["psnr"] for x in data["per_image"]]))
    assert 15 < data["psnr"] < 60  # the perturbed model is close to, not equal to, the truth
    # speed against error: four budgets, smaller is worse here (no fine-tuning)
    b = data["budgets"]
    assert [x["fraction"] for x in b] == [1.0, 0.5, 0.25, 0.1]
    assert [x["num_gaussians"] for x in b] == [300, 150, 75, 30]
    assert b[0]["psnr"] == data["psnr"] and b[0]["psnr"] > b[-1]["psnr"]
    assert all(x["render_fps"] > 0 and x["ply_bytes"] == ply_bytes(x["num_gaussians"], 1) for x in b)
    assert [p["step"] for p in data["training_curve"]] == [0, 100, 200]
    # the model's step, not the stride of the views that rank Gaussians for the default budgets
    assert data["step"] == int(proj.latest_checkpoint().stem.split("-")[1])
    st = data["stats"]
    assert sum(st["opacity_hist"]["counts"]) == 300 and sum(st["log10_scale_hist"]["counts"]) == 900
    assert sum(st["sh_degree_counts"]) == 300
    assert proj.step("eval")["summary"]["psnr"] == data["psnr"]
    # scored as 8-bit images (eval/score.py); the tiny project's log predates the field: unquantised
    assert data["quantisation"] == summary["quantisation"] == "8-bit" and data["curve_quantisation"] == "none"


def test_eval_markdown_and_plots(evaluated) -> None:
    proj, _ = evaluated
    md = proj.eval_md_path.read_text()
    for needle in ("## Summary", "Scores: 8-bit renders, as saved to PNG.", "| PSNR (mean over views) |",
                   "(reports/train_log.jsonl; unquantised renders", "## Speed against error", "| 50% | 150 |",
                   "## Worst five views", "| img_008.png |", "## Model statistics", "![speed against error](speed_vs_error.png)"):
        assert needle in md, needle
    for name in ("speed_vs_error", "scales", "opacities", "sh_degrees"):
        img = cv2.imread(str(proj.plot_path(name)))
        assert img is not None and img.shape[0] > 100, name
        assert f"({name}.png)" in md


def test_eval_of_a_ply_matches_the_checkpoint(evaluated, tmp_path: Path) -> None:
    proj, summary = evaluated
    assert run_cli("export", proj.root, "-o", tmp_path / "m.ply", "-q").exit_code == 0
    before = proj.step("eval")
    r = run_ok("eval", proj.root, "--model", tmp_path / "m.ply", "--out", tmp_path / "rep", "--budgets", "1", "--json")
    s = json.loads(r.stdout)
    assert s["psnr"] == summary["psnr"] and s["ssim"] == summary["ssim"] and s["model"] == str(tmp_path / "m.ply")
    assert s["step"] is None and s["train_seconds"] is None
    assert (tmp_path / "rep" / "eval.json").is_file() and (tmp_path / "rep" / "eval.md").is_file()
    assert proj.step("eval") == before  # the project's own record is untouched
    r = run_ok("eval", proj.root, "--model", tmp_path / "m.ply", "--out", tmp_path / "rep2", "--json")
    s = json.loads(r.stdout)  # default budgets: a .ply has no step, whatever the ranking views' stride
    assert s["step"] is None and s["train_steps"] is None
    assert_user_error(run_cli("eval", proj.root, "--model", tmp_path / "none.ply"), "--model", "no such .ply")


def test_eval_without_matplotlib(tmp_path: Path, monkeypatch) -> None:
    proj = make_tiny_project(tmp_path / "p")
    for name in [m for m in sys.modules if m == "matplotlib" or m.startswith("matplotlib.")] + ["matplotlib"]:
        monkeypatch.setitem(sys.modules, name, None)  # `import matplotlib...` now raises ImportError
    r = run_ok("eval", proj.root, "--budgets", "1", "--json")
    assert "matplotlib is not installed" in r.stderr
    data = json.loads(proj.eval_json_path.read_text())
    assert data["plots"] == [] and [x["fraction"] for x in data["budgets"]] == [1.0]
    md = proj.eval_md_path.read_text()
    assert "matplotlib is not installed" in md and ".png)" not in md and "## Worst five views" in md
    assert not list(proj.reports_dir.glob("*.png"))


def test_contributions_are_exact_blending_weights() -> None:
    g = tiny_gaussians(40, seed=3, sh_degree=0)
    cam = ring_cameras()[2]
    w = contributions(g, [cam])
    vm, K = cam.torch(torch.device("cpu"))
    # independent: colour exactly 1 in red for Gaussian i, exactly 0 for the others
    # (DC = -0.5 / SH_C0 gives 0 before the clamp), black background: the red sum is sum_p w_i
    for i in (0, 7, 19):
        sh = torch.full((40, 1, 3), -0.5 / SH_C0)
        sh[i, 0, 0] = 0.5 / SH_C0
        with torch.no_grad():
            img = rasterize(g.means, g.quats, g.log_scales, g.opacity_logits, sh, vm, K, cam.width, cam.height).image
        assert float(w[i]) == pytest.approx(float(img[..., 0].sum()), rel=1e-4, abs=1e-4)  # float32 sums
    with torch.no_grad():
        alpha = rasterize(g.means, g.quats, g.log_scales, g.opacity_logits, g.sh, vm, K, cam.width, cam.height).alpha
    assert float(w.sum()) == pytest.approx(float(alpha.sum()), rel=1e-5)  # sum_i w_i = 1 - T per pixel
    kept = prune_to(g, w, 0.25)
    assert len(kept) == 10 and set(kept.means[:, 0].tolist()) == set(g.means[torch.argsort(-w)[:10], 0].tolist())


@pytest.mark.parametrize("banded", [False, True])
def test_contributions_equal_the_colour_gradient(banded: bool, monkeypatch) -> None:
    """The forward pass's weight sums against autograd's: with every colour 0.5 (DC 0) the red
    channel's gradient with respect to dc_i is SH_C0 sum_pixels w_i. Small chunks and short segments
    (several chunks, early termination between segments), the image in bands of tile rows, and sizes
    that no block divides (a block's pixels past the image's edge count for nothing)."""
    composite = importlib.import_module("splatcli.render.composite")
    rz = importlib.import_module("splatcli.render.rasterize")  # (the package's `rasterize` is the function)

    monkeypatch.setattr(composite, "CHUNK_ELEMS", 1 << 11)
    monkeypatch.setattr(composite, "SEGMENT", 8)
    monkeypatch.setattr(composite, "SEGMENT_4PX", 8)
    if banded:
        monkeypatch.setattr(rz, "PAIR_BUDGET", 64)  # several bands of 16 rows
    g = tiny_gaussians(400, seed=5, sh_degree=0)
    g.opacity_logits += 2.0  # dense enough that pixels saturate (termination)
    cams = [dataclasses.replace(c, width=c.width - d, height=c.height - 2 * d)
            for c, d in zip(ring_cameras(3, scale=2), (0, 3, 7))]
    w = contributions(g, cams)
    ref = torch.zeros(len(g), dtype=torch.float64)
    for cam in cams:
        vm, K = cam.torch(torch.device("cpu"))
        dc = torch.zeros(len(g), 1, 3, requires_grad=True)
        out = rasterize(g.means, g.quats, g.log_scales, g.opacity_logits, dc, vm, K, cam.width, cam.height,
                        torch.zeros(3), sh_degree=0)
        ref += torch.autograd.grad(out.image[..., 0].sum(), dc)[0][:, 0, 0].double() / SH_C0
    assert float(ref.sum()) > 100.0 and int((ref > 0).sum()) > 300  # (a scene that covers the views)
    torch.testing.assert_close(w, ref, rtol=1e-5, atol=1e-4)  # float32 sums in a different order


def test_used_sh_degree() -> None:
    sh = torch.zeros(3, 9, 3)
    sh[1, 2, 0] = 0.5  # band 1
    sh[2, 5, 1] = -0.2  # band 2
    sh[0, 4, 2] = 0.001  # below the tolerance: degree 0
    assert used_sh_degree(sh).tolist() == [0, 1, 2]


def _write_images(d: Path, imgs: dict[str, np.ndarray]) -> None:
    d.mkdir(parents=True, exist_ok=True)
    for name, img in imgs.items():
        cv2.imwrite(str(d / name), img)


def test_compare_folders(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    gt = {f"v{i}.png": rng.integers(0, 256, (20, 24, 3), dtype=np.uint8) for i in range(3)}
    pred = {k.replace(".png", ".png"): np.clip(v.astype(int) + rng.integers(-9, 10, v.shape), 0, 255).astype(np.uint8)
            for k, v in gt.items()}
    pred["extra.png"] = gt["v0.png"]
    _write_images(tmp_path / "gt", gt)
    _write_images(tmp_path / "pred", pred)
    r = run_ok("eval", "--pred", tmp_path / "pred", "--gt", tmp_path / "gt", "--json")
    s = json.loads(r.stdout)
    assert s["missing"] == ["extra.png"] and s["num_images"] == 3 and s["quantisation"] == "8-bit"
    ref = [10 * np.log10(1 / np.mean((pred[k][..., ::-1] / 255.0 - gt[k][..., ::-1] / 255.0) ** 2)) for k in sorted(gt)]
    assert s["psnr"] == pytest.approx(np.mean(ref), abs=1e-9)
    assert [x["name"] for x in s["per_image"]] == sorted(gt)
    # a size mismatch is named
    _write_images(tmp_path / "pred", {"v1.png": np.zeros((20, 25, 3), np.uint8)})
    assert_user_error(run_cli("eval", "--pred", tmp_path / "pred", "--gt", tmp_path / "gt"), "v1.png", "differs", alone=False)


@pytest.mark.parametrize("args,fragments", [
    (["--split", "val"], ["--split 'val'", "test, train, all"]),
    (["--budgets", "0"], ["--budgets", "(0, 1]"]),
    (["--budgets", "half"], ["--budgets 'half'"]),
    (["--downscale", "-1"], ["--downscale -1"]),
    (["--background", "0.5"], ["--background '0.5'"]),
    (["--pred", "x"], ["--pred and --gt go together"]),
])
def test_eval_option_errors(proj: Project, args: list[str], fragments: list[str]) -> None:
    before = snapshot(proj.root)
    assert_user_error(run_cli("eval", proj.root, *args), *fragments)
    assert snapshot(proj.root) == before


def test_eval_refuses_an_unknown_quantisation(proj: Project) -> None:
    with pytest.raises(SplatError, match="quantisation '16-bit' is not known"):
        check_eval_config(EvalConfig(quantisation="16-bit"))


def test_eval_needs_a_project_or_folders(tmp_path: Path) -> None:
    assert_user_error(run_cli("eval"), "PROJECT")
    assert_user_error(run_cli("eval", "--pred", tmp_path / "a", "--gt", tmp_path / "b"), "--pred", "not a directory")
