"""`splatcli render`: camera sources, outputs (PNG, depth, alpha, video), foreign
.ply files, and one-line refusals that leave the project untouched."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import plyfile
import pytest

from splatcli.device import resolve_device
from splatcli.errors import SplatError
from splatcli.formats.ply import write_ply
from splatcli.project import Project
from splatcli.views.paths import generate_path
from splatcli.views.sources import transforms_views
from support.tiny_project import (
    H,
    W,
    assert_user_error,
    make_tiny_project,
    ring_cameras,
    run_cli,
    run_ok,
    snapshot,
    tiny_gaussians,
)

AUTO_DEVICE = resolve_device("auto").type  # "cpu", or "cuda" where a GPU is

GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])


@pytest.fixture(scope="module")
def proj(tmp_path_factory) -> Project:
    return make_tiny_project(tmp_path_factory.mktemp("render") / "p", background=1.0)


def _png(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None, path
    return img


def _transforms(path: Path, *, per_frame: bool = False, angle_only: bool = False) -> Path:
    frames = []
    for c in ring_cameras():
        c2w_gl = np.linalg.inv(c.viewmat) @ GL_FROM_CV  # OpenCV -> OpenGL camera axes
        fr = {"file_path": f"images/{Path(c.name).stem}", "transform_matrix": c2w_gl.tolist()}
        if per_frame:
            fr.update(fl_x=c.K[0, 0], fl_y=c.K[1, 1], cx=c.K[0, 2], cy=c.K[1, 2], w=W, h=H)
        frames.append(fr)
    data: dict = {"frames": frames}
    if angle_only:  # Blender style: no size, so it is read from the image files
        data["camera_angle_x"] = 2 * math.atan(0.5 * W / ring_cameras()[0].K[0, 0])
    elif not per_frame:
        c = ring_cameras()[0]
        data.update(fl_x=c.K[0, 0], fl_y=c.K[1, 1], cx=c.K[0, 2], cy=c.K[1, 2], w=W, h=H, k1=0.01)
    path.write_text(json.dumps(data))
    return path


def test_split_outputs_and_video(proj: Project, tmp_path: Path) -> None:
    video = tmp_path / "v.mp4"
    r = run_ok("render", proj.root, "--split", "train", "--depth", "--alpha", "--video", video, "--json")
    s = json.loads(r.stdout)
    out = proj.render_dir("train")
    assert Path(s["out_dir"]) == out and s["frames"] == 8 and s["fps"] > 0 and s["device"].startswith(AUTO_DEVICE)
    names = sorted(p.name for p in out.glob("*.png"))
    assert names == sorted(n for n in proj.splits()["train"])  # named after the source images
    assert sorted(p.name for p in (out / "depth").glob("*.png")) == names
    assert _png(out / "alpha" / names[0]).shape == (H, W)
    assert _png(out / names[0]).shape == (H, W, 3)
    # a real video OpenCV reads back: 8 frames of the right size
    cap = cv2.VideoCapture(str(video))
    frames = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        frames.append(f)
    cap.release()
    assert len(frames) == 8 and frames[0].shape == (H, W, 3)
    # lossy codec, but the first frame is recognisably the first PNG
    assert np.abs(frames[0].astype(int) - _png(out / names[0]).astype(int)).mean() < 20


def test_scene_background_is_the_default(proj: Project, tmp_path: Path) -> None:
    assert run_cli("render", proj.root, "-o", tmp_path / "w", "-q").exit_code == 0
    assert run_cli("render", proj.root, "-o", tmp_path / "b", "-q", "--background", "0,0,0").exit_code == 0
    white, black = _png(tmp_path / "w" / "img_000.png"), _png(tmp_path / "b" / "img_000.png")
    assert white[0, 0].tolist() == [255, 255, 255] and black[0, 0].tolist() == [0, 0, 0]  # corners are empty


def test_transforms_json_matches_dataset_cameras(proj: Project, tmp_path: Path) -> None:
    views = transforms_views(_transforms(tmp_path / "t.json"))
    for v, c in zip(views, ring_cameras()):
        np.testing.assert_allclose(v.camera.viewmat, c.viewmat, atol=1e-12)
        np.testing.assert_allclose(v.camera.K, c.K)
    notes: list[str] = []
    pf = transforms_views(_transforms(tmp_path / "pf.json", per_frame=True), notes=notes)
    assert not notes and pf[3].camera.width == W
    (tmp_path / "images").symlink_to(proj.images_dir)  # the size comes from images/img_000.png
    ang = transforms_views(_transforms(tmp_path / "ang.json", angle_only=True))
    np.testing.assert_allclose(ang[0].camera.K, ring_cameras()[0].K, atol=1e-9)
    (tmp_path / "images").unlink()
    with pytest.raises(SplatError, match="pass --width and --height"):
        transforms_views(tmp_path / "ang.json")
    assert transforms_views(tmp_path / "ang.json", default_size=(W, H))[0].camera.width == W
    # rendering through --cameras gives the dataset's pixels
    r = run_cli("render", proj.root, "--cameras", tmp_path / "t.json", "-o", tmp_path / "tj", "--width", "24",
                "--antialias", "off")  # the same cameras; auto would differ: their trained size is unknown here
    assert r.exit_code == 0, r.output
    assert "distortion" in r.stderr  # k1 is ignored, and said so
    assert run_cli("render", proj.root, "--split", "all", "-o", tmp_path / "all", "-q", "--width", "24",
                   "--antialias", "off").exit_code == 0
    for n in ["img_000.png", "img_005.png"]:
        np.testing.assert_array_equal(_png(tmp_path / "tj" / n), _png(tmp_path / "all" / n))


def test_generated_paths(proj: Project, tmp_path: Path) -> None:
    cams = ring_cameras()
    orbit = generate_path("orbit", cams, 12)
    assert len(orbit) == 12
    for v in orbit:  # every frame looks at the ring's centre, from the ring's radius and height
        c = v.camera
        p = c.K @ (c.viewmat[:3, :3] @ np.zeros(3) + c.viewmat[:3, 3])
        np.testing.assert_allclose(p[:2] / p[2], [W / 2, H / 2], atol=1e-6)
        np.testing.assert_allclose(np.linalg.norm(c.center), np.linalg.norm(cams[0].center), rtol=1e-6)
    inter = generate_path("interpolate", cams, 19)  # passes through every camera: 18 = 2 x 9 steps
    for i in (0, 2, 18):
        np.testing.assert_allclose(inter[i].camera.viewmat, cams[i // 2].viewmat, atol=1e-9)
    spiral = generate_path("spiral", cams, 7)  # odd: two turns never revisit a point
    assert len({tuple(np.round(v.camera.center, 6)) for v in spiral}) == 7
    r = run_ok("render", proj.root, "--path", "spiral", "--frames", "3", "--width", "24", "--json")
    s = json.loads(r.stdout)
    assert (s["frames"], s["width"], s["height"]) == (3, 24, 20)
    assert sorted(p.name for p in proj.render_dir("spiral").glob("*.png")) == [f"spiral_000{i}.png" for i in range(3)]


def test_orbit_sweeps_only_the_photographed_arc() -> None:
    """A 270-degree capture orbits over those 270 degrees and back, never behind the scene."""
    def azimuths(views):
        return np.degrees([math.atan2(v.camera.center[2], v.camera.center[0]) for v in views]) % 360

    part = ring_cameras(12)[:10]  # 0..270 degrees in steps of 30: a 90-degree gap
    az = azimuths(generate_path("orbit", part, 40))
    assert az.min() >= -1e-6 and az.max() <= 270 + 1e-6
    assert az.max() > 269 and az.min() < 1  # the whole arc is swept
    full = azimuths(generate_path("orbit", ring_cameras(12), 40))  # all round: the full circle
    assert np.histogram(full, bins=4, range=(0, 360))[0].min() >= 9  # 10 each, give or take a frame on a bin edge


def _foreign_ply(path: Path, n: int = 300, *, nan_rows: int = 0) -> Path:
    """What another tool writes: SH degree 0, no normals, extra properties, other order."""
    t = tiny_gaussians(n, sh_degree=0)
    fields = {"x": t.means[:, 0], "y": t.means[:, 1], "z": t.means[:, 2]}
    fields |= {f"f_dc_{i}": t.sh[:, 0, i] for i in range(3)}
    fields |= {f"rot_{i}": t.quats[:, i] * 7 for i in range(4)}  # unnormalised
    fields |= {f"scale_{i}": t.log_scales[:, i] for i in range(3)}
    fields["opacity"] = t.opacity_logits
    arr = np.empty(n, dtype=[(k, "<f4") for k in fields] + [("red", "u1"), ("confidence", "<f8")])
    for k, v in fields.items():
        arr[k] = v.numpy()
    arr["red"] = 7
    arr["confidence"] = 0.5
    arr["x"][:nan_rows] = np.nan
    plyfile.PlyData([plyfile.PlyElement.describe(arr, "vertex")]).write(str(path))
    return path


def test_render_foreign_ply(proj: Project, tmp_path: Path) -> None:
    ply = _foreign_ply(tmp_path / "other.ply", nan_rows=3)
    r = run_ok("render", ply, "--project", proj.root, "--split", "all", "-o", tmp_path / "o", "--json")
    assert "red, confidence" in r.stderr and "dropped 3 of 300" in r.stderr
    assert json.loads(r.stdout)["num_gaussians"] == 297
    assert len(list((tmp_path / "o").glob("*.png"))) == 10
    # no cameras at all: an orbit around the Gaussians, written beside the .ply
    run_ok("render", ply, "--frames", "2", "--width", "32", "--height", "24")
    imgs = sorted((tmp_path / "renders" / "other_orbit").glob("*.png"))
    assert len(imgs) == 2 and _png(imgs[0]).shape == (24, 32, 3)
    assert _png(imgs[0]).max() > 0  # the splat is in view


def _lying_plys(d: Path) -> dict[str, tuple[Path, str]]:
    d.mkdir()
    out = {}
    write_ply(d / "ok.ply", tiny_gaussians(20))
    data = (d / "ok.ply").read_bytes()
    (d / "lying.ply").write_bytes(data.replace(b"element vertex 20\n", b"element vertex 2000000000\n"))
    out["lying"] = (d / "lying.ply", "header claims 2000000000 vertices")
    (d / "truncated.ply").write_bytes(data[: len(data) // 2])
    out["truncated"] = (d / "truncated.ply", "truncated")
    write_ply(d / "empty.ply", tiny_gaussians(0))
    out["empty"] = (d / "empty.ply", "zero Gaussians")
    (d / "types.ply").write_bytes(data.replace(b"property float opacity", b"property int opacity"))
    out["types"] = (d / "types.ply", "'opacity' is int")
    nan = _foreign_ply(d / "nan.ply", n=5, nan_rows=5)
    out["nan"] = (nan, "none of its 5 Gaussians is valid")
    pc = np.zeros(4, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1")])
    plyfile.PlyData([plyfile.PlyElement.describe(pc, "vertex")]).write(str(d / "cloud.ply"))
    out["cloud"] = (d / "cloud.ply", "plain point cloud")
    (d / "junk.ply").write_bytes(b"\x00\x01garbage" * 10)
    out["junk"] = (d / "junk.ply", "not a PLY file")
    return out


def test_bad_ply_files_are_refused(proj: Project, tmp_path: Path) -> None:
    before = snapshot(proj.root)
    for path, msg in _lying_plys(tmp_path / "bad").values():
        r = run_cli("render", path, "--project", proj.root)
        assert_user_error(r, str(path), msg)
        r = run_cli("eval", "--pred", path.parent, "--gt", path.parent)  # not images either
        assert r.exit_code == 2
    assert snapshot(proj.root) == before
    assert not (tmp_path / "bad" / "renders").exists()


def test_not_a_project_or_not_ready(tmp_path: Path) -> None:
    (tmp_path / "plain").mkdir()
    (tmp_path / "plain" / "x.txt").write_text("x")
    for cmd in ("render", "eval"):
        assert_user_error(run_cli(cmd, tmp_path / "plain"), str(tmp_path / "plain"), "not a splatcli project")
        assert_user_error(run_cli(cmd, tmp_path / "missing"), str(tmp_path / "missing"))
    fresh = Project.create(tmp_path / "fresh", source={"kind": "test"})
    untrained = make_tiny_project(tmp_path / "untrained", trained=False, photos=False)
    for cmd in ("render", "eval"):
        for p, step in ((fresh, "process"), (untrained, "train")):
            before = snapshot(p.root)
            assert_user_error(run_cli(cmd, p.root), str(p.root), f"`splatcli {step}")
            assert snapshot(p.root) == before


@pytest.mark.data
def test_reads_real_transforms_files(shared_data: Path) -> None:
    """The Blender (lego) and instant-ngp (fox) layouts from ../shared/data."""
    lego = shared_data / "lego" / "transforms_train.json"
    fox = shared_data / "fox" / "transforms.json"
    if not lego.is_file() or not fox.is_file():
        pytest.skip("lego or fox is absent")
    v = transforms_views(lego)  # no w/h: the size comes from train/r_0.png (extension appended)
    assert len(v) == 100 and (v[0].camera.width, v[0].camera.height) == (800, 800)
    assert v[0].out_name == "r_0.png" and v[0].camera.K[0, 0] == pytest.approx(1111.11, abs=0.01)
    notes: list[str] = []
    f = transforms_views(fox, notes=notes)  # all 67 frames, even those whose image is absent
    assert len(f) == 67 and (f[0].camera.width, f[0].camera.height) == (1080, 1920) and "distortion" in notes[0]
    for cams in ([x.camera for x in v], [x.camera for x in f]):
        orbit = generate_path("orbit", cams, 8)
        assert all(np.isfinite(o.camera.viewmat).all() for o in orbit)
