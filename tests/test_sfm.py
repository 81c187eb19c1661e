"""Unit tests of splatcli/sfm: parsers, validators, alignment, bounds, pairing, image checks.

Fast: no structure from motion runs here (see test_process.py for that).
"""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from splatcli.camera import Camera, focus_point
from splatcli.errors import SplatError
from splatcli.inputs.images import ImageError, check_complete, exif_orientation, fit_size, read_image
from splatcli.inputs.transforms import read_transforms
from splatcli.process.bounds import frustum_bounds, points_bounds
from splatcli.process.detect import detect_input
from splatcli.process.video import blurry_frames, choose_frames
from splatcli.sfm.colmap_files import check_model
from splatcli.sfm.reconstruct import (
    FOCAL_SPREAD,
    SfmOptions,
    _focal_spread,
    choose_matcher,
    exhaustive_pairs,
    looks_ordered,
    natural_key,
    sequential_pairs,
)
from splatcli.sfm.retrieval import retrieval_pairs
from support.align import compare_poses, umeyama


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:  # [4, 4] world-to-camera, OpenCV axes
    eye, target, up = (np.asarray(v, float) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    v = np.eye(4)
    v[:3, :3] = R
    v[:3, 3] = -R @ eye
    return v


def orbit(n: int = 12, radius: float = 4.0, w: int = 64, h: int = 48, f: float = 60.0) -> list[Camera]:
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
    cams = []
    for i in range(n):
        a = 2 * math.pi * i / n
        eye = (radius * math.cos(a), radius * math.sin(a), 1.0 + 0.3 * math.sin(3 * a))
        cams.append(Camera(f"{i:03d}.png", w, h, K, look_at(eye, (0, 0, 0))))
    return cams


# ---- alignment -----------------------------------------------------------------


def rot(axis, deg) -> np.ndarray:  # [3, 3]
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return cv2.Rodrigues(axis * math.radians(deg))[0]


def test_umeyama_recovers_a_similarity():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 3))
    R, s, t = rot([1, 2, 3], 40), 2.5, np.array([1.0, -2.0, 0.5])
    dst = s * src @ R.T + t
    sim = umeyama(src, dst)
    np.testing.assert_allclose(sim.R, R, atol=1e-10)
    assert sim.scale == pytest.approx(s, rel=1e-10)
    np.testing.assert_allclose(sim.apply(src), dst, atol=1e-10)


def test_compare_poses_is_invariant_to_a_similarity_and_sees_errors():
    ref = orbit()
    R, s, t = rot([0, 1, 1], 70), 0.3, np.array([5.0, 1.0, -2.0])
    # Move the world: x' = s R x + t. A camera's world-to-camera becomes [R_c R^T | s t_c - R_c R^T t].
    moved = []
    for c in ref:
        v = np.eye(4)
        v[:3, :3] = c.viewmat[:3, :3] @ R.T
        v[:3, 3] = s * c.viewmat[:3, 3] - v[:3, :3] @ t
        moved.append(Camera(c.name, c.width, c.height, c.K, v))
    e = compare_poses(moved, ref)
    assert e.max_rotation_deg < 1e-6 and e.max_center_error_rel < 1e-9
    # Perturb one camera's rotation by 2 degrees: exactly that error shows.
    bad = list(moved)
    v = bad[3].viewmat.copy()
    v[:3, :3] = rot([0, 0, 1], 2.0) @ v[:3, :3]
    v[:3, 3] = rot([0, 0, 1], 2.0) @ v[:3, 3]  # same centre
    bad[3] = Camera(bad[3].name, 64, 48, bad[3].K, v)
    e = compare_poses(bad, ref)
    assert e.rotation_deg[3] == pytest.approx(2.0, abs=1e-6)
    assert e.max_center_error_rel < 1e-9


# ---- bounds ----------------------------------------------------------------------


def test_focus_and_frustum_bounds_of_an_orbit_surround_the_target():
    cams = orbit()
    f = focus_point(cams)
    assert f is not None and np.linalg.norm(f) < 0.1
    lo, hi = frustum_bounds(cams)
    assert (lo < 0).all() and (hi > 0).all()
    assert (hi - lo).max() < 8.0  # inside the orbit, not around the cameras


def test_frustum_bounds_of_forward_facing_cameras_lie_ahead():
    K = np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])
    cams = [Camera(f"{i}.png", 64, 48, K, look_at((0.1 * i, 0, 0), (0.1 * i, 0, 10), up=(0, -1, 0))) for i in range(5)]
    assert focus_point(cams) is None  # parallel axes
    lo, hi = frustum_bounds(cams)
    assert lo[2] > 0 and hi[2] > lo[2]  # in front of the cameras (+z)


def test_points_bounds_ignore_outliers():
    rng = np.random.default_rng(0)
    pts = np.concatenate([rng.uniform(-1, 1, size=(2000, 3)), [[1000.0, 1000.0, 1000.0]]])
    lo, hi = points_bounds(pts)
    assert (hi < 1.01).all() and (lo > -1.01).all()


# ---- pairs and ordering -----------------------------------------------------------


def test_pairs():
    names = [f"{i:03d}.jpg" for i in range(40)]
    ex = exhaustive_pairs(names)
    assert len(ex) == 40 * 39 // 2
    seq = sequential_pairs(names, 5)
    assert len(set(seq)) == len(seq) and set(seq) <= set(ex)
    idx = {(names.index(a), names.index(b)) for a, b in seq}
    assert (0, 5) in idx and (0, 6) not in idx and (0, 8) in idx and (0, 32) in idx  # neighbours + 2^k loop pairs


def test_ordered_names_and_natural_sort():
    assert looks_ordered(["IMG_0001.JPG", "IMG_0002.JPG", "IMG_0010.JPG"])
    assert not looks_ordered(["a.jpg", "b.jpg", "c.jpg"])
    assert not looks_ordered(["IMG_1.jpg", "DSC_2.jpg", "IMG_3.jpg"])
    assert sorted(["f10.png", "f9.png", "f100.png"], key=natural_key) == ["f9.png", "f10.png", "f100.png"]


def test_retrieval_pairs_each_image_with_those_that_share_its_features():
    """Three places, each photographed 8 times: a photo's features are its place's plus noise. Each
    image's 7 most alike are the rest of its place, so no pair crosses places, and the count is
    n k / 2 here, not n (n - 1) / 2."""
    rng = np.random.default_rng(0)
    places = [rng.integers(0, 256, size=(300, 128)) for _ in range(3)]
    names, descs = [], []
    for p, feats in enumerate(places):
        for v in range(8):
            keep = feats[rng.random(len(feats)) < 0.7]
            descs.append(np.clip(keep + rng.normal(0, 8, keep.shape), 0, 255).astype(np.uint8))
            names.append(f"{p}-{v}.jpg")
    order = rng.permutation(len(names))  # the names say nothing about the order
    names, descs = [names[i] for i in order], [descs[i] for i in order]
    pairs = retrieval_pairs(names, descs, k=7)
    assert all(a[0] == b[0] for a, b in pairs), [pq for pq in pairs if pq[0][0] != pq[1][0]]
    assert len(pairs) == 3 * 8 * 7 // 2 and len(set(pairs)) == len(pairs)
    assert all(names.index(a) < names.index(b) for a, b in pairs)
    assert retrieval_pairs(names[:1], descs[:1], k=7) == []
    empty = [np.zeros((0, 128), np.uint8)] * 3  # no features at all: still pairs, no error
    assert len(retrieval_pairs(["a", "b", "c"], empty, k=1)) >= 2


def test_auto_pairs_unordered_names_above_the_exhaustive_limit_by_retrieval():
    opts = SfmOptions()
    few = [f"{c}.jpg" for c in "abcdefghij"]
    many = [f"photo-{i:x}{i * 7919 % 97}.jpg" for i in range(opts.exhaustive_max_images + 1)]
    assert choose_matcher(opts, few) == "exhaustive"
    assert choose_matcher(opts, many) == "retrieval"
    assert choose_matcher(opts, [f"IMG_{i:04d}.JPG" for i in range(60)]) == "sequential"


# ---- video helpers -----------------------------------------------------------------


def test_choose_frames():
    assert choose_frames(100, 30.0, every_fps=None, num_frames=5) == [0, 25, 50, 74, 99]
    assert choose_frames(90, 30.0, every_fps=2.0, num_frames=None) == list(range(0, 90, 15))
    assert choose_frames(3, 30.0, every_fps=None, num_frames=10) == [0, 1, 2]


def test_blurry_frames_are_those_far_below_their_neighbours():
    scores = [100.0, 105, 98, 20, 101, 99, 103, 97, 30, 100]
    assert blurry_frames(scores) == [3, 8]
    assert blurry_frames([10.0] * 12) == []  # a uniformly soft video keeps every frame


# ---- images ----------------------------------------------------------------------


def texture(h: int = 48, w: int = 64, seed: int = 0) -> np.ndarray:  # [H, W, 3] uint8
    return np.random.default_rng(seed).integers(0, 256, size=(h, w, 3), dtype=np.uint8)


def jpeg_bytes(img: np.ndarray) -> bytes:
    return cv2.imencode(".jpg", img)[1].tobytes()


def with_exif_orientation(jpeg: bytes, orientation: int) -> bytes:
    """Insert an APP1 Exif segment holding only the orientation tag."""
    tiff = b"II*\x00" + struct.pack("<I", 8) + struct.pack("<H", 1)
    tiff += struct.pack("<HHIHH", 0x0112, 3, 1, orientation, 0) + struct.pack("<I", 0)
    payload = b"Exif\x00\x00" + tiff
    app1 = b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload
    return jpeg[:2] + app1 + jpeg[2:]


def test_truncated_jpeg_and_png_are_refused(tmp_path):
    img = texture()
    jpg = jpeg_bytes(img)
    png = cv2.imencode(".png", img)[1].tobytes()
    check_complete(jpg, ".jpg")
    check_complete(png, ".png")
    with pytest.raises(ImageError, match="truncated JPEG"):
        check_complete(jpg[: len(jpg) * 2 // 3], ".jpg")
    with pytest.raises(ImageError, match="truncated PNG"):
        check_complete(png[: len(png) // 2], ".png")
    (tmp_path / "x.jpg").write_bytes(b"not an image at all")
    with pytest.raises(ImageError):
        read_image(tmp_path / "x.jpg", orient=True)


def test_exif_orientation_is_applied_only_when_asked(tmp_path):
    img = texture(48, 64)
    p = tmp_path / "r.jpg"
    p.write_bytes(with_exif_orientation(jpeg_bytes(img), 6))  # 6: rotate 90 degrees clockwise to view
    rotated, alpha, changed = read_image(p, orient=True)
    assert rotated.shape == (64, 48, 3) and changed and alpha is None
    raw, _, changed = read_image(p, orient=False)
    assert raw.shape == (48, 64, 3) and not changed
    p.write_bytes(with_exif_orientation(jpeg_bytes(img), 1))  # upright: copied as is
    assert exif_orientation(p.read_bytes()) == 1
    assert not read_image(p, orient=True)[2]
    assert exif_orientation(jpeg_bytes(img)) is None


def test_rgba_png_gives_alpha_and_grey_gives_three_channels(tmp_path):
    rgba = np.dstack([texture(), np.full((48, 64), 128, np.uint8)])
    cv2.imwrite(str(tmp_path / "a.png"), rgba)
    img, alpha, changed = read_image(tmp_path / "a.png", orient=False)
    assert img.shape == (48, 64, 3) and alpha is not None and alpha.max() == 128 and changed
    cv2.imwrite(str(tmp_path / "g.png"), texture()[..., 0])
    img, alpha, _ = read_image(tmp_path / "g.png", orient=False)
    assert img.shape == (48, 64, 3) and alpha is None


def test_fit_size():
    assert fit_size(1080, 1920, 711) == (400, 711)
    assert fit_size(100, 50, 1600) == (100, 50)


# ---- transforms.json --------------------------------------------------------------


def write_transforms(folder: Path, frames: list[dict], name: str = "transforms.json", **top) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    p = folder / name
    p.write_text(json.dumps({**top, "frames": frames}))
    return p


def gl_c2w(viewmat: np.ndarray) -> list:
    """Our world-to-camera (OpenCV) as an OpenGL camera-to-world matrix."""
    c2w = np.linalg.inv(viewmat)
    return (c2w @ np.diag([1.0, -1.0, -1.0, 1.0])).tolist()


def test_transforms_pose_conversion_and_blender_intrinsics(tmp_path):
    cams = orbit(4)
    (tmp_path / "train").mkdir()
    for c in cams:
        cv2.imwrite(str(tmp_path / "train" / c.name), texture())
    frames = [{"file_path": f"./train/{Path(c.name).stem}", "transform_matrix": gl_c2w(c.viewmat)} for c in cams]
    tf = write_transforms(tmp_path, frames, "transforms_train.json", camera_angle_x=0.8)
    scene = read_transforms(tf)
    assert [f.name for f in scene.frames] == sorted(c.name for c in cams)  # extension resolved
    for f, c in zip(scene.frames, sorted(cams, key=lambda c: c.name)):
        np.testing.assert_allclose(f.viewmat, c.viewmat, atol=1e-12)
        model, params = f.intrinsics.resolve(64, 48, "x")
        assert model == "PINHOLE"
        assert params[0] == pytest.approx(32 / math.tan(0.4)) and params[2:] == [32.0, 24.0]
    assert not scene.has_test_split


def test_transforms_intrinsics_distortion_and_rescaled_images(tmp_path):
    c = orbit(1)[0]
    cv2.imwrite(str(tmp_path / "a.png"), texture())
    tf = write_transforms(tmp_path, [{"file_path": "a.png", "transform_matrix": gl_c2w(c.viewmat), "fl_x": 90.0}],
                          fl_x=50.0, fl_y=51.0, cx=60.0, cy=50.0, w=128, h=96, k1=0.1, k2=-0.02, p1=0.001, p2=0.0)
    f = read_transforms(tf).frames[0]
    model, params = f.intrinsics.resolve(64, 48, "x")  # the image is a half-size copy
    assert model == "OPENCV"
    assert params == pytest.approx([45.0, 25.5, 30.0, 25.0, 0.1, -0.02, 0.001, 0.0])  # per-frame fl_x wins
    with pytest.raises(SplatError, match="not a uniform rescale"):
        f.intrinsics.resolve(64, 64, "x")


def test_transforms_missing_files_are_counted_and_test_split_read(tmp_path):
    cams = orbit(4)
    (tmp_path / "imgs").mkdir()
    for c in cams[:3]:
        cv2.imwrite(str(tmp_path / "imgs" / c.name), texture())
    fr = [{"file_path": f"imgs/{c.name}", "transform_matrix": gl_c2w(c.viewmat)} for c in cams]
    write_transforms(tmp_path, fr[:2] + fr[3:], "transforms_train.json", camera_angle_x=0.8)
    write_transforms(tmp_path, fr[2:3], "transforms_test.json", camera_angle_x=0.8)
    scene = read_transforms(tmp_path / "transforms_train.json")
    assert scene.missing == [f"imgs/{cams[3].name}"]
    assert scene.has_test_split
    assert [f.name for f in scene.frames if f.split == "test"] == [cams[2].name]


@pytest.mark.parametrize(
    "content, match",
    [
        ("{not json", "not valid JSON"),
        ("[]", "JSON object"),
        ('{"camera_angle_x": 0.8}', "no `frames`"),
        ('{"camera_angle_x": 0.8, "frames": [{"transform_matrix": []}]}', "no file_path"),
        ('{"frames": [{"file_path": "a.png", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}',
         "no focal length"),
        ('{"camera_angle_x": 0.8, "frames": [{"file_path": "a.png", "transform_matrix": [1, 2]}]}',
         "transform_matrix"),
        ('{"camera_angle_x": 0.8, "frames": [{"file_path": "../a.png", "transform_matrix": []}]}',
         "outside the input folder"),
        ('{"camera_angle_x": 0.8, "frames": [{"file_path": "/etc/passwd", "transform_matrix": []}]}',
         "outside the input folder"),
        ('{"camera_angle_x": 0.8, "frames": [{"file_path": "nope.png", "transform_matrix": []}]}',
         "none of the 1 listed images exists"),
    ],
)
def test_bad_transforms_name_the_file_and_problem(tmp_path, content, match):
    cv2.imwrite(str(tmp_path / "a.png"), texture())
    p = tmp_path / "transforms.json"
    p.write_text(content)
    with pytest.raises(SplatError, match=match) as ei:
        read_transforms(p)
    assert str(p) in str(ei.value) and "\n" not in str(ei.value)


# ---- COLMAP model files -------------------------------------------------------------


def write_text_model(d: Path, cams: list[Camera], with_points: bool = True) -> None:
    """A PINHOLE text model: one camera, one keypoint per image, one point seen by all."""
    d.mkdir(parents=True, exist_ok=True)
    c = cams[0]
    (d / "cameras.txt").write_text(f"# c\n1 PINHOLE {c.width} {c.height} {c.K[0, 0]} {c.K[1, 1]} {c.K[0, 2]} {c.K[1, 2]}\n")
    lines = ["# images\n"]
    for i, cam in enumerate(cams, start=1):
        q = quat_wxyz(cam.viewmat[:3, :3])
        t = cam.viewmat[:3, 3]
        lines.append(f"{i} {q[0]} {q[1]} {q[2]} {q[3]} {t[0]} {t[1]} {t[2]} 1 {cam.name}\n")
        lines.append("10.0 12.0 1\n" if with_points else "\n")
    (d / "images.txt").write_text("".join(lines))
    track = " ".join(f"{i} 0" for i in range(1, len(cams) + 1))
    (d / "points3D.txt").write_text(f"1 0.1 0.2 0.3 255 0 0 0.5 {track}\n" if with_points else "")


def quat_wxyz(R: np.ndarray) -> np.ndarray:  # [4]
    w = math.sqrt(max(0.0, 1 + R[0, 0] + R[1, 1] + R[2, 2])) / 2
    x = math.copysign(math.sqrt(max(0.0, 1 + R[0, 0] - R[1, 1] - R[2, 2])) / 2, R[2, 1] - R[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1 - R[0, 0] + R[1, 1] - R[2, 2])) / 2, R[0, 2] - R[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1 - R[0, 0] - R[1, 1] + R[2, 2])) / 2, R[1, 0] - R[0, 1])
    return np.array([w, x, y, z])


def bin_model(tmp_path: Path) -> Path:
    """The text model converted to .bin by pycolmap."""
    import pycolmap

    write_text_model(tmp_path / "txt", orbit(5))
    rec = pycolmap.Reconstruction(str(tmp_path / "txt"))
    out = tmp_path / "bin"
    out.mkdir()
    rec.write(str(out))
    return out


def test_check_model_accepts_good_text_and_binary(tmp_path):
    binary = bin_model(tmp_path)  # converted from the text model it writes to tmp_path / "txt"
    for d, fmt in ((tmp_path / "txt", "txt"), (binary, "bin")):
        s = check_model(d)
        assert s.format == fmt and len(s.images) == 5 and s.num_points3D == 1


@pytest.mark.parametrize("target, damage", [
    ("images.bin", lambda data: data[: len(data) - 30]),
    ("images.bin", lambda data: struct.pack("<Q", 1 << 60) + data[8:]),
    ("points3D.bin", lambda data: data[:8] + bytes(range(256)) * 2),
    ("points3D.bin", None),  # the file is removed
    ("cameras.bin", lambda data: b""),
], ids=["truncate_images", "huge_count", "garbage_points", "missing_points", "empty_cameras"])
def test_garbled_binary_models_are_refused_by_name(tmp_path, target, damage):
    d = bin_model(tmp_path)
    p = d / target
    if damage is None:
        p.unlink()
    else:
        p.write_bytes(damage(p.read_bytes()))
    with pytest.raises(SplatError) as ei:
        check_model(d)
    assert target in str(ei.value) and "\n" not in str(ei.value)


def test_text_model_with_bad_names_or_ids_is_refused(tmp_path):
    d = tmp_path / "m"
    write_text_model(d, orbit(3))
    text = (d / "images.txt").read_text()
    (d / "images.txt").write_text(text.replace("001.png", "../../etc/x.png"))
    with pytest.raises(SplatError, match="outside the images folder"):
        check_model(d)
    (d / "images.txt").write_text(text.replace(" 1 001.png", " 7 001.png"))
    with pytest.raises(SplatError, match="camera 7"):
        check_model(d)
    (d / "images.txt").write_text(text)
    (d / "points3D.txt").write_text("1 0 0 0 1 2 3 0.1 9 0\n")
    with pytest.raises(SplatError, match="missing image or keypoint"):
        check_model(d)


# ---- input detection ------------------------------------------------------------------


def test_detect_input_kinds(tmp_path):
    photos = tmp_path / "photos"
    photos.mkdir()
    cv2.imwrite(str(photos / "a.jpg"), texture())
    assert detect_input(photos).kind == "images"
    scene = tmp_path / "scene"
    (scene / "images").mkdir(parents=True)
    (scene / "ground_truth.json").write_text("{}")
    cv2.imwrite(str(scene / "images" / "a.jpg"), texture())
    spec = detect_input(scene)
    assert spec.kind == "images" and spec.images_dir == scene / "images"
    ws = tmp_path / "ws"
    write_text_model(ws / "sparse" / "0", orbit(3))
    (ws / "images").mkdir()
    spec = detect_input(ws)
    assert spec.kind == "colmap" and spec.model_dir == ws / "sparse" / "0"
    assert detect_input(ws / "sparse" / "0").images_dir == ws / "images"
    write_transforms(tmp_path / "blender", [], "transforms_train.json")
    assert detect_input(tmp_path / "blender").kind == "transforms"
    assert detect_input(tmp_path / "blender" / "transforms_train.json").kind == "transforms"
    (tmp_path / "v.mp4").write_bytes(b"")
    assert detect_input(tmp_path / "v.mp4").kind == "video"
    with pytest.raises(SplatError, match="single image"):
        detect_input(photos / "a.jpg")
    with pytest.raises(SplatError, match="no such file"):
        detect_input(tmp_path / "nothing")
    with pytest.raises(SplatError, match="no COLMAP model"):
        detect_input(photos, "colmap")


def test_the_focal_spread_is_measured_within_each_camera_taken_apart():
    """One camera each is kept when the images of one shared camera find different focal lengths;
    two shared cameras of other sizes (or EXIF cameras) differ from each other anyway."""
    small, large = [f"s{i}" for i in range(10)], [f"l{i}" for i in range(10)]
    apart = [[n] for n in small + large]
    focals = {**{n: 500.0 + i for i, n in enumerate(small)}, **{n: 1000.0 - i for i, n in enumerate(large)}}
    assert _focal_spread(focals, [small, large], apart) < 1.05 < FOCAL_SPREAD  # 2x apart between the groups
    zooms = {**focals, **{n: 1000.0 * (1 + i % 2) for i, n in enumerate(large)}}
    assert _focal_spread(zooms, [small, large], apart) > 1.9
    assert _focal_spread(zooms, [small, large], [[n] for n in small] + [large]) < 1.05  # large not taken apart
    assert _focal_spread({"l0": 1000.0}, [large], apart) == 1.0  # under two registered: nothing to compare
