"""Property tests for the readers of untrusted files other than .ply (see
test_ply_properties.py): whatever bytes or JSON they are given, checkpoints,
COLMAP models, transforms.json and project manifests either load or fail with a
one-line `SplatError` naming the file; never another exception, never a hang.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import resource
import shutil
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings, strategies as st

from splatcli.errors import SplatError
from splatcli.files.checkpoint import load_checkpoint, save_checkpoint
from splatcli.gaussians import Gaussians
from splatcli.inputs.images import load_rgb
from splatcli.inputs.transforms import read_transforms
from splatcli.options import table
from splatcli.project import Project
from splatcli.sfm.colmap_files import check_model
from splatcli.train.config import TrainConfig
from splatcli.views.sources import transforms_views
from support import data_dir

SETTINGS = settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture],
                    derandomize=True)


def _one_line_error(exc: SplatError, path: Path) -> None:
    msg = str(exc)
    assert "\n" not in msg and str(path) in msg, msg


def _read_or_refused(read, path: Path):
    """read()'s result, or None when it raised a SplatError that is one line naming `path`."""
    try:
        return read()
    except SplatError as e:
        _one_line_error(e, path)
        return None


def _mutated(data: bytes, muts: list[tuple[float, int]], cut: float = 1.0) -> bytes:
    """`data` with byte pos * len set to val for each (pos, val), cut to its first `cut` share
    (whole from 0.98 up)."""
    b = bytearray(data)
    for pos, val in muts:
        b[int(pos * len(b))] = val
    return bytes(b[: int(len(b) * cut) if cut < 0.98 else len(b)])


def _npy(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a)
    return buf.getvalue()


# ---- checkpoints --------------------------------------------------------------------


def _checkpoint_bytes() -> bytes:
    g = torch.Generator().manual_seed(0)
    n = 5
    gs = Gaussians(means=torch.randn(n, 3, generator=g), quats=torch.randn(n, 4, generator=g),
                   log_scales=torch.randn(n, 3, generator=g), opacity_logits=torch.randn(n, generator=g),
                   sh=torch.randn(n, 4, 3, generator=g))
    with tempfile.TemporaryDirectory() as d:
        p = save_checkpoint(Path(d) / "c.pt", step=7, gaussians=gs, sh_degree=1, config={"iterations": 10})
        return p.read_bytes()


CKPT = _checkpoint_bytes()


def _load_ckpt(data: bytes) -> None:
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "step-000000007.pt"
        p.write_bytes(data)
        ck = _read_or_refused(lambda: load_checkpoint(p), p)
        if ck is None:
            return
        # accepted: a consistent checkpoint, usable as it is (every tensor holds the same N Gaussians)
        g, n = ck.gaussians, len(ck.gaussians)
        assert isinstance(ck.step, int) and ck.step >= 0
        assert g.means.shape == (n, 3) and g.quats.shape == (n, 4) and g.log_scales.shape == (n, 3)
        assert g.opacity_logits.shape == (n,) and g.sh.shape[0] == n and g.sh.shape[2] == 3
        assert 0 <= ck.sh_degree <= g.sh_degree and len(ck.model()) == n
        if data == CKPT:  # the intact file reads back what was saved
            assert (ck.step, n, ck.sh_degree) == (7, 5, 1)


@SETTINGS
@given(st.integers(0, len(CKPT)))
def test_checkpoint_truncations(cut: int) -> None:
    _load_ckpt(CKPT[:cut])


@SETTINGS
@given(st.lists(st.tuples(st.integers(0, len(CKPT) - 1), st.integers(0, 255)), min_size=1, max_size=8))
def test_checkpoint_byte_mutations(muts: list[tuple[int, int]]) -> None:
    b = bytearray(CKPT)
    for i, v in muts:
        b[i] = v
    _load_ckpt(bytes(b))


@SETTINGS
@given(st.binary(max_size=1024))
def test_checkpoint_random_bytes(data: bytes) -> None:
    _load_ckpt(data)


# ---- COLMAP models ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def colmap_models(tmp_path_factory) -> dict[str, dict[str, bytes]]:
    """A small synthetic model's three files, binary and text."""
    from colmap_models import synthetic_model

    model = synthetic_model(num_images=3, num_points=8, camera_model="PINHOLE", width=32, height=24)
    out = {}
    for fmt in ("bin", "txt"):
        d = tmp_path_factory.mktemp(fmt)
        model.write(d, text=fmt == "txt")
        out[fmt] = {stem: (d / f"{stem}.{fmt}").read_bytes() for stem in ("cameras", "images", "points3D")}
    return out


def _check(files: dict[str, bytes], fmt: str) -> None:
    with tempfile.TemporaryDirectory() as d:
        for stem, data in files.items():
            (Path(d) / f"{stem}.{fmt}").write_bytes(data)
        s = _read_or_refused(lambda: check_model(Path(d)), Path(d))
        if s is None:
            return
        # accepted: every count it reports is consistent with the files
        assert s.images and all(cid in s.cameras for _, cid, _ in s.images.values())


@SETTINGS
@given(stem=st.sampled_from(["cameras", "images", "points3D"]), fmt=st.sampled_from(["bin", "txt"]),
       muts=st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), min_size=1, max_size=6))
def test_colmap_byte_mutations(colmap_models, stem: str, fmt: str, muts: list[tuple[int, int]]) -> None:
    files = dict(colmap_models[fmt])
    b = bytearray(files[stem])
    for i, v in muts:
        b[i % len(b)] = v
    files[stem] = bytes(b)
    _check(files, fmt)


@SETTINGS
@given(stem=st.sampled_from(["cameras", "images", "points3D"]), fmt=st.sampled_from(["bin", "txt"]),
       frac=st.floats(0, 1))
def test_colmap_truncations(colmap_models, stem: str, fmt: str, frac: float) -> None:
    files = dict(colmap_models[fmt])
    files[stem] = files[stem][: int(len(files[stem]) * frac)]
    _check(files, fmt)


@SETTINGS
@given(stem=st.sampled_from(["cameras", "images", "points3D"]), count=st.integers(0, 2**64 - 1))
def test_colmap_bin_lying_counts(colmap_models, stem: str, count: int) -> None:
    files = dict(colmap_models["bin"])
    files[stem] = count.to_bytes(8, "little") + files[stem][8:]
    _check(files, "bin")


# ---- LLFF poses_bounds.npy ------------------------------------------------------------------


def _llff_bytes() -> bytes:
    """A valid poses_bounds.npy of 3 cameras (the ring of tests/tiny_project.py)."""
    from splatcli.inputs.llff import to_poses_bounds
    from support.tiny_project import ring_cameras

    cams = ring_cameras(3)
    return _npy(to_poses_bounds([c.viewmat for c in cams], [(c.height, c.width, c.K[0, 0]) for c in cams],
                                [(1.0, 6.0)] * 3))


LLFF = _llff_bytes()


def _read_llff(data: bytes) -> None:
    from splatcli.inputs.llff import read_llff

    with tempfile.TemporaryDirectory() as d:
        root = Path(d)
        (root / "images").mkdir()
        for i in range(3):
            (root / "images" / f"{i}.png").write_bytes(b"\x89PNG\r\n\x1a\n")  # content is staging's business
        pb = root / "poses_bounds.npy"
        pb.write_bytes(data)
        scene = _read_or_refused(lambda: read_llff(pb), pb)
        if scene is None:
            return
        # accepted: 3 frames with proper poses and positive, ordered numbers
        assert len(scene.frames) == 3
        for f in scene.frames:
            R = f.viewmat[:3, :3]
            assert np.allclose(R @ R.T, np.eye(3), atol=1e-9) and np.linalg.det(R) > 0
            assert f.focal > 0 and f.width >= 1 and f.height >= 1 and 0 < f.near < f.far
            assert np.isfinite(f.viewmat).all()


@SETTINGS
@given(st.binary(max_size=512))
def test_llff_random_bytes(data: bytes) -> None:
    _read_llff(data)


@SETTINGS
@given(muts=st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(0, 255)), min_size=1, max_size=8),
       cut=st.floats(0, 1))
def test_llff_byte_mutations_and_truncations(muts: list[tuple[float, int]], cut: float) -> None:
    _read_llff(_mutated(LLFF, muts, cut))


@SETTINGS
@given(rows=st.integers(0, 5), cols=st.sampled_from([14, 15, 17, 18]),
       values=st.lists(st.floats(allow_nan=True, allow_infinity=True, width=64)
                       | st.sampled_from([0.0, -1.0, 1.0, 1e-300, 1e300]), min_size=90, max_size=90))
def test_llff_random_arrays(rows: int, cols: int, values: list[float]) -> None:
    a = np.asarray(values[: rows * cols] + [0.0] * max(0, rows * cols - 90), np.float64).reshape(rows, cols)
    _read_llff(_npy(a))


@SETTINGS
@given(col=st.integers(0, 16), value=st.floats(allow_nan=True, allow_infinity=True) | st.sampled_from([0.0, -1.0]))
def test_llff_one_value_changed(col: int, value: float) -> None:
    """A valid file with one number changed: the checks catch what matters (focal, bounds, size, rotation)."""
    a = np.load(io.BytesIO(LLFF))
    a[1, col] = value
    _read_llff(_npy(a))


# ---- EXIF camera facts -----------------------------------------------------------------------


def _exif_jpeg() -> bytes:
    from test_cameras import photo

    with tempfile.TemporaryDirectory() as d:
        return photo(Path(d) / "a.jpg", size=(32, 24), make="Panasonic", model="DMC-FZ150", focal=108.0,
                     focal_35=600).read_bytes()


EXIF_JPEG = _exif_jpeg()


def _read_exif(data: bytes) -> None:
    from splatcli.inputs.exif import MAX_FOCAL_MM, MAX_NAME, MIN_FOCAL_MM, read_exif_camera

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "a.jpg"
        p.write_bytes(data)
        t0 = time.monotonic()
        e = read_exif_camera(p)  # never raises
        assert time.monotonic() - t0 < 10.0
        for name in (e.make, e.model):
            assert name is None or (0 < len(name) <= MAX_NAME and name.isprintable() and name == name.strip())
        for f in (e.focal_mm, e.focal_35mm):
            assert f is None or (math.isfinite(f) and MIN_FOCAL_MM <= f <= MAX_FOCAL_MM)
        if data == EXIF_JPEG:
            assert (e.make, e.model, e.focal_mm, e.focal_35mm) == ("Panasonic", "DMC-FZ150", 108.0, 600.0)


@SETTINGS
@given(muts=st.lists(st.tuples(st.floats(0, 0.3, exclude_max=True), st.integers(0, 255)), min_size=0, max_size=8),
       cut=st.floats(0, 1))
def test_exif_byte_mutations_and_truncations(muts: list[tuple[float, int]], cut: float) -> None:
    """Mutations land in the first 30% of the file: the EXIF block, not the pixels."""
    _read_exif(_mutated(EXIF_JPEG, muts, cut))


@SETTINGS
@given(make=st.text(max_size=80), focal=st.floats(allow_nan=True, allow_infinity=True))
def test_exif_lying_values(make: str, focal: float) -> None:
    from PIL import Image

    ex = Image.Exif()
    ex[0x010F] = make
    ex.get_ifd(0x8769)[0x920A] = focal
    buf = io.BytesIO()
    try:
        Image.new("RGB", (8, 8)).save(buf, "JPEG", exif=ex)
    except (ValueError, UnicodeEncodeError, OverflowError, ZeroDivisionError):
        return  # Pillow cannot write it: no such file to read
    _read_exif(buf.getvalue())


# ---- transforms.json and manifests --------------------------------------------------------

JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-10**20, 10**20) | st.floats(allow_nan=False)
    | st.text(max_size=12),
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=8), inner, max_size=5),
    max_leaves=20,
)
KEYS = ["frames", "file_path", "transform_matrix", "fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x",
        "camera_model", "k1", "ply_file_path", "test_filenames", "is_fisheye"]
FRAME = st.dictionaries(st.sampled_from(KEYS), JSON_VALUES | st.just("a.png")
                        | st.just(np.eye(4).tolist()), max_size=6)
TRANSFORMS = st.dictionaries(st.sampled_from(KEYS), JSON_VALUES, max_size=6).flatmap(
    lambda top: st.lists(FRAME, max_size=4).map(lambda frames: {**top, "frames": frames}))


@contextlib.contextmanager
def _transforms_file(data: dict) -> Iterator[tuple[Path, Path]]:
    """(input folder holding a.png, its transforms.json written from `data`)."""
    with tempfile.TemporaryDirectory() as d:
        root = Path(d) / "in"
        root.mkdir()
        (root / "a.png").write_bytes(b"\x89PNG\r\n\x1a\n")  # exists; content is staging's business
        tf = root / "transforms.json"
        tf.write_text(json.dumps(data))
        yield root, tf


@SETTINGS
@given(TRANSFORMS)
def test_transforms_random_structure_in_both_uses(data: dict) -> None:
    """The reader as `process` uses it (every frame inside the input folder), and as
    `render --cameras` does (cameras only, images may be absent)."""
    with _transforms_file(data) as (root, tf):
        scene = _read_or_refused(lambda: read_transforms(tf), tf)
        if scene is not None:
            assert all(f.source.resolve().is_relative_to(root.resolve()) for f in scene.frames)
        views = _read_or_refused(lambda: transforms_views(tf, default_size=(32, 24)), tf)
        if views is None:
            return
        assert len(views) == len(data["frames"])
        for v in views:
            assert v.camera.width >= 1 and v.camera.height >= 1 and np.isfinite(v.camera.K).all()
            assert v.camera.K[0, 0] > 0 and v.camera.K[1, 1] > 0 and np.isfinite(v.camera.viewmat).all()


@SETTINGS
@given(st.binary(max_size=256))
def test_transforms_random_bytes(data: bytes) -> None:
    with tempfile.TemporaryDirectory() as d:
        tf = Path(d) / "transforms.json"
        tf.write_bytes(data)
        with pytest.raises(SplatError) as ei:
            read_transforms(tf)
        _one_line_error(ei.value, tf)


MANIFEST_KEYS = ["schema_version", "splits", "steps", "scene", "train", "test", "process", "background"]
MANIFEST_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-3, 3) | st.floats(allow_nan=False) | st.text(max_size=6),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.sampled_from(MANIFEST_KEYS), inner, max_size=4),
    max_leaves=12,
)


@SETTINGS
@given(st.dictionaries(st.sampled_from(MANIFEST_KEYS), MANIFEST_VALUES, max_size=5).map(
    lambda d: {**d, "schema_version": 1} if "schema_version" not in d else d) | JSON_VALUES)
def test_manifest_random_json(data) -> None:
    with tempfile.TemporaryDirectory() as d:
        root = Path(d) / "p"
        root.mkdir()
        (root / "splatcli.json").write_text(json.dumps(data))
        try:
            p = Project.open(root)
            p.splits()
            p.require_trained()
        except SplatError as e:
            assert "\n" not in str(e), str(e)
        finally:
            shutil.rmtree(root)


# ---- the stored train config (checkpoints carry it; --resume reads it) ----------------

CONFIG_VALUES = (st.none() | st.booleans() | st.integers(-3, 5) | st.integers(-2**70, 2**70)
                 | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=6)
                 | st.lists(st.integers(), max_size=2) | st.dictionaries(st.text(max_size=3), st.integers(), max_size=2))


@SETTINGS
@given(st.dictionaries(st.sampled_from(sorted(table(TrainConfig)) + ["default", "mcmc", "compact", "sh_auto", "exposure", "density"]), CONFIG_VALUES,
                       max_size=6))
def test_stored_train_config_random_values(d: dict) -> None:
    """Garbled values either give a config the loop can run with, or one line naming the key."""
    try:
        cfg = TrainConfig.from_dict(d, where="CKPT: stored train config")
    except SplatError as e:
        msg = str(e)
        assert "\n" not in msg and msg.startswith("CKPT: stored train config"), msg
        return
    assert cfg.iterations >= 1 and cfg.refine.refine_every >= 1 and cfg.checkpoint_every >= 1 and cfg.log_every >= 1
    assert cfg.sh_degree == "auto" or 0 <= int(cfg.sh_degree) <= 3
    assert cfg.train_scale(1) > 0  # the schedule evaluates


# ---- images (train, eval and render read photos through inputs.images.load_rgb) -----------


def _image_corpus() -> dict[str, bytes]:
    """Small files of every kind we read, made here, plus real photos from ../shared/data."""
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.integers(0, 255, (40, 56, 3), dtype=np.uint8), (5, 5), 1)
    out = {
        "rgb.png": cv2.imencode(".png", img)[1].tobytes(),
        "rgba.png": cv2.imencode(".png", np.dstack([img, img[..., 0]]))[1].tobytes(),
        "grey16.png": cv2.imencode(".png", (img[..., 0].astype(np.uint16) * 257))[1].tobytes(),
        "photo.jpg": cv2.imencode(".jpg", img)[1].tobytes(),
    }
    data = data_dir()
    for src in (data / "lego" / "train" / "r_0.png", data / "fox" / "images" / "0001.jpg"):
        if src.is_file():
            out[f"real{src.suffix}"] = src.read_bytes()
    return out


IMAGES = _image_corpus()


def _load_image(name: str, data: bytes) -> None:
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / name
        p.write_bytes(data)
        t0 = time.monotonic()
        img = _read_or_refused(lambda: load_rgb(p, None, (1.0, 1.0, 1.0)), p)
        if img is not None:
            assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3
        assert time.monotonic() - t0 < 10.0, "no input may hang a reader"


@SETTINGS
@given(name=st.sampled_from(sorted(IMAGES)), frac=st.floats(0, 1))
def test_image_truncations(name: str, frac: float) -> None:
    data = IMAGES[name]
    _load_image(name, data[: int(len(data) * frac)])


@SETTINGS
@given(name=st.sampled_from(sorted(IMAGES)),
       muts=st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(0, 255)), min_size=1, max_size=8))
def test_image_byte_mutations(name: str, muts: list[tuple[float, int]]) -> None:
    _load_image(name, _mutated(IMAGES[name], muts))


@pytest.mark.parametrize("w,h", [(65535, 65535), (1, 2**31 - 1), (2**31 - 1, 2**31 - 1)])
def test_image_with_a_lying_header_is_refused_without_allocating(w: int, h: int) -> None:
    """A PNG whose header claims gigapixels: refused from the header, memory stays small."""
    import struct
    import zlib

    data = bytearray(IMAGES["rgb.png"])
    ihdr = data.index(b"IHDR")
    data[ihdr + 4: ihdr + 12] = struct.pack(">II", w, h)
    data[ihdr + 17: ihdr + 21] = struct.pack(">I", zlib.crc32(bytes(data[ihdr: ihdr + 17])))
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    _load_image("big.png", bytes(data))
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 200 * 1024  # KB: under 200 MB more


# ---- real transforms files, mutated (skipped where ../shared/data is absent) -------------

REAL_TRANSFORMS = [p for p in (data_dir() / "fox" / "transforms.json", data_dir() / "lego" / "transforms_train.json")
                   if p.is_file()]


@pytest.mark.skipif(not REAL_TRANSFORMS, reason="../shared/data (real captures) is absent")
@SETTINGS
@given(which=st.integers(0, 1), muts=st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(0, 255)),
                                               min_size=1, max_size=6), cut=st.floats(0.2, 1))
def test_real_transforms_mutated_in_both_uses(which: int, muts: list[tuple[float, int]], cut: float) -> None:
    """Byte mutations and truncations of real transforms files, through the reader as
    `process` uses it and as `render --cameras` does: loaded, or one line naming the file."""
    src = REAL_TRANSFORMS[which % len(REAL_TRANSFORMS)]
    data = _mutated(src.read_bytes(), muts)
    with tempfile.TemporaryDirectory() as d:
        tf = Path(d) / src.name
        tf.write_bytes(data[: max(1, int(len(data) * cut))])
        for read in (lambda: read_transforms(tf, images=False), lambda: transforms_views(tf, default_size=(32, 24))):
            t0 = time.monotonic()
            _read_or_refused(read, tf)
            assert time.monotonic() - t0 < 10.0
