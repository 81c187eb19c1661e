"""Importing existing poses: COLMAP workspaces and transforms.json, end to end.

Models come from `pycolmap.synthesize_dataset` (via tests/colmap_models.py)
or are written by hand; images are random textures of the right size. No
structure from motion runs here, so every test takes well under a second.
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from colmap_models import synthetic_model
from splatcli.errors import SplatError
from splatcli.inputs.llff import to_poses_bounds
from splatcli.process.run import ProcessConfig, process
from splatcli.project import Project
from splatcli.sfm import colmap
from splatcli.sfm.colmap import read_scene
from support.tiny_project import assert_user_error, make_tiny_project, run_cli
from test_sfm import gl_c2w, orbit, texture, write_text_model


def make_workspace(root: Path, *, camera_model: str = "PINHOLE", text: bool = False, num_cameras: int = 1,
                   num_images: int = 5, size: tuple[int, int] = (64, 48)) -> colmap.Model:
    """root/images/<name> + root/sparse/0 (a synthetic model)."""
    model = synthetic_model(num_images=num_images, camera_model=camera_model, width=size[0], height=size[1],
                            num_cameras=num_cameras)
    (root / "images").mkdir(parents=True)
    for i, name in enumerate(model.registered_names()):
        cv2.imwrite(str(root / "images" / name), texture(size[1], size[0], seed=i))
    model.write(root / "sparse" / "0", text=text)
    return model


def tree_digest(root: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(root.rglob("*")):
        h.update(str(p.relative_to(root)).encode())
        if p.is_file():
            h.update(p.read_bytes())
    return h.hexdigest()


def assert_contract(project: Path) -> dict:
    """What every later command relies on (see process.py's docstring)."""
    proj = Project.open(project)
    proj.require_processed()
    scene = read_scene(proj.sparse_dir)
    assert proj.manifest()["scene"]["model_sha256"] == colmap.model_digest(proj.sparse_dir)  # later reads skip the walk
    names = sorted(p.relative_to(proj.images_dir).as_posix() for p in proj.images_dir.rglob("*") if p.is_file())
    assert [c.name for c in scene.cameras] == names
    for c in scene.cameras:
        img = cv2.imread(str(proj.images_dir / c.name))
        assert img.shape[:2] == (c.height, c.width)
        assert c.K[0, 1] == 0 and c.K[2, 2] == 1
    m = proj.manifest()
    splits = m["splits"]
    assert sorted(splits["train"] + splits["test"]) == names and not set(splits["train"]) & set(splits["test"])
    sc = m["scene"]
    assert {"has_points", "init", "background", "bounds_min", "bounds_max"} <= set(sc)
    assert sc["has_points"] == (len(scene.points) > 0)
    assert sc["init"] == ("sfm" if sc["has_points"] else "random")
    assert all(lo < hi for lo, hi in zip(sc["bounds_min"], sc["bounds_max"]))
    assert (proj.process_report_path).is_file()
    assert not (project / ".process-tmp").exists()
    return m


# ---- COLMAP workspaces ---------------------------------------------------------


@pytest.mark.parametrize("text", [False, True], ids=["bin", "txt"])
def test_import_pinhole_colmap_keeps_poses_and_points(tmp_path, text):
    ws = tmp_path / "ws"
    model = make_workspace(ws, text=text)
    r = process(ws, tmp_path / "p")
    assert r.input_kind == "colmap" and r.registered == 5 and r.points == 50 and not r.undistorted
    m = assert_contract(tmp_path / "p")
    assert m["scene"]["init"] == "sfm" and m["splits"]["test"] == [sorted(model.registered_names())[0]]
    got = read_scene(Project(tmp_path / "p").sparse_dir)
    for a, b in zip(got.cameras, model.cameras()):
        np.testing.assert_allclose(a.viewmat, b.viewmat, atol=1e-9)
        np.testing.assert_allclose(a.K, b.K, atol=1e-9)
    assert not (tmp_path / "p" / "sfm" / "distorted").exists()
    r = process(ws / "sparse" / "0", tmp_path / "q")  # the model given as its own folder
    assert r.input_kind == "colmap" and r.registered == 5
    with pytest.raises(SplatError, match="no transforms.json"):
        process(ws, tmp_path / "forced", ProcessConfig(input_type="transforms"))


def test_import_distorted_colmap_with_two_cameras_is_undistorted(tmp_path):
    ws = tmp_path / "ws"
    model = make_workspace(ws, camera_model="OPENCV", num_cameras=2, num_images=3)
    r = process(ws, tmp_path / "p")
    assert r.undistorted and r.registered == 6
    assert_contract(tmp_path / "p")
    proj = Project(tmp_path / "p")
    assert (proj.distorted_dir / "cameras.bin").is_file()
    got = read_scene(proj.sparse_dir)
    for a, b in zip(got.cameras, model.cameras()):  # undistortion keeps poses
        np.testing.assert_allclose(a.viewmat, b.viewmat, atol=1e-9)


def test_undistorted_images_are_colmaps_own_to_interpolation(tmp_path):
    """The images are resampled here through one pixel map per camera (COLMAP still writes the model and
    one image): the same cameras, and the same pictures as COLMAP's undistorter up to bilinear weights
    (OpenCV's are on a 1/32 px grid; real photos: 46 dB apart before JPEG)."""
    import pycolmap

    ws = tmp_path / "ws"
    model = make_workspace(ws, camera_model="OPENCV", num_cameras=2, num_images=2, size=(96, 64))
    names = model.registered_names()
    for i, name in enumerate(names):  # smooth pictures: noise blurred
        cv2.imwrite(str(ws / "images" / name), cv2.GaussianBlur(texture(64, 96, seed=i), (0, 0), 2.0))
    done = []
    sparse = colmap.undistort(model, ws / "images", tmp_path / "ours", jpeg_quality=100, on_progress=done.append)
    assert done[-1] == len(names)
    uo = pycolmap.UndistortCameraOptions()
    uo.blank_pixels = 0.0
    pycolmap.undistort_images(str(tmp_path / "theirs"), str(tmp_path / "ours" / "_in"), str(ws / "images"),
                              output_type="COLMAP", undistort_options=uo, jpeg_quality=100)
    ours, theirs = read_scene(sparse), read_scene(tmp_path / "theirs" / "sparse")
    assert [c.name for c in ours.cameras] == names
    for a, b in zip(ours.cameras, theirs.cameras):
        np.testing.assert_array_equal(a.K, b.K)
        mine, ref = (cv2.imread(str(d / "images" / a.name)).astype(float) for d in (tmp_path / "ours", tmp_path / "theirs"))
        assert mine.shape == ref.shape == (a.height, a.width, 3)
        assert 10 * math.log10(255**2 / max(((mine - ref) ** 2).mean(), 1e-9)) > 40.0, a.name


def test_import_distorted_rgba_images_undistorts_masks_too(tmp_path):
    ws = tmp_path / "ws"
    model = make_workspace(ws, camera_model="OPENCV", num_images=4)
    names = model.registered_names()
    for i, name in enumerate(names[:-1]):  # the last image stays RGB: it gets an opaque mask
        alpha = np.full((48, 64), 255, np.uint8)
        alpha[:, :20] = 0
        cv2.imwrite(str(ws / "images" / name), np.dstack([texture(48, 64, seed=i), alpha]))
    r = process(ws, tmp_path / "p")
    assert r.masks and r.undistorted
    m = assert_contract(tmp_path / "p")
    assert m["scene"]["background"] == [1.0, 1.0, 1.0]
    proj = Project(tmp_path / "p")
    for c in read_scene(proj.sparse_dir).cameras:
        mask = cv2.imread(str(proj.mask_path(c.name)), cv2.IMREAD_UNCHANGED)
        assert mask.shape == (c.height, c.width)
        if c.name == names[-1]:
            assert mask.min() == 255
        else:
            assert mask[:, :10].max() < 128 and mask[:, -10:].min() > 128
            img = cv2.imread(str(proj.images_dir / c.name))
            assert img[c.height // 2, 2].min() > 200  # composited over white


def test_import_keeps_full_resolution_whatever_max_size(tmp_path):
    """--max-size caps what SIFT sees; imported datasets are never resampled."""
    ws = tmp_path / "ws"
    model = make_workspace(ws, size=(128, 96))
    process(ws, tmp_path / "p", ProcessConfig(max_size=64))
    got = read_scene(Project(tmp_path / "p").sparse_dir)
    for a, b in zip(got.cameras, model.cameras()):
        assert (a.width, a.height) == (128, 96)
        np.testing.assert_allclose(a.K, b.K, atol=1e-9)


def test_import_skips_missing_images_with_a_warning(tmp_path):
    ws = tmp_path / "ws"
    model = make_workspace(ws)
    gone = model.registered_names()[1]
    (ws / "images" / gone).unlink()
    notes = []
    r = process(ws, tmp_path / "p", on_event=notes.append)
    assert r.registered == 4
    assert gone not in [c.name for c in read_scene(Project(tmp_path / "p").sparse_dir).cameras]
    assert any("1 image(s) of the model are missing" in getattr(n, "message", "") for n in notes)
    assert_contract(tmp_path / "p")


# ---- transforms.json -------------------------------------------------------------


def blender_scene(root: Path, n_train: int = 6, n_test: int = 2) -> None:
    """RGBA PNGs without extension in file_path, camera_angle_x, train/test files."""
    cams = orbit(n_train + n_test)
    for split, sub in (("train", cams[:n_train]), ("test", cams[n_train:])):
        (root / split).mkdir(parents=True)
        frames = []
        for i, c in enumerate(sub):
            rgb = texture(48, 64, seed=i)
            alpha = np.zeros((48, 64), np.uint8)
            alpha[10:40, 16:48] = 255
            cv2.imwrite(str(root / split / f"r_{i}.png"), np.dstack([rgb, alpha]))
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": gl_c2w(c.viewmat)})
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": 0.9, "frames": frames}))


def test_import_blender_scene_composites_over_white_or_black_and_keeps_masks(tmp_path):
    blender_scene(tmp_path / "lego")
    r = process(tmp_path / "lego", tmp_path / "p")
    assert r.input_kind == "transforms" and r.registered == 8 and r.points == 0 and r.masks
    m = assert_contract(tmp_path / "p")
    assert m["scene"]["background"] == [1.0, 1.0, 1.0] and m["scene"]["init"] == "random"
    # train_r_0 / test_r_0 collide by base name, so names carry the folder.
    assert m["splits"]["test"] == ["test_r_0.png", "test_r_1.png"]
    proj = Project(tmp_path / "p")
    img = cv2.imread(str(proj.images_dir / "train_r_0.png"))
    assert (img[0, 0] == 255).all()  # transparent -> white background
    assert sorted(p.name for p in proj.masks_dir.iterdir()) == [n + ".png" for n in sorted(m["splits"]["train"]
                                                                                         + m["splits"]["test"])]
    mask = cv2.imread(str(proj.mask_path("train_r_0.png")), cv2.IMREAD_UNCHANGED)
    assert mask.shape == (48, 64) and mask[0, 0] == 0 and mask[20, 20] == 255
    K = read_scene(proj.sparse_dir).cameras[0].K
    assert K[0, 0] == pytest.approx(32 / math.tan(0.45)) and K[0, 2] == 32
    process(tmp_path / "lego", tmp_path / "black", ProcessConfig(background=(0.0, 0.0, 0.0)))
    black = Project(tmp_path / "black")
    assert black.manifest()["scene"]["background"] == [0.0, 0.0, 0.0]
    assert (cv2.imread(str(black.images_dir / "train_r_0.png"))[0, 0] == 0).all()


def test_import_nerfstudio_with_distortion_and_missing_files(tmp_path):
    root = tmp_path / "ns"
    (root / "images").mkdir(parents=True)
    cams = orbit(6, w=96, h=72, f=80.0)
    frames = []
    for i, c in enumerate(cams):
        if i != 2:  # listed but absent
            cv2.imwrite(str(root / "images" / f"f{i}.jpg"), texture(72, 96, seed=i))
        frames.append({"file_path": f"images/f{i}.jpg", "transform_matrix": gl_c2w(c.viewmat)})
    (root / "transforms.json").write_text(json.dumps({
        "fl_x": 80.0, "fl_y": 80.0, "cx": 48.0, "cy": 36.0, "w": 96, "h": 72, "k1": -0.05, "k2": 0.01,
        "p1": 0.0, "p2": 0.0, "frames": frames}))
    notes = []
    r = process(root / "transforms.json", tmp_path / "p", on_event=notes.append)
    assert r.registered == 5 and r.total == 6 and r.missing == 1 and r.undistorted
    assert any("1 image(s) listed" in getattr(n, "message", "") and n.level == "warning" for n in notes)
    m = assert_contract(tmp_path / "p")
    assert m["scene"]["background"] == [0.0, 0.0, 0.0]
    got = {c.name: c for c in read_scene(Project(tmp_path / "p").sparse_dir).cameras}
    for i, c in enumerate(cams):
        if i != 2:
            np.testing.assert_allclose(got[f"f{i}.jpg"].viewmat, c.viewmat, atol=1e-9)


@pytest.mark.data
def test_lego_imports_when_the_data_is_present(shared_data, tmp_path):
    lego = shared_data / "lego"
    if not (lego / "transforms_train.json").is_file():
        pytest.skip("lego absent")
    r = process(lego, tmp_path / "p")
    assert r.registered == 100 and r.test == 13 and r.masks
    assert r.init == "sfm" and r.points == r.triangulated > 1000  # the object has texture enough (the alpha masks the rest)
    assert r.mean_reprojection_error < 1.5
    m = assert_contract(tmp_path / "p")
    lo, hi = np.array(m["scene"]["bounds_min"]), np.array(m["scene"]["bounds_max"])
    # the box of the points: the model itself (about 1.3 x 2.3 x 1.3 around the origin), not the empty space
    assert (lo > -2.5).all() and (hi < 2.5).all() and (lo < 0).all() and (hi > 0).all() and (hi - lo).min() > 1.0


# ---- failures: exit 2, one line naming the file, nothing changed ----------------------


def bad_transforms(root: Path, case: str) -> Path:
    root.mkdir(parents=True)
    cv2.imwrite(str(root / "a.png"), texture())
    cam = orbit(1)[0]
    frame = {"file_path": "a.png", "transform_matrix": gl_c2w(cam.viewmat)}
    content = {
        "not_json": "{ this is not json",
        "no_frames": json.dumps({"camera_angle_x": 0.8}),
        "no_focal": json.dumps({"frames": [frame]}),
        "no_matrix": json.dumps({"camera_angle_x": 0.8, "frames": [{"file_path": "a.png"}]}),
        "missing_files": json.dumps({"camera_angle_x": 0.8, "frames": [{**frame, "file_path": "gone.png"}]}),
        "escape": json.dumps({"camera_angle_x": 0.8, "frames": [{**frame, "file_path": "../../secret.png"}]}),
        "absolute": json.dumps({"camera_angle_x": 0.8, "frames": [{**frame, "file_path": "/etc/hostname"}]}),
    }[case]
    (root / "transforms.json").write_text(content)
    return root / "transforms.json"


@pytest.mark.parametrize("case, needle", [
    ("not_json", "not valid JSON"), ("no_frames", "no `frames`"), ("no_focal", "no focal length"),
    ("no_matrix", "transform_matrix"), ("missing_files", "none of the 1 listed images exists"),
    ("escape", "outside the input folder"), ("absolute", "outside the input folder"),
])
def test_bad_transforms_fail_cleanly(tmp_path, case, needle):
    tf = bad_transforms(tmp_path / "in", case)
    r = run_cli("process", tf, "-o", tmp_path / "p")
    assert_user_error(r, str(tf), needle)
    assert not (tmp_path / "p").exists()


@pytest.mark.parametrize("damage, needle", [
    ("missing_images_bin", "images.bin: missing"), ("garbled_images_bin", "images.bin"),
    ("garbled_points_bin", "points3D.bin"), ("truncated_cameras_bin", "cameras.bin"),
    ("escaping_name", "outside the images folder"),
])
def test_bad_colmap_models_fail_cleanly_and_leave_the_project_alone(tmp_path, damage, needle):
    good = tmp_path / "good"
    make_workspace(good)
    assert run_cli("process", good, "-o", tmp_path / "p").exit_code == 0
    before = tree_digest(tmp_path / "p")
    ws = tmp_path / "ws"
    if damage == "escaping_name":
        write_text_model(ws / "sparse" / "0", orbit(3))
        t = (ws / "sparse" / "0" / "images.txt")
        t.write_text(t.read_text().replace("001.png", "/etc/001.png"))
        (ws / "images").mkdir()
    else:
        make_workspace(ws)
        d = ws / "sparse" / "0"
        if damage == "missing_images_bin":
            (d / "images.bin").unlink()
        elif damage == "garbled_images_bin":
            data = bytearray((d / "images.bin").read_bytes())
            data[8:200] = bytes(range(192))
            (d / "images.bin").write_bytes(bytes(data))
        elif damage == "garbled_points_bin":
            (d / "points3D.bin").write_bytes((d / "points3D.bin").read_bytes()[:8] + b"\xff" * 500)
        else:
            (d / "cameras.bin").write_bytes((d / "cameras.bin").read_bytes()[:20])
    r = run_cli("process", ws, "-o", tmp_path / "p", "--overwrite")
    assert_user_error(r, needle)
    assert tree_digest(tmp_path / "p") == before


def test_output_rules(tmp_path):
    ws = tmp_path / "ws"
    make_workspace(ws)
    other = tmp_path / "other"
    other.mkdir()
    (other / "keep.txt").write_text("mine")
    assert_user_error(run_cli("process", ws, "-o", other), str(other), "--overwrite")
    assert (other / "keep.txt").read_text() == "mine"
    assert_user_error(run_cli("process", ws, "-o", ws), "holds the input")
    assert run_cli("process", ws, "-o", tmp_path / "p").exit_code == 0
    assert_user_error(run_cli("process", ws, "-o", tmp_path / "p"), "already holds a processed dataset")
    r = run_cli("process", ws, "-o", tmp_path / "p", "--overwrite", "--json")
    assert r.exit_code == 0 and json.loads(r.stdout)["registered"] == 5


def test_bad_options_are_one_line_errors(tmp_path):
    ws = tmp_path / "ws"
    make_workspace(ws)
    for args, needle in ((["--matcher", "magic"], "--matcher"), (["--background", "teal"], "--background"),
                         (["--max-size", "4"], "--max-size"), (["--input-type", "photos"], "--input-type")):
        assert_user_error(run_cli("process", ws, "-o", tmp_path / "p", *args), needle)
    assert not (tmp_path / "p").exists()


def test_a_model_we_wrote_is_not_walked_again(tmp_path, monkeypatch):
    """The model `process` wrote and recorded (by digest) is read without the file walk;
    a model changed since then is walked again."""
    proj = make_tiny_project(tmp_path / "p", trained=False)
    scene = proj.manifest()["scene"]
    proj.update_manifest(scene={**scene, "model_sha256": colmap.model_digest(proj.sparse_dir)})
    walked = []
    real = colmap.check_model
    monkeypatch.setattr(colmap, "check_model", lambda d: walked.append(d) or real(d))
    cams = colmap.read_project_scene(proj).cameras
    assert walked == [] and len(cams) == len(proj.splits()["train"]) + len(proj.splits()["test"])
    proj.update_manifest(scene={**scene, "model_sha256": "0" * 64})
    assert [c.name for c in colmap.read_project_scene(proj).cameras] == [c.name for c in cams]
    assert walked == [proj.sparse_dir]


# ---- LLFF poses_bounds.npy ---------------------------------------------------------


def llff_capture(root: Path, *, n: int = 5, factor: int = 1, size: tuple[int, int] = (64, 48),
                 bounds: tuple[float, float] = (2.0, 6.0)) -> list:
    """root/images[_factor]/NNN.png (random textures) + poses_bounds.npy written from an
    orbit's cameras, its (h, w, f) at `factor` x the images' size as LLFF stores them."""
    cams = orbit(n, w=size[0], h=size[1])
    folder = root / ("images" if factor == 1 else f"images_{factor}")
    folder.mkdir(parents=True)
    for i, c in enumerate(cams):
        cv2.imwrite(str(folder / c.name), texture(size[1], size[0], seed=i))
    rows = to_poses_bounds([c.viewmat for c in cams],
                           [(c.height * factor, c.width * factor, c.K[0, 0] * factor) for c in cams], [bounds] * n)
    np.save(root / "poses_bounds.npy", rows)
    return cams


def test_llff_poses_convert_exactly_and_images_n_scale_the_focal_length(tmp_path):  # given as folder or file
    cams = llff_capture(tmp_path / "fern", factor=4)
    notes = []
    r = process(tmp_path / "fern", tmp_path / "p", ProcessConfig(triangulate=False), on_event=notes.append)
    assert r.input_kind == "llff" and r.registered == 5 and r.init == "random" and not r.undistorted
    assert any("images read from images_4/" in getattr(n, "message", "") for n in notes)
    m = assert_contract(tmp_path / "p")
    got = read_scene(Project(tmp_path / "p").sparse_dir).cameras
    for a, b in zip(got, cams):
        assert a.name == b.name
        np.testing.assert_allclose(a.viewmat, b.viewmat, atol=1e-9)
        np.testing.assert_allclose(a.K, b.K, atol=1e-9)  # f / 4 for images_4, principal point at the centre
    # The scene box comes from the near/far bounds: around the orbit's centre, between 2 and 6 deep.
    lo, hi = np.array(m["scene"]["bounds_min"]), np.array(m["scene"]["bounds_max"])
    assert (lo < 0).all() and (hi > 0).all() and (hi - lo).max() < 12
    r = process(tmp_path / "fern" / "poses_bounds.npy", tmp_path / "q", ProcessConfig(triangulate=False))  # the file
    assert r.input_kind == "llff" and r.registered == 5
    with pytest.raises(SplatError, match="no poses_bounds.npy here"):
        process(tmp_path / "fern" / "images_4", tmp_path / "forced", ProcessConfig(input_type="llff"))
