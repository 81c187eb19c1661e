"""Issue 5, "Bad input": the single checklist, every case through the CLI.

Each error case asserts, through typer's CliRunner on `splatcli.cli.main.app`:
exit code 2; stderr is exactly one line, `error: ...`, naming the file (or the
option) and the problem; nothing on stdout; no traceback anywhere; and every
file of the project (and of the input) unchanged, bytes and mtime. The cases
that are not errors (non-image files mixed in, a truncated image among good
ones, mixed sizes and orientations, some NaN rows in a .ply) assert exit 0 and
the note saying what was skipped.

Nothing here runs structure from motion: the `process` cases that must get past
it replace `run_sfm` with a stand-in that poses the staged images on a ring
(what is under test is how the input is read, not SfM). Projects are the hand-made
tiny project of tests/support/tiny_project.py, copied per test.
"""

from __future__ import annotations

import json
import os
import pickle
import shutil
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from splatcli.files.atomic import MAX_JSON_BYTES
from splatcli.files.checkpoint import CHECKPOINT_SCHEMA
from splatcli.formats.ply import gaussians_to_rows, ply_header, ply_property_names
from splatcli.inputs.llff import MAX_POSES_BYTES, to_poses_bounds
from splatcli.inputs.transforms import MAX_TRANSFORMS_BYTES
from splatcli.project import MANIFEST_NAME, SCHEMA_VERSION, Project
from support.tiny_project import (
    assert_user_error as assert_error,
    make_tiny_project,
    ring_cameras,
    run_cli as cli,
    snapshot,
    tiny_gaussians,
)
from test_sfm import gl_c2w, jpeg_bytes, texture, with_exif_orientation

# ---- helpers ----------------------------------------------------------------------


def assert_ok_with_note(r, *fragments: str) -> None:
    text = (r.stdout or "") + (r.stderr or "")
    assert "Traceback" not in text, text
    assert r.exit_code == 0, (r.exit_code, text)
    notes = " ".join(ln for ln in r.stderr.splitlines() if ln.startswith(("note:", "warning:")))
    for f in fragments:
        assert f in notes, (f, r.stderr)


def refused(args: list, *fragments: str, watch: tuple[Path, ...]) -> str:
    """The command fails with one `error:` line holding `fragments`; nothing under `watch` changed."""
    before = snapshot(*watch)
    line = assert_error(cli(*args), *fragments)
    assert snapshot(*watch) == before, line
    return line


def png_bytes(img: np.ndarray) -> bytes:
    return cv2.imencode(".png", img)[1].tobytes()


# ---- projects ------------------------------------------------------------------------


@pytest.fixture(scope="module")
def bases(tmp_path_factory) -> dict[str, Path]:
    """Built once: a trained and an untrained tiny project (grey photos: nothing here renders them)."""
    d = tmp_path_factory.mktemp("bases")
    return {"trained": make_tiny_project(d / "trained", photos=False).root,
            "untrained": make_tiny_project(d / "untrained", trained=False, photos=False).root}


@pytest.fixture
def proj(bases, tmp_path) -> Path:
    """A fresh copy of the trained tiny project."""
    return Path(shutil.copytree(bases["trained"], tmp_path / "proj"))


def set_field(path: Path, keys: tuple, value) -> None:
    """Hand-edit a JSON file: set data[k0][k1]... = value."""
    data = json.loads(path.read_text())
    target = data
    for k in keys[:-1]:
        target = target[k]
    target[keys[-1]] = value
    path.write_text(json.dumps(data))


def checkpoint_of(root: Path) -> Path:
    ck = Project(root).latest_checkpoint()
    assert ck is not None
    return ck


# ---- the broken projects and checkpoints of the train/render/eval/export cases ------


class Payload:
    """A pickled object whose unpickling would create a folder (it must never run)."""

    def __init__(self, marker: Path) -> None:
        self.marker = str(marker)

    def __reduce__(self):
        return (os.mkdir, (self.marker,))


def break_project(case: str, tmp_path: Path, bases: dict[str, Path]) -> tuple[Path, Path, list[str]]:
    """(project path, the file at fault, message fragments) for one broken-project case."""
    proj = tmp_path / "proj"
    if case == "missing_path":
        return proj, proj, ["no such project directory", "splatcli process"]
    if case == "not_a_project":
        proj.mkdir()
        (proj / "notes.txt").write_text("my notes")
        return proj, proj, ["not a splatcli project", "splatcli process"]
    if case == "a_file":
        proj.write_text("a file, not a folder")
        return proj, proj, ["splatcli project"]  # render also says "nor a 3DGS .ply file"
    if case == "unprocessed":
        Project.create(proj, source={"kind": "test"})
        return proj, proj, ["no processed dataset", "`splatcli process"]
    if case == "sparse_missing":
        shutil.copytree(bases["trained"], proj)
        shutil.rmtree(Project(proj).sparse_dir)
        return proj, proj, ["no processed dataset", "`splatcli process"]
    if case == "untrained":
        shutil.copytree(bases["untrained"], proj)
        return proj, proj, ["no trained model", "`splatcli train"]
    shutil.copytree(bases["trained"], proj)
    m = proj / MANIFEST_NAME
    if case == "manifest_newer":
        set_field(m, ("schema_version",), SCHEMA_VERSION + 1)
        return proj, m, ["schema version", "newer", "upgrade splatcli"]
    if case == "manifest_not_json":
        m.write_text('{"schema_version": 1, "splits": ')
        return proj, m, ["not valid JSON"]
    if case == "manifest_not_object":
        m.write_text("[1, 2, 3]")
        return proj, m, ["not a splatcli manifest"]
    if case == "manifest_bad_field":  # hand-edited: a field of the wrong type
        set_field(m, ("steps", "process"), None)
        return proj, m, ["manifest field steps.process is None, expected an object"]
    if case == "manifest_bad_scene":
        set_field(m, ("scene", "background"), "white")
        return proj, m, ["manifest field scene.background is 'white', expected a list of 3 finite numbers"]
    if case == "manifest_huge":  # refused by its size before a byte is parsed (a sparse file: no disk used)
        os.truncate(m, MAX_JSON_BYTES + 1)
        return proj, m, [f"{MAX_JSON_BYTES + 1} bytes", f"more than the {MAX_JSON_BYTES} allowed"]
    ck = checkpoint_of(proj)
    if case == "ckpt_newer":
        raw = torch.load(ck, weights_only=True)
        raw["schema"] = CHECKPOINT_SCHEMA + 1
        torch.save(raw, ck)
        return proj, ck, ["checkpoint schema", "newer", "upgrade splatcli"]
    if case == "ckpt_truncated":
        data = ck.read_bytes()
        ck.write_bytes(data[: len(data) // 2])
        return proj, ck, ["truncated or corrupt"]
    if case == "ckpt_empty":
        ck.write_bytes(b"")
        return proj, ck, ["truncated or corrupt"]
    if case == "ckpt_garbage":
        ck.write_bytes(bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8)))
        return proj, ck, ["not a readable checkpoint", "not a PyTorch zip archive"]
    if case == "ckpt_foreign":
        torch.save({"model": torch.zeros(3)}, ck)
        return proj, ck, ["not a splatcli checkpoint"]
    if case == "ckpt_pickled_payload":
        raw = torch.load(ck, weights_only=True)
        raw["extra"] = {"x": Payload(tmp_path / "pwned")}
        torch.save(raw, ck)
        return proj, ck, ["refused", "objects other than tensors", "posix.mkdir", "not loaded"]
    if case == "ckpt_raw_pickle":
        ck.write_bytes(pickle.dumps({"format": "splatcli-checkpoint", "x": Payload(tmp_path / "pwned")}))
        return proj, ck, ["not a PyTorch zip archive"]
    if case == "ckpt_bad_shapes":
        raw = torch.load(ck, weights_only=True)
        raw["gaussians"]["quats"] = raw["gaussians"]["quats"][:, :3]
        torch.save(raw, ck)
        return proj, ck, ["quats", "shape"]
    raise AssertionError(case)


# Which command is asked to read what: train only reads a checkpoint with --resume;
# eval and export read the latest checkpoint; render reads it through the project.
PROJECT_CASES = [
    "missing_path", "not_a_project", "a_file", "unprocessed", "sparse_missing", "untrained",
    "manifest_newer", "manifest_not_json", "manifest_not_object", "manifest_bad_field", "manifest_bad_scene", "manifest_huge",
    "ckpt_newer", "ckpt_truncated", "ckpt_empty", "ckpt_garbage", "ckpt_foreign", "ckpt_pickled_payload",
    "ckpt_raw_pickle", "ckpt_bad_shapes",
]
COMMANDS = {
    "train": lambda p: ["train", p, "--resume", "--iterations", "1"],
    "render": lambda p: ["render", p, "--frames", "2"],
    "eval": lambda p: ["eval", p, "--no-plots"],
    "export": lambda p: ["export", p],
}


@pytest.mark.parametrize("cmd, case", [
    (cmd, case) for cmd in COMMANDS for case in PROJECT_CASES
    if not (cmd == "train" and case == "untrained")  # what train expects (--resume without a checkpoint starts afresh)
])
def test_broken_project(cmd: str, case: str, tmp_path: Path, bases) -> None:
    root, culprit, fragments = break_project(case, tmp_path, bases)
    refused(COMMANDS[cmd](root), str(culprit), *fragments, watch=(tmp_path,))
    assert not (tmp_path / "pwned").exists()  # the pickled payload never ran


# ---- .ply files: render FILE.ply, eval PROJ --model FILE.ply, train PROJ --init-ply FILE.ply ----


def good_rows(n: int = 40, sh_degree: int = 1) -> np.ndarray:  # [n, P] float32, 3DGS property order
    return gaussians_to_rows(tiny_gaussians(n, seed=3, sh_degree=sh_degree))


def write_rows(path: Path, rows: np.ndarray, sh_degree: int = 1, count: int | None = None) -> Path:
    header = ply_header(rows.shape[0] if count is None else count, sh_degree)
    path.write_bytes(header + np.ascontiguousarray(rows, "<f4").tobytes())
    return path


def bad_ply(case: str, d: Path) -> tuple[Path, list[str]]:
    """(the .ply, message fragments) for one bad-.ply case."""
    d.mkdir(parents=True, exist_ok=True)
    p = d / f"{case}.ply"
    rows = good_rows()
    n = rows.shape[0]
    if case == "missing":
        return p, ["no such"]
    if case == "all_nan_inf":
        rows[: n // 2, 0] = np.nan
        rows[n // 2 :, -1] = np.inf
        return write_rows(p, rows), [f"none of its {n} Gaussians is valid", "NaN/Inf"]
    if case == "zero_vertices":
        return write_rows(p, rows[:0]), ["zero Gaussians"]
    if case == "wrong_type_int":
        data = write_rows(p, rows).read_bytes()
        p.write_bytes(data.replace(b"property float opacity\n", b"property int opacity\n"))
        return p, ["'opacity' is int", "float or double"]
    if case == "wrong_type_uchar":
        names = ply_property_names(1)
        dtype = [(nm, "u1" if nm == "scale_0" else "<f4") for nm in names]
        table = np.zeros(n, dtype=dtype)
        for i, nm in enumerate(names):
            table[nm] = rows[:, i] if nm != "scale_0" else 1
        head = ply_header(n, 1).replace(b"property float scale_0\n", b"property uchar scale_0\n")
        p.write_bytes(head + table.tobytes())
        return p, ["'scale_0' is uchar", "float or double"]
    if case == "list_property":
        data = write_rows(p, rows).read_bytes()
        p.write_bytes(data.replace(b"property float x\n", b"property list uchar float x\n"))
        return p, ["'x' is list uchar float", "float or double"]
    if case == "header_lies_more":
        return write_rows(p, rows, count=n + 7), [f"header claims {n + 7} vertices", "lying header"]
    if case == "header_lies_huge":  # must be refused without allocating the claimed size
        return write_rows(p, rows, count=10**15), [f"header claims {10**15} vertices"]
    if case == "truncated_body":
        data = write_rows(p, rows).read_bytes()
        p.write_bytes(data[: len(data) - 100])
        return p, [f"header claims {n} vertices", "truncated"]
    if case == "no_end_header":
        p.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n")
        return p, ["no end_header"]
    if case == "not_ply":
        p.write_bytes(b"\x00\x01 this is no ply file" * 20)
        return p, ["not a PLY file"]
    if case == "point_cloud":
        head = b"ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\nproperty float y\n" \
               b"property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
        p.write_bytes(head + b"\x00" * (4 * 15))
        return p, ["plain point cloud", "not a Gaussian splat"]
    if case == "ascii":
        p.write_bytes(ply_header(1, 0).replace(b"binary_little_endian", b"ascii") + b" ".join([b"0"] * 17) + b"\n")
        return p, ["ASCII PLY is not supported"]
    if case == "bad_sh_count":
        names = ply_property_names(1)
        head = ply_header(n, 1).replace(b"property float f_rest_8\n", b"")
        keep = [i for i, nm in enumerate(names) if nm != "f_rest_8"]
        p.write_bytes(head + np.ascontiguousarray(rows[:, keep], "<f4").tobytes())
        return p, ["f_rest_* properties match no SH degree"]
    if case == "directory":
        p.mkdir()
        return p, ["is a directory"]
    raise AssertionError(case)


PLY_CASES = ["missing", "all_nan_inf", "zero_vertices", "wrong_type_int", "wrong_type_uchar", "list_property",
             "header_lies_more", "header_lies_huge", "truncated_body", "no_end_header", "not_ply", "point_cloud",
             "ascii", "bad_sh_count", "directory"]
PLY_COMMANDS = {
    "render": lambda proj, ply: ["render", ply, "--frames", "2"],
    "render_project": lambda proj, ply: ["render", ply, "--project", proj],
    "eval": lambda proj, ply: ["eval", proj, "--model", ply, "--no-plots"],
    "train": lambda proj, ply: ["train", proj, "--init-ply", ply, "--iterations", "1"],
}


@pytest.mark.parametrize("case", PLY_CASES)
@pytest.mark.parametrize("cmd", list(PLY_COMMANDS))
def test_bad_ply(cmd: str, case: str, proj: Path, tmp_path: Path) -> None:
    ply, fragments = bad_ply(case, tmp_path / "plys")
    refused(PLY_COMMANDS[cmd](proj, ply), str(ply), *fragments, watch=(tmp_path,))


@pytest.mark.parametrize("case", ["missing_path", "not_a_project", "unprocessed"])
def test_good_ply_with_a_bad_project(case: str, tmp_path: Path, bases) -> None:
    """`render FILE.ply --project P`, `eval P --model FILE.ply`, `train P --init-ply FILE.ply`: P is at fault."""
    root, culprit, fragments = break_project(case, tmp_path, bases)
    ply = write_rows(tmp_path / "good.ply", good_rows())
    for args in (["render", ply, "--project", root], ["eval", root, "--model", ply, "--no-plots"],
                 ["train", root, "--init-ply", ply, "--iterations", "1"]):
        refused(args, str(culprit), *fragments, watch=(tmp_path,))


def test_ply_with_some_nan_rows_renders_with_a_note(tmp_path: Path) -> None:
    """Not an error: rows with NaN/Inf are dropped and counted; the rest renders."""
    rows = good_rows()
    rows[:3, 1] = np.nan
    rows[3:5, 7] = -np.inf
    ply = write_rows(tmp_path / "some_nan.ply", rows)
    r = cli("render", ply, "--frames", "2", "--width", "24", "--out", tmp_path / "out")
    assert_ok_with_note(r, "some_nan.ply: dropped 5 of 40 Gaussians with NaN/Inf values")
    assert len(list((tmp_path / "out").glob("*.png"))) == 2


# ---- options out of range: one line saying which values are allowed ------------------

NO_GPU = not torch.cuda.is_available()
OPTION_CASES = [
    # (command, options, fragments)
    ("train", ["--iterations", "-5"], ["--iterations -5", "at least 1"]),
    ("train", ["--iterations", "0"], ["--iterations 0", "at least 1"]),
    ("train", ["--max-size", "0"], ["--max-size 0", "at least 16"]),
    ("train", ["--downscale", "0"], ["--downscale 0", "(0, 64]"]),
    ("train", ["--downscale", "-2"], ["--downscale -2", "(0, 64]"]),
    ("train", ["--max-gaussians", "0"], ["--max-gaussians 0", "at least 1"]),
    ("train", ["--eval-every", "-1"], ["--eval-every -1", "0 or more"]),
    ("train", ["--sh-degree", "7"], ["--sh-degree '7'", "0, 1, 2, 3 or auto"]),
    ("train", ["--preset", "turbo"], ["--preset 'turbo'", "default"]),
    ("train", ["--renderer", "gsplat"], ["--renderer gsplat needs a CUDA device", "--renderer torch"]),
    ("train", ["--iterations", "many"], ["'--iterations'", "Invalid value"]),
    ("train", ["--compact-keep", "0"], ["--compact-keep 0.0", "(0, 1]"]),
    ("train", ["--compact-keep", "0.25"], ["--compact-keep", "give --compact too"]),  # typer versions word the rest differently
    ("render", ["--width", "0"], ["--width 0", "between 1 and 16384"]),
    ("render", ["--height", "-4"], ["--height -4", "between 1 and 16384"]),
    ("render", ["--downscale", "0"], ["--downscale 0", "(0, 64]"]),
    ("render", ["--frames", "0", "--path", "orbit"], ["--frames 0", "between 1 and 100000"]),
    ("render", ["--fps", "0", "--video", "v.mp4"], ["--fps 0", "(0, 1000]"]),
    ("render", ["--split", "val"], ["--split 'val'", "test, train, all"]),
    ("render", ["--path", "zigzag"], ["--path 'zigzag'", "orbit, spiral, interpolate"]),
    ("render", ["--background", "teal"], ["--background 'teal'", "white, black, gray"]),
    ("render", ["--background", "1,2,3"], ["--background '1,2,3'", "[0, 1]"]),
    ("render", ["--cameras", "missing.json"], ["missing.json", "not found"]),
    ("render", ["--video", "a.gif"], ["--video a.gif", ".mp4"]),
    ("render", ["--renderer", "gsplat"], ["--renderer gsplat needs a CUDA device"]),
    ("render", ["--renderer", "opengl"], ["--renderer 'opengl'", "auto, torch, gsplat"]),
    ("eval", ["--downscale", "0"], ["--downscale 0"]),
    ("eval", ["--downscale", "-1"], ["--downscale -1"]),
    ("eval", ["--split", "val"], ["--split 'val'", "test, train, all"]),
    ("eval", ["--budgets", "1,abc"], ["--budgets", "(0, 1]"]),
    ("eval", ["--budgets", "0"], ["--budgets", "(0, 1]"]),
    ("eval", ["--budgets", "1.5"], ["--budgets", "(0, 1]"]),
    ("eval", ["--background", "teal"], ["--background 'teal'", "white, black, gray"]),
    ("eval", ["--renderer", "gsplat"], ["--renderer gsplat needs a CUDA device"]),
    *[(c, ["--device", "tpu"], ["--device 'tpu'", "auto, cpu, cuda"]) for c in ("train", "render", "eval")],
    *[(c, ["--device", "cuda"], ["--device cuda", "no CUDA GPU", "auto, cpu, cuda"])
      for c in ("train", "render", "eval")],
    ("export", ["--format", "obj"], ["--format 'obj'", "ply, compressed-ply, spz, sog, splat"]),
    ("export", ["-o", "."], ["-o .", "is a directory", "scene.ply"]),
]


@pytest.mark.parametrize("cmd, opts, fragments", OPTION_CASES,
                         ids=[f"{c}{''.join(o)}" for c, o, _ in OPTION_CASES])
def test_option_out_of_range(cmd: str, opts: list[str], fragments: list[str], proj: Path) -> None:
    if ("cuda" in opts or "gsplat" in opts) and not NO_GPU:
        pytest.skip("a CUDA GPU is available: --device cuda (and --renderer gsplat) is valid here")
    refused([cmd, proj, *opts], *fragments, watch=(proj,))


PROCESS_OPTION_CASES = [
    (["--max-size", "0"], ["--max-size 0", "at least 32"]),
    (["--max-size", "-100"], ["--max-size -100", "at least 32"]),
    (["--num-frames", "0"], ["--num-frames 0", "at least 2"]),
    (["--fps", "0"], ["--fps 0", "positive"]),
    (["--fps", "-3"], ["--fps -3", "positive"]),
    (["--matcher", "magic"], ["--matcher 'magic'", "auto, exhaustive, sequential"]),
    (["--input-type", "photos"], ["--input-type 'photos'", "auto, images, video, colmap, transforms"]),
    (["--background", "teal"], ["--background 'teal'", "auto, white, black, gray or R,G,B"]),
    (["--camera-model", "fancy_lens"], ["--camera-model 'FANCY_LENS'", "SIMPLE_RADIAL", "OPENCV"]),
    (["--single-camera", "--per-image-cameras"], ["--single-camera and --per-image-cameras", "choose one"]),
]


@pytest.mark.parametrize("opts, fragments", PROCESS_OPTION_CASES, ids=["".join(o) for o, _ in PROCESS_OPTION_CASES])
def test_process_option_out_of_range(opts: list[str], fragments: list[str], tmp_path: Path, proj: Path) -> None:
    src = image_folder(tmp_path / "photos", 3)
    refused(["process", src, "-o", proj, "--overwrite", *opts], *fragments, watch=(proj, src))


# ---- process: folders of photos, videos, transforms.json, COLMAP models --------------


def image_folder(d: Path, n: int, *, size: tuple[int, int] = (64, 48)) -> Path:
    d.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        (d / f"img_{i:02d}.png").write_bytes(png_bytes(texture(size[1], size[0], seed=i)))
    return d


@pytest.fixture
def fake_sfm(monkeypatch):
    """`run_sfm` replaced by a stand-in that poses every staged image on a ring:
    the cases below test reading the input, not structure from motion."""
    import splatcli.process.capture as proc
    from splatcli.sfm import colmap
    from splatcli.sfm.reconstruct import SfmResult

    calls = []

    def run_sfm(image_dir, names, work, opts, *, cameras, min_side, where, split_cameras=None, on_event=None,
                mask_dir=None, features_ready=False, on_features=None):
        calls.append(list(names))
        cams = ring_cameras(len(names))
        specs = []
        for name, cam in zip(names, cams):
            h, w = cv2.imread(str(Path(image_dir) / name)).shape[:2]
            specs.append(colmap.CameraSpec(name, w, h, "PINHOLE", [float(w), float(w), w / 2, h / 2], cam.viewmat))
        (Path(work) / "database.db").write_bytes(b"")
        return SfmResult(model=colmap.build_model(specs), names=list(names), model_sizes=[len(names)],
                         unregistered=[], matcher="exhaustive", num_pairs=0, keypoints_median=0.0)

    monkeypatch.setattr(proc, "run_sfm", run_sfm)
    return calls


def process_error(src: Path, proj: Path, *fragments: str, extra: tuple = ()) -> None:
    """`process SRC -o PROJ --overwrite` fails; the old project and the input are untouched."""
    refused(["process", src, "-o", proj, "--overwrite", *extra], *fragments, watch=(proj, src))
    assert not (proj / ".process-tmp").exists()


def _claim_huge(data: bytes, suffix: str) -> bytes:
    """The same image with a header that declares 65535 x 65535 px (4.3 gigapixels)."""
    b = bytearray(data)
    if suffix == ".png":
        b[16:24] = (65535).to_bytes(4, "big") * 2
    else:
        pos = 2
        while not (0xC0 <= b[pos + 1] <= 0xC3):  # walk to the start-of-frame marker
            pos += 2 + int.from_bytes(b[pos + 2 : pos + 4], "big")
        b[pos + 5 : pos + 9] = (65535).to_bytes(2, "big") * 2
    return bytes(b)


def encoded(suffix: str, seed: int = 9) -> tuple[bytes, str]:
    """texture(seed) encoded as .png or .jpg, and the format's name."""
    img = texture(seed=seed)
    return (png_bytes(img), "PNG") if suffix == ".png" else (jpeg_bytes(img), "JPEG")


def photo_input(case: str, d: Path) -> tuple[Path, list[str]]:
    """A folder (or file) of photos `process` must refuse: (the input, message fragments)."""
    if case == "missing":
        return d, ["no such file or folder"]
    d.mkdir()
    if case == "empty":
        return d, ["no images found"]
    if case == "non_images":
        (d / "notes.txt").write_text("not a photo")
        (d / "scan.pdf").write_bytes(b"%PDF-1.4")
        return d, ["no images found"]
    if case == "only_truncated":
        for i in range(3):
            data = jpeg_bytes(texture(seed=i))
            (d / f"{i}.jpg").write_bytes(data[: len(data) // 3])
        return d, ["found 0", "truncated JPEG"]
    image_folder(d, 1)
    if case == "one_image":
        return d, ["at least 2 readable images, found 1"]
    if case == "single_file":
        return d / "img_00.png", ["a single image", "at least 2 photos"]
    what, suffix = case.split(".")  # "cut.png": one image and a truncated one; "huge.jpg": one claiming 4.3 gigapixels
    data, kind = encoded("." + suffix)
    if what == "cut":
        (d / case).write_bytes(data[: len(data) // 2])
        return d, ["found 1", f"{case}: truncated {kind}"]
    (d / case).write_bytes(_claim_huge(data, "." + suffix))  # refused before decoding
    return d, ["found 1", f"{case}: too large (65535 x 65535 px"]


@pytest.mark.parametrize("case", ["missing", "empty", "non_images", "only_truncated", "one_image", "single_file",
                                  "cut.png", "cut.jpg", "huge.png", "huge.jpg"])
def test_process_bad_photos(case: str, tmp_path: Path, proj: Path) -> None:
    src, fragments = photo_input(case, tmp_path / "in")
    process_error(src, proj, str(src), *fragments)


def test_process_non_images_mixed_in_are_skipped_with_a_note(tmp_path: Path, fake_sfm) -> None:
    d = image_folder(tmp_path / "photos", 4)
    (d / "notes.txt").write_text("not a photo")
    (d / "Thumbs.db").write_bytes(b"\x00" * 64)
    r = cli("process", d, "-o", tmp_path / "p")
    assert_ok_with_note(r, "skipped 2 file(s) that are not images", "notes.txt")
    assert fake_sfm == [[f"img_{i:02d}.png" for i in range(4)]]
    assert sorted(Project(tmp_path / "p").splits()["train"] + Project(tmp_path / "p").splits()["test"]) == fake_sfm[0]


@pytest.mark.parametrize("suffix", [".png", ".jpg"])
def test_process_truncated_image_among_good_ones_is_skipped_with_a_note(suffix: str, tmp_path: Path, fake_sfm) -> None:
    d = image_folder(tmp_path / "photos", 3)
    data, kind = encoded(suffix)
    (d / f"zz_cut{suffix}").write_bytes(data[: len(data) // 2])
    r = cli("process", d, "-o", tmp_path / "p", "--json")
    assert_ok_with_note(r, f"zz_cut{suffix}: truncated {kind}")
    summary = json.loads(r.stdout)
    assert summary["registered"] == 3 and len(summary["skipped"]) == 1
    assert not (Project(tmp_path / "p").images_dir / f"zz_cut{suffix}").exists()


def test_process_mixed_sizes_and_orientations_are_handled(tmp_path: Path, fake_sfm) -> None:
    d = tmp_path / "mixed"
    d.mkdir()
    (d / "a_landscape.png").write_bytes(png_bytes(texture(48, 64, seed=1)))
    (d / "b_portrait.png").write_bytes(png_bytes(texture(64, 48, seed=2)))
    (d / "c_small.jpg").write_bytes(jpeg_bytes(texture(30, 40, seed=3)))
    # stored 64 wide x 48 high, EXIF says "rotate 90 degrees clockwise": 48 x 64 once oriented
    (d / "d_exif.jpg").write_bytes(with_exif_orientation(jpeg_bytes(texture(48, 64, seed=4)), 6))
    r = cli("process", d, "-o", tmp_path / "p")
    assert_ok_with_note(r, "sizes; using one camera per image")
    from splatcli.sfm.colmap import read_scene

    sizes = {c.name: (c.width, c.height) for c in read_scene(Project(tmp_path / "p").sparse_dir).cameras}
    assert sizes == {"a_landscape.png": (64, 48), "b_portrait.png": (48, 64), "c_small.jpg": (40, 30),
                     "d_exif.jpg": (48, 64)}


def test_process_single_camera_refuses_mixed_sizes(tmp_path: Path, proj: Path) -> None:
    d = image_folder(tmp_path / "photos", 3)
    (d / "z_portrait.png").write_bytes(png_bytes(texture(64, 48, seed=5)))
    process_error(d, proj, "--single-camera", "2 sizes (48x64, 64x48)", extra=("--single-camera",))


def test_process_exif_that_lies_is_a_warning_and_the_photos_are_used(tmp_path: Path, fake_sfm) -> None:
    """A focal length of 0 and a make full of control characters: dropped with one warning each;
    the photos share a camera by what is left (make, model and size)."""
    from test_cameras import photo

    d = tmp_path / "photos"
    for i in range(3):
        photo(d / f"img_{i}.jpg", make="Canon\x00\x07", model="EOS 60D", focal=0.0 if i else 50.0, seed=i)
    r = cli("process", d, "-o", tmp_path / "p", "--json")
    assert_ok_with_note(r, "EXIF ignored: img_1.jpg: focal length 0 mm is not a focal length",
                        "EXIF ignored: img_2.jpg: focal length 0 mm")
    cams = json.loads(r.stdout)["cameras"]
    assert sorted(c["names"] for c in cams) == [["img_0.jpg"], ["img_1.jpg", "img_2.jpg"]]
    assert {c["make"] for c in cams} == {"Canon"} and sorted(str(c["focal_mm"]) for c in cams) == ["50.0", "None"]


def write_video(path: Path, n: int = 6) -> Path:
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48))
    if not vw.isOpened():
        pytest.skip("OpenCV cannot write MJPG video here")
    for i in range(n):
        vw.write(texture(seed=i))
    vw.release()
    return path


@pytest.mark.parametrize("case", ["garbage", "empty", "truncated"])
def test_process_unreadable_video(case: str, tmp_path: Path, proj: Path) -> None:
    v = tmp_path / "clip.avi" if case == "truncated" else tmp_path / "clip.mp4"
    if case == "garbage":
        v.write_bytes(b"\x00\x01 definitely not a video" * 100)
    elif case == "empty":
        v.write_bytes(b"")
    else:
        data = write_video(tmp_path / "good.avi").read_bytes()
        v.write_bytes(data[:200])  # the container header, no frame
    process_error(v, proj, str(v), "cannot read the video")


# ---- transforms.json ----------------------------------------------------------------


def transforms_input(root: Path, case: str) -> tuple[Path, list[str]]:
    """A transforms.json input broken in one way: (the file, message fragments)."""
    root.mkdir(parents=True)
    cams = ring_cameras(3)
    for i in range(3):
        (root / f"f{i}.png").write_bytes(png_bytes(texture(40, 48, seed=i)))
    frames = [{"file_path": f"f{i}.png", "transform_matrix": gl_c2w(c.viewmat)} for i, c in enumerate(cams)]
    good = {"camera_angle_x": 0.9, "frames": frames}
    outside = root.parent / "outside.png"  # exists: refused for where it is, not for being absent
    outside.write_bytes(png_bytes(texture(40, 48, seed=7)))
    bad_m = [row[:] for row in frames[1]["transform_matrix"]]
    bad_m[0][0] = float("nan")
    content, frag = {
        "not_json": ("{ this is not json", ["not valid JSON"]),
        "not_utf8": (b"\xff\xfe{\x00", ["not UTF-8"]),
        "a_list": (json.dumps([good]), ["must hold a JSON object"]),
        "no_frames": (json.dumps({"camera_angle_x": 0.9}), ["no `frames` list"]),
        "empty_frames": (json.dumps({"camera_angle_x": 0.9, "frames": []}), ["no `frames` list"]),
        "frame_not_object": (json.dumps({**good, "frames": [frames[0], 3]}), ["frame 1 is not a JSON object"]),
        "no_file_path": (json.dumps({**good, "frames": [{"transform_matrix": frames[0]["transform_matrix"]}]}),
                         ["frame 0 has no file_path"]),
        "no_focal": (json.dumps({"frames": frames}), ["no focal length"]),
        "bad_focal": (json.dumps({**good, "camera_angle_x": "wide"}), ["camera_angle_x", "finite number"]),
        "no_matrix": (json.dumps({**good, "frames": [{"file_path": "f0.png"}]}), ["transform_matrix"]),
        "nan_matrix": (json.dumps({**good, "frames": [frames[0], {**frames[1], "transform_matrix": bad_m}]}),
                       ["frame 1", "transform_matrix"]),
        "missing_files": (json.dumps({**good, "frames": [{**f, "file_path": f"gone{i}.png"} for i, f in enumerate(frames)]}),
                          ["none of the 3 listed images exists", "gone0.png"]),
        "escape_dotdot": (json.dumps({**good, "frames": [frames[0], {**frames[1], "file_path": "../outside.png"}]}),
                          ["'../outside.png'", "outside the input folder"]),
        "escape_absolute": (json.dumps({**good, "frames": [{**frames[0], "file_path": str(outside)}]}),
                            [repr(str(outside)), "outside the input folder"]),
        "escape_ply": (json.dumps({**good, "ply_file_path": "../../points.ply"}),
                       ["ply_file_path", "outside the input folder"]),
        "size_mismatch": (json.dumps({**good, "w": 100, "h": 40, "fl_x": 50.0}),
                          ["f0.png", "not a uniform rescale"]),
        "huge": ("{", [f"more than the {MAX_TRANSFORMS_BYTES} allowed"]),
    }[case]
    tf = root / "transforms.json"
    (tf.write_bytes if isinstance(content, bytes) else tf.write_text)(content)
    if case == "huge":  # the JSON reader bounds what it reads by the file's size (a sparse file: no disk used)
        os.truncate(tf, MAX_TRANSFORMS_BYTES + 1)
    return tf, frag


TRANSFORMS_CASES = ["not_json", "not_utf8", "a_list", "no_frames", "empty_frames", "frame_not_object", "no_file_path",
                    "no_focal", "bad_focal", "no_matrix", "nan_matrix", "missing_files", "escape_dotdot",
                    "escape_absolute", "escape_ply", "size_mismatch", "huge"]


@pytest.mark.parametrize("case", [*TRANSFORMS_CASES, "not_json/given_as_its_folder"])
def test_process_bad_transforms(case: str, tmp_path: Path, proj: Path) -> None:
    tf, fragments = transforms_input(tmp_path / "in", case.split("/")[0])
    process_error(tf.parent if case.endswith("/given_as_its_folder") else tf, proj, str(tf), *fragments)


def test_transforms_with_some_files_missing_or_truncated_imports_the_rest(tmp_path: Path) -> None:
    """Not an error: listed-but-absent files and a truncated image are skipped with a warning."""
    root = tmp_path / "in"
    tf, _ = transforms_input(root, "not_json")
    cams = ring_cameras(5)
    for i in (3, 4):
        (root / f"f{i}.png").write_bytes(png_bytes(texture(40, 48, seed=i)))
    data = jpeg_bytes(texture(40, 48, seed=5))
    (root / "f5.jpg").write_bytes(data[: len(data) // 2])
    frames = [{"file_path": f"f{i}.png", "transform_matrix": gl_c2w(c.viewmat)} for i, c in enumerate(cams)]
    frames += [{"file_path": "gone.png", "transform_matrix": gl_c2w(cams[0].viewmat)},
               {"file_path": "f5.jpg", "transform_matrix": gl_c2w(cams[1].viewmat)}]
    tf.write_text(json.dumps({"camera_angle_x": 0.9, "frames": frames}))
    r = cli("process", tf, "-o", tmp_path / "p", "--json")
    assert_ok_with_note(r, "1 image(s) listed in transforms.json do not exist", "f5.jpg: truncated JPEG")
    assert json.loads(r.stdout)["registered"] == 5


# ---- LLFF poses_bounds.npy ----------------------------------------------------------------


def llff_input(root: Path, case: str) -> tuple[Path, list[str]]:
    """An LLFF capture broken in one way: (the file at fault, message fragments)."""
    (root / "images").mkdir(parents=True)
    cams = ring_cameras(3)
    for i, c in enumerate(cams):
        (root / "images" / c.name).write_bytes(png_bytes(texture(c.height, c.width, seed=i)))
    rows = to_poses_bounds([c.viewmat for c in cams], [(c.height, c.width, c.K[0, 0]) for c in cams],
                           [(1.0, 6.0)] * 3)
    pb = root / "poses_bounds.npy"
    frag: list[str]
    if case == "wrong_shape":
        rows, frag = rows[:, :15], ["shape (3, 15)", "expected (N, 17)"]
    elif case == "one_dimensional":
        rows, frag = rows.reshape(-1), ["shape (51,)", "expected (N, 17)"]
    elif case == "nan":
        rows[1, 5], frag = np.nan, ["row 1", "NaN"]
    elif case == "infinite_bound":
        rows[2, 16], frag = np.inf, ["row 2", "NaN or infinity"]
    elif case == "count_disagrees":
        rows, frag = rows[:2], ["2 poses but 3 images", "counts must agree"]
    elif case == "zero_focal":
        rows[0, 14], frag = 0.0, ["row 0", "focal length 0 must be positive"]
    elif case == "near_beyond_far":
        rows[1, 15], frag = 9.0, ["row 1", "near 9 and far 6"]
    elif case == "not_a_rotation":
        rows[0, 0:3] *= 3.0
        frag = ["row 0", "not a rotation"]
    elif case == "size_mismatch":
        rows[:, 4], frag = 100.0, ["not a uniform rescale"]  # h: 100, the images are 48 high
    elif case == "strings":
        rows, frag = np.array([["a"] * 17] * 3), ["expected numbers"]
    elif case == "pickled_objects":
        rows, frag = np.array([[{"x": 1}] * 17] * 3, dtype=object), ["not a readable .npy array"]
    elif case == "not_npy":
        pb.write_bytes(b"LLFF poses, trust me" * 10)
        return pb, ["not a readable .npy array"]
    elif case == "truncated":
        np.save(pb, rows)
        pb.write_bytes(pb.read_bytes()[:200])
        return pb, ["not a readable .npy array"]
    elif case == "huge":  # refused by its size (a sparse file: no disk used)
        pb.write_bytes(b"LLFF poses, trust me" * 10)
        os.truncate(pb, MAX_POSES_BYTES + 1)
        return pb, [f"more than the {MAX_POSES_BYTES} allowed"]
    elif case == "no_images":
        np.save(pb, rows)
        for q in (root / "images").iterdir():
            q.unlink()
        (root / "images").rmdir()
        return pb, ["no images/ (or images_N/) folder"]
    else:
        raise AssertionError(case)
    np.save(pb, rows, allow_pickle=case == "pickled_objects")
    return pb, frag


LLFF_CASES = ["wrong_shape", "one_dimensional", "nan", "infinite_bound", "count_disagrees", "zero_focal",
              "near_beyond_far", "not_a_rotation", "size_mismatch", "strings", "pickled_objects", "not_npy",
              "truncated", "no_images", "huge"]


@pytest.mark.parametrize("case", LLFF_CASES)
def test_process_bad_llff(case: str, tmp_path: Path, proj: Path) -> None:
    """Named with --input-type llff; the huge file is also refused when the input type is detected."""
    pb, fragments = llff_input(tmp_path / "in", case)
    process_error(tmp_path / "in", proj, str(pb if case != "size_mismatch" else tmp_path / "in"), *fragments,
                  extra=() if case == "huge" else ("--input-type", "llff"))


# ---- COLMAP models ---------------------------------------------------------------------


def colmap_workspace(root: Path, *, text: bool) -> Path:
    """root/images + root/sparse/0: a small synthetic PINHOLE model with points."""
    from colmap_models import synthetic_model

    model = synthetic_model(num_images=4, num_points=30, camera_model="PINHOLE", width=64, height=48)
    (root / "images").mkdir(parents=True)
    for i, name in enumerate(model.registered_names()):
        (root / "images" / name).write_bytes(png_bytes(texture(48, 64, seed=i)))
    model.write(root / "sparse" / "0", text=text)
    return root / "sparse" / "0"


def damage(p: Path, edit) -> Path:
    """Replace p's bytes b by edit(b); edit None deletes p."""
    if edit is None:
        p.unlink()
    else:
        p.write_bytes(edit(p.read_bytes()))
    return p


def _garble(b: bytes) -> bytes:
    return b[:8] + bytes(range(192)) + b[200:]


COLMAP_DAMAGE = {  # case: (file, edit, message fragments)
    "bin_missing_cameras": ("cameras.bin", None, ["missing"]),
    "bin_missing_images": ("images.bin", None, ["missing"]),
    "bin_missing_points3D": ("points3D.bin", None, ["missing"]),
    "bin_truncated_cameras": ("cameras.bin", lambda b: b[:20], ["truncated or garbled", "more than the file can hold"]),
    "bin_truncated_images": ("images.bin", lambda b: b[:-10], ["truncated or garbled"]),
    "bin_garbled_images": ("images.bin", _garble, ["images.bin"]),
    # a count that would make a reader allocate terabytes
    "bin_huge_count": ("points3D.bin", lambda b: struct.pack("<Q", 2**62) + b[8:],
                       ["garbled", "more than the file can hold"]),
    "bin_garbled_points": ("points3D.bin", lambda b: b[:8] + b"\xff" * 500, ["points3D.bin"]),
    "bin_empty_cameras": ("cameras.bin", lambda b: b"", ["truncated or garbled"]),
    "txt_garbled_cameras": ("cameras.txt", lambda b: b"1 PINHOLE sixty-four 48 50 50 32 24\n",
                            ["line 1", "expected numbers"]),
    "txt_unknown_model": ("cameras.txt", lambda b: b"1 FANCY_LENS 64 48 50 50 32 24\n",
                          ["line 1", "CAMERA_ID MODEL WIDTH HEIGHT"]),
    "txt_missing_points3D": ("points3D.txt", None, ["missing"]),
}


def break_colmap(case: str, ws: Path) -> tuple[Path, list[str]]:
    """Damage the workspace's model in one way: (the file at fault, message fragments)."""
    d = colmap_workspace(ws, text=case.startswith("txt_"))
    if case in COLMAP_DAMAGE:
        name, edit, fragments = COLMAP_DAMAGE[case]
        return damage(d / name, edit), fragments
    if case == "bin_escape_name":
        return _rename_first_image_bin(d, "../../outside.png"), ["'../../outside.png'", "outside the images folder"]
    if case in ("txt_escape_dotdot", "txt_escape_absolute"):
        p = d / "images.txt"
        name = "../outside.png" if case == "txt_escape_dotdot" else str(ws.parent / "outside.png")
        (ws.parent / "outside.png").write_bytes(png_bytes(texture(48, 64)))
        lines = p.read_text().splitlines()
        first = next(i for i, ln in enumerate(lines) if ln.strip() and not ln.startswith("#"))
        tok = lines[first].split()
        lines[first] = " ".join(tok[:9] + [name])
        p.write_text("\n".join(lines) + "\n")
        return p, [repr(name), "outside the images folder"]
    raise AssertionError(case)


def _rename_first_image_bin(d: Path, new: str) -> Path:
    """Rewrite the first image's name in images.bin (record: id, 7 doubles, camera id, name\\0, ...)."""
    p = d / "images.bin"
    data = p.read_bytes()
    start = 8 + 4 + 56 + 4
    end = data.index(b"\0", start)
    p.write_bytes(data[:start] + new.encode() + data[end:])
    return p


COLMAP_CASES = [*COLMAP_DAMAGE, "bin_escape_name", "txt_escape_dotdot", "txt_escape_absolute"]


@pytest.mark.parametrize("case", COLMAP_CASES)
def test_process_bad_colmap_model(case: str, tmp_path: Path, proj: Path) -> None:
    culprit, fragments = break_colmap(case, tmp_path / "ws")
    process_error(tmp_path / "ws", proj, str(culprit), *fragments)


def test_colmap_images_missing_from_the_folder(tmp_path: Path, proj: Path) -> None:
    colmap_workspace(tmp_path / "ws", text=False)
    for p in (tmp_path / "ws" / "images").iterdir():
        p.unlink()
    process_error(tmp_path / "ws", proj, str(tmp_path / "ws" / "images"), "none of the model's 4 images exists")


# ---- where process writes ------------------------------------------------------------


@pytest.mark.parametrize("case, frags", [
    ("output_is_a_file", ["exists and is not a directory"]),
    ("output_not_a_project", ["not a splatcli project", "--overwrite"]),
    ("output_holds_input", ["holds the input"]),
    ("already_processed", ["already holds a processed dataset", "--overwrite"]),
])
def test_process_output_rules(case: str, frags: list[str], tmp_path: Path, proj: Path) -> None:
    src = image_folder(tmp_path / "photos", 3)
    out = {"output_is_a_file": tmp_path / "out.txt", "output_not_a_project": tmp_path / "mine",
           "output_holds_input": tmp_path, "already_processed": proj}[case]
    if case == "output_is_a_file":
        out.write_text("mine")
    elif case == "output_not_a_project":
        out.mkdir()
        (out / "keep.txt").write_text("mine")
    refused(["process", src, "-o", out], str(out), *frags, watch=(tmp_path,))


# ---- eval --pred/--gt ----------------------------------------------------------------


def test_eval_folders_bad(tmp_path: Path) -> None:
    assert_error(cli("eval", "--pred", tmp_path / "none"), "--pred and --gt go together")
    image_folder(tmp_path / "a", 2)
    (tmp_path / "b").mkdir()
    for gt in (tmp_path / "nowhere", tmp_path / "b"):
        refused(["eval", "--pred", tmp_path / "a", "--gt", gt], str(gt), watch=(tmp_path,))


# ---- render --cameras transforms.json ------------------------------------------------


@pytest.mark.parametrize("case, fragments", [
    ("not_json", ["not valid JSON"]),
    ("no_frames", ["has no `frames` list"]),
    ("bad_matrix", ["frame 0", "transform_matrix"]),
    ("no_focal", ["frame 0", "no focal length"]),
    ("missing", ["not found"]),
])
def test_render_bad_cameras_file(case: str, fragments: list[str], proj: Path, tmp_path: Path) -> None:
    tf = tmp_path / "cams.json"
    frame = {"file_path": "x.png", "w": 32, "h": 24, "transform_matrix": gl_c2w(ring_cameras(1)[0].viewmat)}
    content = {"not_json": "{", "no_frames": json.dumps({"fl_x": 20}),
               "bad_matrix": json.dumps({"fl_x": 20, "frames": [{**frame, "transform_matrix": [[1, 2]]}]}),
               "no_focal": json.dumps({"frames": [frame]}), "missing": None}[case]
    if content is not None:
        tf.write_text(content)
    refused(["render", proj, "--cameras", tf], str(tf), *fragments, watch=(tmp_path,))


# ---- a project whose files were damaged after process --------------------------------


@pytest.mark.parametrize("cmd", ["train", "eval"])
@pytest.mark.parametrize("damage", ["image_missing", "image_garbage"])
def test_project_image_damaged(cmd: str, damage: str, proj: Path, tmp_path: Path) -> None:
    """An image of the dataset deleted or overwritten: named, with what to do."""
    name = Project(proj).splits()["test"][0]
    img = Project(proj).images_dir / name
    if damage == "image_missing":
        img.unlink()
    else:
        img.write_bytes(b"not a png")
    args = ["train", proj, "--iterations", "1"] if cmd == "train" else ["eval", proj, "--no-plots"]
    refused(args, str(img), watch=(tmp_path,))


@pytest.mark.parametrize("key, value, fragment", [
    ("downscale", "big", "steps.train.config.downscale is 'big'"),
    ("downscale", 0, "steps.train.config.downscale is 0"),
    ("max_size", -5, "steps.train.config.max_size is -5"),
])
def test_eval_with_a_hand_edited_train_config(key: str, value, fragment: str, proj: Path, tmp_path: Path) -> None:
    m = proj / MANIFEST_NAME
    set_field(m, ("steps", "train", "config", key), value)
    refused(["eval", proj, "--no-plots"], str(m), fragment, "pass --downscale", watch=(tmp_path,))


def _binary_sparse(proj: Path) -> Path:
    """Rewrite the project's text model as .bin (what `process` writes)."""
    from splatcli.sfm import colmap

    sparse = Project(proj).sparse_dir
    model = colmap.read_model(sparse)
    for p in sparse.iterdir():
        p.unlink()
    model.write(sparse)
    return sparse


@pytest.mark.parametrize("name, edit, fragments", [
    pytest.param("images.txt", lambda b: b"1 2 3\n", ["line 1"], id="txt_garbled_images"),
    pytest.param("points3D.bin", lambda b: struct.pack("<Q", 2**40) + b[8:],
                 ["truncated or garbled", "more than the file can hold"], id="bin_huge_points"),
    pytest.param("cameras.bin", lambda b: b[:20], ["truncated or garbled"], id="bin_truncated_cameras"),
    pytest.param("images.bin", lambda b: b[:-20], ["truncated or garbled"], id="bin_truncated_images"),
    pytest.param("points3D.bin", None, ["missing"], id="bin_missing_points"),
])
def test_sparse_model_damaged_after_process(name: str, edit, fragments: list[str], proj: Path, tmp_path: Path) -> None:
    """pycolmap trusts the counts in .bin files (a huge one aborts the interpreter): the
    project's model is checked before pycolmap reads it."""
    sparse = _binary_sparse(proj) if name.endswith(".bin") else Project(proj).sparse_dir
    damage(sparse / name, edit)
    for args in (["train", proj, "--iterations", "1"], ["render", proj], ["eval", proj, "--no-plots"]):
        refused(args, str(sparse), name, *fragments, watch=(tmp_path,))


def test_render_cameras_file_path_cannot_escape(tmp_path):
    """render --cameras reads an image's size only through a path inside its folder."""
    from splatcli.errors import SplatError
    from splatcli.views.sources import transforms_views

    (tmp_path / "cams").mkdir()
    f = tmp_path / "cams" / "transforms.json"
    f.write_text(json.dumps({"fl_x": 50, "frames": [
        {"file_path": "../../etc/passwd", "transform_matrix": np.eye(4).tolist()}]}))
    with pytest.raises(SplatError, match="outside the input folder"):
        transforms_views(f)
