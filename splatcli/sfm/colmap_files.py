"""Check a COLMAP model's files before pycolmap reads them.

pycolmap trusts the counts written in `.bin` files, so a library read does not
serve here: with the point count of a 30-point points3D.bin set to 2^40, pycolmap
4.2 ran for minutes and took gigabytes of memory before failing; a larger file or a
smaller machine is killed instead. So we walk every file first, with each count
bounded by the bytes actually left in the file, and check that the three files
agree (camera ids, image ids, point indices). Every problem becomes a one-line
`SplatError` naming the file.

Only `cameras`, `images` and `points3D` are read; COLMAP >= 3.12 `rigs` and
`frames` files are ignored (we import each image with its own pose).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

from ..errors import SplatError

MODEL_FILES = ("cameras", "images", "points3D")

# COLMAP camera model id -> (name, number of params).
CAMERA_MODELS: dict[int, tuple[str, int]] = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}
_MODEL_BY_NAME = {name: (mid, n) for mid, (name, n) in CAMERA_MODELS.items()}
MAX_IMAGE_SIDE = 1 << 17  # pixels; anything larger is a garbled file


@dataclass
class ModelSummary:
    """What the checked files hold."""

    format: str  # "bin" or "txt"
    cameras: dict[int, tuple[str, int, int]] = field(default_factory=dict)  # id -> (model, width, height)
    images: dict[int, tuple[str, int, int]] = field(default_factory=dict)  # id -> (name, camera_id, num_points2D)
    num_points3D: int = 0


def model_format(model_dir: Path) -> str | None:
    """"bin" or "txt" when `model_dir` holds a COLMAP model, else None."""
    for fmt in ("bin", "txt"):
        if (model_dir / f"cameras.{fmt}").is_file() or (model_dir / f"images.{fmt}").is_file():
            return fmt
    return None


def check_model(model_dir: Path) -> ModelSummary:
    """Walk the model's files; raise SplatError on the first problem."""
    model_dir = Path(model_dir)
    fmt = model_format(model_dir)
    if fmt is None:
        raise SplatError(f"{model_dir}: no COLMAP model (cameras.bin or cameras.txt) found")
    for stem in MODEL_FILES:
        p = model_dir / f"{stem}.{fmt}"
        if not p.is_file():
            raise SplatError(f"{p}: missing; a COLMAP model needs cameras, images and points3D files")
    summary = ModelSummary(format=fmt)
    if fmt == "bin":
        _check_bin(model_dir, summary)
    else:
        _check_txt(model_dir, summary)
    if not summary.images:
        raise SplatError(f"{model_dir / ('images.' + fmt)}: the model has no images")
    return summary


def check_image_name(name: str, where: Path) -> None:
    """Refuse names that would leave the images folder."""
    p = PurePosixPath(name.replace("\\", "/"))
    if not name or p.is_absolute() or ".." in p.parts or name.startswith("~"):
        raise SplatError(f"{where}: image name {name!r} points outside the images folder")


# ---- binary -----------------------------------------------------------------


class _Reader:
    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            self.buf = memoryview(path.read_bytes())
        except OSError as exc:
            raise SplatError(f"{path}: cannot read: {exc.strerror or exc}") from None
        self.pos = 0

    def left(self) -> int:
        return len(self.buf) - self.pos

    def take(self, fmt: str) -> tuple:
        size = struct.calcsize(fmt)
        if size > self.left():
            raise SplatError(f"{self.path}: truncated or garbled (ends inside a record at byte {self.pos})")
        out = struct.unpack_from(fmt, self.buf, self.pos)
        self.pos += size
        return out

    def skip(self, n: int) -> None:
        if n > self.left():
            raise SplatError(f"{self.path}: truncated or garbled (a record claims more bytes than the file has)")
        self.pos += n

    def count(self, min_record: int, what: str) -> int:
        (n,) = self.take("<Q")
        if n * min_record > self.left():
            raise SplatError(f"{self.path}: truncated or garbled: claims {n} {what}, more than the file can hold")
        return n

    def cstring(self) -> str:
        end = bytes(self.buf[self.pos : self.pos + 4096]).find(b"\0")
        if end < 0:
            raise SplatError(f"{self.path}: truncated or garbled: an image name is not terminated")
        raw = bytes(self.buf[self.pos : self.pos + end])
        self.pos += end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise SplatError(f"{self.path}: garbled: an image name is not UTF-8") from None

    def done(self) -> None:
        if self.left():
            raise SplatError(f"{self.path}: garbled: {self.left()} unexpected bytes at the end")


def _finite(values: tuple, path: Path, what: str) -> None:
    if not all(math.isfinite(v) for v in values):
        raise SplatError(f"{path}: garbled: {what} is not finite")


def _check_camera(path: Path, cid: int, model_id: int, width: int, height: int, params: tuple, s: ModelSummary) -> None:
    if cid in s.cameras:
        raise SplatError(f"{path}: camera id {cid} appears twice")
    if not (0 < width <= MAX_IMAGE_SIDE and 0 < height <= MAX_IMAGE_SIDE):
        raise SplatError(f"{path}: camera {cid} has an impossible size {width}x{height}")
    _finite(params, path, f"camera {cid}'s parameters")
    s.cameras[cid] = (CAMERA_MODELS[model_id][0], width, height)


def _check_bin(d: Path, s: ModelSummary) -> None:
    r = _Reader(d / "cameras.bin")
    for _ in range(r.count(24, "cameras")):
        cid, mid, w, h = r.take("<iiQQ")
        if mid not in CAMERA_MODELS:
            raise SplatError(f"{r.path}: camera {cid} has unknown model id {mid}")
        params = r.take(f"<{CAMERA_MODELS[mid][1]}d")
        _check_camera(r.path, cid, mid, w, h, params, s)
    r.done()

    r = _Reader(d / "images.bin")
    for _ in range(r.count(4 + 56 + 4 + 1 + 8, "images")):
        (iid,) = r.take("<I")
        pose = r.take("<7d")
        (cid,) = r.take("<I")
        name = r.cstring()
        _finite(pose, r.path, f"image {iid}'s pose")
        if cid not in s.cameras:
            raise SplatError(f"{r.path}: image {name!r} uses camera {cid}, which cameras.bin does not have")
        if iid in s.images:
            raise SplatError(f"{r.path}: image id {iid} appears twice")
        check_image_name(name, r.path)
        (n2d,) = r.take("<Q")
        r.skip(_checked_mul(n2d, 24, r))
        s.images[iid] = (name, cid, n2d)
    r.done()

    r = _Reader(d / "points3D.bin")
    n = r.count(8 + 24 + 3 + 8 + 8, "points")
    for _ in range(n):
        pid, x, y, z = r.take("<Q3d")
        r.skip(3)
        (err,) = r.take("<d")
        _finite((x, y, z), r.path, f"point {pid}'s position")
        (tl,) = r.take("<Q")
        elems = _checked_mul(tl, 8, r)
        if elems > r.left():
            raise SplatError(f"{r.path}: truncated or garbled (point {pid}'s track is longer than the file)")
        track = struct.unpack_from(f"<{2 * tl}I", r.buf, r.pos)
        r.pos += elems
        for k in range(0, len(track), 2):
            img = s.images.get(track[k])
            if img is None or not 0 <= track[k + 1] < img[2]:
                raise SplatError(f"{r.path}: point {pid}'s track refers to a missing image or keypoint")
    r.done()
    s.num_points3D = n


def _checked_mul(n: int, size: int, r: _Reader) -> int:
    if n > r.left() // size + 1:
        raise SplatError(f"{r.path}: truncated or garbled: a record claims {n} entries, more than the file can hold")
    return n * size


# ---- text -------------------------------------------------------------------


def _lines(path: Path) -> list[tuple[int, str]]:
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise SplatError(f"{path}: not UTF-8 text") from None
    except OSError as exc:
        raise SplatError(f"{path}: cannot read: {exc.strerror or exc}") from None
    return [(i + 1, ln.strip()) for i, ln in enumerate(text.splitlines()) if ln.strip() and not ln.lstrip().startswith("#")]


def _nums(tokens: list[str], path: Path, lineno: int, kind=float) -> list:
    try:
        vals = [kind(t) for t in tokens]
    except ValueError:
        raise SplatError(f"{path}: line {lineno}: expected numbers, got {' '.join(tokens)[:60]!r}") from None
    if kind is float:
        _finite(tuple(vals), path, f"line {lineno}")
    return vals


def _check_txt(d: Path, s: ModelSummary) -> None:
    path = d / "cameras.txt"
    for lineno, ln in _lines(path):
        tok = ln.split()
        if len(tok) < 4 or tok[1] not in _MODEL_BY_NAME:
            raise SplatError(f"{path}: line {lineno}: expected `CAMERA_ID MODEL WIDTH HEIGHT PARAMS...`")
        mid, nparams = _MODEL_BY_NAME[tok[1]]
        cid, w, h = _nums([tok[0], tok[2], tok[3]], path, lineno, int)
        params = _nums(tok[4:], path, lineno)
        if len(params) != nparams:
            raise SplatError(f"{path}: line {lineno}: {tok[1]} needs {nparams} parameters, got {len(params)}")
        _check_camera(path, cid, mid, w, h, tuple(params), s)

    path = d / "images.txt"
    # images.txt alternates a pose line and a (possibly empty) keypoint line.
    raw = path.read_text(encoding="utf-8", errors="replace").splitlines()
    body = [(i + 1, ln) for i, ln in enumerate(raw) if not ln.lstrip().startswith("#")]
    k = 0
    while k < len(body):
        lineno, ln = body[k]
        if not ln.strip():
            k += 1
            continue
        tok = ln.split()
        if len(tok) < 10:
            raise SplatError(f"{path}: line {lineno}: expected `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`")
        iid, cid = _nums([tok[0], tok[8]], path, lineno, int)
        _nums(tok[1:8], path, lineno)
        name = " ".join(tok[9:])
        if cid not in s.cameras:
            raise SplatError(f"{path}: line {lineno}: image {name!r} uses camera {cid}, which cameras.txt does not have")
        if iid in s.images:
            raise SplatError(f"{path}: line {lineno}: image id {iid} appears twice")
        check_image_name(name, path)
        pts = body[k + 1][1].split() if k + 1 < len(body) else []
        if len(pts) % 3:
            raise SplatError(f"{path}: line {lineno + 1}: keypoints must come in `X Y POINT3D_ID` triples")
        s.images[iid] = (name, cid, len(pts) // 3)
        k += 2

    path = d / "points3D.txt"
    n = 0
    for lineno, ln in _lines(path):
        tok = ln.split()
        if len(tok) < 8 or (len(tok) - 8) % 2:
            raise SplatError(f"{path}: line {lineno}: expected `POINT3D_ID X Y Z R G B ERROR TRACK...`")
        _nums(tok[1:4], path, lineno)
        track = _nums(tok[8:], path, lineno, int)
        for j in range(0, len(track), 2):
            img = s.images.get(track[j])
            if img is None or not 0 <= track[j + 1] < img[2]:
                raise SplatError(f"{path}: line {lineno}: the track refers to a missing image or keypoint")
        n += 1
    s.num_points3D = n
