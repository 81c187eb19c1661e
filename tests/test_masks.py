"""Masks: every source `process` reads (a masks/ folder with both namings, a transforms.json
mask_path, an alpha channel, --invert-masks), their checks, SfM ignoring masked pixels,
the loss and the scores ignoring them, and --mask-mode background painting them."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
import torch

from splatcli.eval.metrics import psnr, ssim
from splatcli.events import Stages
from splatcli.inputs.images import StagedImage, load_mask
from splatcli.process.masks import stage_all, staged_mask
from splatcli.process.run import ProcessConfig, process
from splatcli.project import Project
from splatcli.sfm import colmap
from splatcli.train.data import load_train_data
from splatcli.train.loss import photometric_loss
from support.tiny_project import assert_user_error, make_tiny_project, run_cli, run_ok
from test_process import render

N_VIEWS, W, H = 16, 256, 192


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """The sample scene with a ball rolling through it; half its masks renamed
    to the stem naming (001.png), the other half kept as COLMAP's (002.jpg.png)."""
    out = render(tmp_path_factory.mktemp("scene") / "scene", num_views=N_VIEWS, width=W, height=H, distractor=True)
    for i in range(0, N_VIEWS, 2):
        (out / "masks" / f"{i + 1:03d}.jpg.png").rename(out / "masks" / f"{i + 1:03d}.png")
    return out


@pytest.fixture(scope="module")
def processed(scene, tmp_path_factory) -> Project:
    out = tmp_path_factory.mktemp("proj") / "p"
    r = process(scene, out, ProcessConfig(seed=0))
    assert r.registered == N_VIEWS and r.mask_source == "files"
    return Project(out)


def _moved(scene: Path) -> list[str]:
    return json.loads((scene / "ground_truth.json").read_text())["distractor_views"]


def test_mask_folder_is_read_with_both_namings_and_undistorted(processed, scene):
    moved = _moved(scene)
    assert len(moved) >= N_VIEWS // 3 and all(int(n[:3]) % 4 for n in moved)  # never a held-out view
    facts = processed.manifest()["scene"]
    assert facts["masks"] is True and facts["mask_source"] == "files"
    assert facts["background"] == [0.0, 0.0, 0.0]  # black: file masks are not an object capture's alpha
    assert processed.mask_source() == "files" and processed.mask_mode() == "ignore"
    for i in range(N_VIEWS):
        name = f"{i:03d}.jpg"
        m = cv2.imread(str(processed.mask_path(name)), cv2.IMREAD_UNCHANGED)
        img = cv2.imread(str(processed.images_dir / name))
        assert m.shape == img.shape[:2] and set(np.unique(m)) <= {0, 255}  # undistorted, still binary
        src = cv2.imread(str(next((scene / "masks").glob(f"{name[:3]}.*png"))), cv2.IMREAD_GRAYSCALE)
        # Undistortion crops a few pixels: the masked area keeps its share of the image.
        assert (m == 0).mean() == pytest.approx((src == 0).mean(), abs=0.01)
        assert ((m == 0).any()) == (name in moved)


def test_sfm_finds_no_features_under_a_mask(processed, scene):
    db = pycolmap.Database.open(str(processed.database_path))
    try:
        checked = 0
        for image in db.read_all_images():
            src = next((scene / "masks").glob(f"{image.name[:3]}.*png"))
            masked = cv2.imread(str(src), cv2.IMREAD_GRAYSCALE) == 0
            kp = db.read_keypoints(image.image_id)[:, :2]  # x, y in pixels (corner convention)
            u = np.clip(kp[:, 0].astype(int), 0, W - 1)
            v = np.clip(kp[:, 1].astype(int), 0, H - 1)
            assert len(kp) > 100
            assert not masked[v, u].any(), image.name
            checked += int(masked.any())
        assert checked == len(_moved(scene))
    finally:
        db.close()


def test_pycolmap_receives_the_mask_folder(tmp_path, monkeypatch):
    seen = {}
    monkeypatch.setattr(pycolmap, "extract_features", lambda *a, **k: seen.update(k))
    colmap.extract_features(tmp_path / "db", tmp_path, ["a.jpg"], colmap.SiftOptions(),
                            mask_dir=tmp_path / "masks")
    assert str(seen["reader_options"].mask_path) == str(tmp_path / "masks")
    colmap.extract_features(tmp_path / "db", tmp_path, ["a.jpg"], colmap.SiftOptions())
    assert str(seen["reader_options"].mask_path) in ("", ".")  # pycolmap's default: no masks


def test_a_mask_of_the_wrong_size_is_one_line_naming_it(scene, tmp_path):
    src = tmp_path / "cap"
    shutil.copytree(scene, src)
    bad = src / "masks" / "002.jpg.png"
    cv2.imwrite(str(bad), np.zeros((H // 2, W // 2), np.uint8))
    assert_user_error(run_cli("process", src, "-o", tmp_path / "p"), str(bad), "128x96", f"{W}x{H}", alone=False)


def test_images_without_a_mask_are_kept_whole_with_a_warning(scene, tmp_path):
    """Checked on the staging step alone (no SfM): a missing mask is all-keep."""
    notes = []
    run = Stages(lambda e: notes.append(getattr(e, "message", None)))
    staged = [StagedImage(n, W, H, False) for n in ("000.jpg", "001.jpg")]
    found = {"000.jpg": None, "001.jpg": scene / "masks" / "001.png"}
    assert stage_all(found, staged, tmp_path, run, invert=False, where=scene / "masks") == "files"
    assert (cv2.imread(str(staged_mask(tmp_path, "000.jpg")), cv2.IMREAD_GRAYSCALE) == 255).all()
    assert (cv2.imread(str(staged_mask(tmp_path, "001.jpg")), cv2.IMREAD_GRAYSCALE) == 0).any()
    assert any(n and "1 image(s) have no mask" in n and "000.jpg" in n for n in notes), notes


def _transforms_capture(root: Path, *, alpha: bool = False, masks: bool = True, size=(64, 48)) -> Path:
    """Four random 64x48 frames (RGBA when `alpha`) in a transforms.json, with a
    mask_path each: the left half black (masked out)."""
    rng = np.random.default_rng(0)
    (root / "images").mkdir(parents=True)
    (root / "masks").mkdir()
    frames = []
    for i in range(4):
        img = rng.integers(0, 256, (48, 64, 4 if alpha else 3), dtype=np.uint8)
        if alpha:
            img[..., 3] = 255
            img[:10, :, 3] = 0
        cv2.imwrite(str(root / "images" / f"f{i}.png"), img)
        fr = {"file_path": f"images/f{i}.png",
              "transform_matrix": [[1, 0, 0, i * 0.1], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]]}
        if masks:
            m = np.full((size[1], size[0]), 255, np.uint8)
            m[:, : size[0] // 2] = 0
            cv2.imwrite(str(root / "masks" / f"f{i}.png"), m)
            fr["mask_path"] = f"masks/f{i}.png"
        frames.append(fr)
    (root / "transforms.json").write_text(json.dumps({"camera_angle_x": 0.9, "frames": frames}))
    return root


@pytest.mark.parametrize("invert", [False, True])
def test_transforms_mask_path_and_invert(tmp_path, invert):
    src = _transforms_capture(tmp_path / "cap")
    args = ["--invert-masks"] if invert else []
    r = run_ok("process", src, "-o", tmp_path / "p", "--json", *args)
    assert json.loads(r.stdout)["mask_source"] == "files"
    m = cv2.imread(str(Project(tmp_path / "p").mask_path("f1.png")), cv2.IMREAD_UNCHANGED)
    left, right = (255, 0) if invert else (0, 255)
    assert m.shape == (48, 64) and (m[:, :32] == left).all() and (m[:, 32:] == right).all()


def test_transforms_mask_errors_name_the_file(tmp_path):
    src = _transforms_capture(tmp_path / "small", size=(32, 24))
    assert_user_error(run_cli("process", src, "-o", tmp_path / "p1"), str(src / "masks" / "f0.png"), "32x24",
                      "64x48", alone=False)
    src = _transforms_capture(tmp_path / "gone")
    (src / "masks" / "f2.png").unlink()
    assert_user_error(run_cli("process", src, "-o", tmp_path / "p2"), str(src / "masks" / "f2.png"),
                      "images/f2.png")


def test_alpha_masks_stay_the_background_mode(tmp_path):
    src = _transforms_capture(tmp_path / "cap", alpha=True, masks=False)
    r = process(src, tmp_path / "p")
    proj = Project(tmp_path / "p")
    assert r.mask_source == "alpha" and proj.mask_source() == "alpha" and proj.mask_mode() == "background"
    assert proj.manifest()["scene"]["background"] == [1.0, 1.0, 1.0]
    m = cv2.imread(str(proj.mask_path("f0.png")), cv2.IMREAD_UNCHANGED)
    assert (m[:10] == 0).all() and (m[10:] == 255).all()
    # auto (background) loads no masks: the images already are composited, as before masks existed
    data = load_train_data(proj, 1.0, None, torch.device("cpu"))
    assert data.mask_mode == "background" and all(v.keep is None for v in data.train + data.test)


# ---- the loss and the scores ------------------------------------------------------


def _pair(seed: int = 0, h: int = 24, w: int = 32):
    g = torch.Generator().manual_seed(seed)
    pred = torch.rand(h, w, 3, generator=g, dtype=torch.float64)
    gt = torch.rand(h, w, 3, generator=g, dtype=torch.float64)
    keep = torch.rand(h, w, generator=g) > 0.3
    return pred, gt, keep


def test_ignore_loss_and_gradient_do_not_see_masked_pixels():
    pred, gt, keep = _pair()
    other = gt.clone()
    other[~keep] = torch.rand(int((~keep).sum()), 3, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    losses, grads = [], []
    for target in (gt, other):
        p = pred.clone().requires_grad_(True)
        loss = photometric_loss(p, target, 0.2, keep)
        loss.backward()
        losses.append(loss.detach())
        grads.append(p.grad)
    assert losses[0] == losses[1]  # exactly: masked pixels enter as zeros
    assert torch.equal(grads[0], grads[1])
    assert (grads[0][~keep] == 0).all() and (grads[0][keep] != 0).any()
    # and unmasked pixels do matter
    worse = gt.clone()
    worse[keep] = 1 - worse[keep]
    assert photometric_loss(pred, worse, 0.2, keep) != losses[0]


def test_an_all_keep_mask_is_the_plain_loss_and_metrics():
    pred, gt, _ = _pair(1)
    keep = torch.ones(pred.shape[:2], dtype=torch.bool)
    # float64 sums in another order: equal to rounding
    torch.testing.assert_close(photometric_loss(pred, gt, 0.2, keep), photometric_loss(pred, gt, 0.2))
    torch.testing.assert_close(psnr(pred, gt, keep), psnr(pred, gt))
    torch.testing.assert_close(ssim(pred, gt, keep), ssim(pred, gt))


def test_masked_psnr_is_over_kept_pixels():
    pred, gt, keep = _pair(2)
    mse = ((pred - gt) ** 2)[keep].mean()
    torch.testing.assert_close(psnr(pred, gt, keep), 10 * torch.log10(1 / mse))


def test_background_mode_paints_masked_pixels_and_ignore_keeps_masks(processed):
    cpu = torch.device("cpu")
    off = load_train_data(processed, 2.0, None, cpu, mask_mode="off")
    bgm = load_train_data(processed, 2.0, None, cpu, mask_mode="background")
    ign = load_train_data(processed, 2.0, None, cpu, mask_mode="ignore")
    assert (off.mask_mode, bgm.mask_mode, ign.mask_mode) == ("off", "background", "ignore")
    for a, b, c in zip(off.train, bgm.train, ign.train):
        assert a.keep is None and b.keep is None and c.keep is not None
        keep = torch.from_numpy(load_mask(processed.mask_path(a.camera.name), (a.camera.width, a.camera.height)))
        assert torch.equal(c.keep, keep)
        assert torch.equal(b.image[keep], a.image[keep])
        assert (b.image[~keep] == 0).all()  # the scene background is black
        assert torch.equal(c.image, a.image)
        coarse = c.at_scale(0.5)  # the coarse level carries its mask
        assert coarse.keep is not None and coarse.keep.shape == coarse.image.shape[:2]


def test_eval_scores_only_unmasked_pixels_and_says_so(tmp_path):
    proj = make_tiny_project(tmp_path / "p")
    names = proj.splits()["test"]
    proj.masks_dir.mkdir()
    for cam_name in json.loads(json.dumps(names)) + proj.splits()["train"]:
        m = np.full((40, 48), 255, np.uint8)
        m[:, :20] = 0
        cv2.imwrite(str(proj.mask_path(cam_name)), m)
    proj.update_manifest(scene={**proj.manifest()["scene"], "masks": True, "mask_source": "files"})
    step = proj.step("train")
    proj.record_step("train", config=step["config"], summary={**step["summary"], "mask_mode": "ignore"})
    r1 = run_cli("eval", proj.root, "--json", "--budgets", "1", "--no-plots")
    assert r1.exit_code == 0, r1.output
    first = json.loads(r1.stdout)
    assert first["masks"].startswith("unmasked pixels only")
    assert "Masks: scored on unmasked pixels only" in proj.eval_md_path.read_text()
    for n in names:  # spoil the masked half of every photograph: the scores do not move
        img = cv2.imread(str(proj.images_dir / n))
        img[:, :20] = 255 - img[:, :20]
        cv2.imwrite(str(proj.images_dir / n), img)
    second = json.loads(run_cli("eval", proj.root, "--json", "--budgets", "1", "--no-plots").stdout)
    assert second["psnr"] == first["psnr"] and second["ssim"] == first["ssim"]
    proj.record_step("train", config=step["config"], summary={**step["summary"], "mask_mode": "off"})
    third = json.loads(run_cli("eval", proj.root, "--json", "--budgets", "1", "--no-plots").stdout)
    assert third["masks"] is None and third["psnr"] < first["psnr"] - 3


def test_train_refuses_an_unknown_mask_mode(tmp_path):
    proj = make_tiny_project(tmp_path / "p", trained=False, photos=False)
    assert_user_error(run_cli("train", proj.root, "--mask-mode", "blur"), "--mask-mode 'blur'", "ignore")
