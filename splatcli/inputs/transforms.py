"""Read `transforms.json` (nerfstudio, instant-ngp, NeRF Blender scenes).

The file stores camera-to-world poses in the OpenGL convention (x right, y up,
z backwards). We convert them to our OpenCV world-to-camera `viewmat`
(x right, y down, z forward) and keep the world frame as it is.

Intrinsics come per frame or globally (per-frame keys win): `fl_x`, `fl_y`,
`cx`, `cy`, `w`, `h`, or only `camera_angle_x` (Blender), plus distortion
`k1 k2 k3 k4 p1 p2`. The image size may be unknown until the image is read,
so `Intrinsics.resolve(width, height)` finishes the job then.

No pycolmap here: this module only parses and validates.
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import SplatError
from ..files.atomic import read_json_file
from ..files.safepath import safe_join

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG", ".tif", ".tiff", ".bmp", ".webp")
# A transforms file is kilobytes per frame; 256 MiB covers ~500k frames.
MAX_TRANSFORMS_BYTES = 256 * 1024 * 1024

# OpenGL camera axes (y up, z back) -> OpenCV camera axes (y down, z forward).
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class Intrinsics:
    """Camera intrinsics as written in the file; `None` where the file is silent."""

    fl_x: float | None
    fl_y: float | None
    cx: float | None
    cy: float | None
    w: float | None
    h: float | None
    angle_x: float | None
    angle_y: float | None
    k: tuple[float, float, float, float]  # k1..k4
    p: tuple[float, float]  # p1, p2
    fisheye: bool

    @property
    def distorted(self) -> bool:
        return self.fisheye or any(v != 0.0 for v in self.k + self.p)

    def resolve(self, width: int, height: int, where: str) -> tuple[str, list[float]]:
        """COLMAP model name and params for an image of `width` x `height` pixels.

        When the file states `w`/`h` and the image is a uniformly rescaled copy
        (e.g. a downscaled folder), the intrinsics are scaled to match.
        """
        sx = sy = 1.0
        if self.w is not None and self.h is not None:
            sx, sy = width / self.w, height / self.h
            if abs(sx - sy) > 0.02 * max(sx, sy):
                raise SplatError(
                    f"{where}: image is {width}x{height} but the transforms file says "
                    f"{self.w:g}x{self.h:g} (not a uniform rescale)"
                )
        if self.fl_x is not None:
            fx = self.fl_x * sx
            fy = (self.fl_y if self.fl_y is not None else self.fl_x) * sy
        elif self.angle_x is not None:
            fx = 0.5 * width / math.tan(0.5 * self.angle_x)
            fy = 0.5 * height / math.tan(0.5 * self.angle_y) if self.angle_y is not None else fx
        else:  # checked when parsing; kept for type-checkers
            raise SplatError(f"{where}: no focal length (fl_x or camera_angle_x)")
        cx = self.cx * sx if self.cx is not None else width / 2.0
        cy = self.cy * sy if self.cy is not None else height / 2.0
        k1, k2, k3, k4 = self.k
        p1, p2 = self.p
        if self.fisheye:
            return "OPENCV_FISHEYE", [fx, fy, cx, cy, k1, k2, k3, k4]
        if k3 != 0.0 or k4 != 0.0:
            return "FULL_OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, 0.0, 0.0]
        if any(v != 0.0 for v in (k1, k2, p1, p2)):
            return "OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2]
        return "PINHOLE", [fx, fy, cx, cy]


@dataclass(frozen=True)
class Frame:
    """One image listed in a transforms file."""

    source: Path | None  # the image file (None: absent, allowed when only cameras are read)
    name: str  # name in the project's images/ (for cameras only: the file_path as written)
    split: str  # "train" or "test"
    viewmat: np.ndarray  # [4, 4] float64 world-to-camera, OpenCV axes
    intrinsics: Intrinsics
    file_path: str = ""  # as written in the file
    mask: Path | None = None  # nerfstudio's per-frame mask_path, resolved (process only)


@dataclass
class TransformsScene:
    frames: list[Frame]  # sorted by name
    files: list[Path]  # the JSON files read
    missing: list[str]  # file_path values whose file does not exist
    has_test_split: bool  # the input defines its own held-out images
    ply_path: Path | None  # sparse points shipped with the file (nerfstudio), if any
    notes: list[str]


def find_transforms(path: Path) -> Path | None:
    """The transforms file `path` names or holds, or None."""
    if path.is_file():
        return path if path.suffix.lower() == ".json" and path.name.startswith("transforms") else None
    if path.is_dir():
        for name in ("transforms_train.json", "transforms.json"):
            if (path / name).is_file():
                return path / name
    return None


def _sources(path: Path, images: bool, notes: list[str]) -> list[tuple[Path, str]]:
    """The files to read with their split: a Blender `transforms_train.json` brings its test (or else val) sibling."""
    sources = [(path, "train")]
    if images and path.name == "transforms_train.json":
        test, val = path.parent / "transforms_test.json", path.parent / "transforms_val.json"
        if test.is_file():
            sources.append((test, "test"))
            if val.is_file():
                notes.append(f"{val.name} ignored: {test.name} provides the held-out images")
        elif val.is_file():
            sources.append((val, "test"))
    return sources


@dataclass
class _Raw:
    """What the files hold, before any frame is checked."""

    frames: list[tuple[Path, int, dict[str, Any], dict[str, Any], str]]  # (file, index, frame, file's object, split)
    ply_path: Path | None
    test_set: set[str] | None  # nerfstudio's own held-out file names, where the main file lists them


def _read_files(path: Path, sources: list[tuple[Path, str]], notes: list[str]) -> _Raw:
    raw = _Raw([], None, None)
    for src, split in sources:
        data = read_json_file(src, "transforms file", max_bytes=MAX_TRANSFORMS_BYTES)
        if not isinstance(data, dict):
            raise SplatError(f"{src}: transforms file must hold a JSON object, not {type(data).__name__}")
        frames = data.get("frames")
        if not isinstance(frames, list) or not frames:
            raise SplatError(f"{src}: transforms file has no `frames` list")
        for i, fr in enumerate(frames):
            if not isinstance(fr, dict):
                raise SplatError(f"{src}: frame {i} is not a JSON object")
            raw.frames.append((src, i, fr, data, split))
        if src != path:
            continue
        if isinstance(data.get("ply_file_path"), str):
            raw.ply_path = safe_join(path.parent, data["ply_file_path"], src, "ply_file_path")
            if not raw.ply_path.is_file():
                notes.append(f"{src.name}: ply_file_path {data['ply_file_path']} not found; no sparse points")
                raw.ply_path = None
        # nerfstudio may name its own split inside transforms.json
        lists = {key: {os.path.normpath(v) for v in data[key]} for key in ("test_filenames", "val_filenames")
                 if isinstance(data.get(key), list) and all(isinstance(v, str) for v in data[key])}
        if len(sources) == 1:
            raw.test_set = lists.get("test_filenames") or lists.get("val_filenames") or None
    return raw


def _parse_frames(root: Path, raw: _Raw, images: bool) -> tuple[list[Frame], list[str], int]:
    """The frames (images=True: those whose image exists, each image once; names to be given), the
    file_path values whose image is missing, and how many frames listed an image again."""
    frames: list[Frame] = []
    missing: list[str] = []
    seen: set[Path] = set()
    duplicates = 0
    for src, i, fr, data, split in raw.frames:
        where = f"{src}: frame {i}"
        fp = fr.get("file_path")
        if not isinstance(fp, str) or not fp.strip():
            raise SplatError(f"{where} has no file_path")
        image = _resolve_image(root, fp, src, where)
        if images:
            if image is None:
                missing.append(fp)
                continue
            if image in seen:
                duplicates += 1
                continue
            seen.add(image)
        viewmat, intr = _viewmat(fr.get("transform_matrix"), where), _intrinsics(fr, data, where)
        if not images:
            frames.append(Frame(source=image, name=fp, split=split, viewmat=viewmat, intrinsics=intr, file_path=fp))
            continue
        mask = _mask(root, fr.get("mask_path"), src, where, fp)
        if raw.test_set is not None:
            rel = os.path.normpath(os.path.relpath(image, root))
            split = "test" if rel in raw.test_set or os.path.normpath(fp) in raw.test_set else "train"
        frames.append(Frame(source=image, name="", split=split, viewmat=viewmat, intrinsics=intr, file_path=fp,
                            mask=mask))
    return frames, missing, duplicates


def read_transforms(path: Path, *, images: bool = True) -> TransformsScene:
    """Parse a transforms file: the one reader of `process` and `render --cameras`.

    images=True (process): the listed images must exist (missing ones are counted,
    frames listing one image twice are imported once) and a Blender
    `transforms_train.json` brings its test/val siblings as the held-out split.
    images=False (render --cameras): only the cameras are wanted; every frame is
    kept in file order, with `source` None when its image is absent.
    Raises SplatError naming the file for anything malformed, and (images=True)
    when no listed image exists.
    """
    path = Path(path)
    notes: list[str] = []
    sources = _sources(path, images, notes)
    raw = _read_files(path, sources, notes)
    frames, missing, duplicates = _parse_frames(path.parent, raw, images)
    if not images:
        return TransformsScene(frames=frames, files=[path], missing=[], has_test_split=False, ply_path=None,
                               notes=notes)
    if duplicates:
        notes.append(f"{duplicates} duplicate frame(s) listed twice were imported once")
    if not frames:
        raise SplatError(
            f"{path}: none of the {len(raw.frames)} listed images exists (first: {raw.frames[0][2].get('file_path')})"
        )
    names = _unique_names([f.source for f in frames], path.parent)
    frames = sorted((dataclasses.replace(f, name=name) for f, name in zip(frames, names)), key=lambda f: f.name)
    has_test = len(sources) > 1 or raw.test_set is not None
    if has_test and not any(f.split == "test" for f in frames):
        has_test = False
        notes.append("the input's test split has no existing images; holding out every 8th image instead")
    return TransformsScene(frames=frames, files=[s for s, _ in sources], missing=missing, has_test_split=has_test,
                           ply_path=raw.ply_path, notes=notes)


def _mask(root: Path, mask_path: Any, src: Path, where: str, image: str) -> Path | None:
    """A frame's `mask_path` (nerfstudio), which must name an existing file."""
    if mask_path is None:
        return None
    if not isinstance(mask_path, str) or not mask_path.strip():
        raise SplatError(f"{where}: mask_path must be a file name")
    p = safe_join(root, mask_path, src, "mask_path")
    if not p.is_file():
        raise SplatError(f"{p}: no such file (the mask_path of {image} in {src.name})")
    return p


def _resolve_image(root: Path, file_path: str, src: Path, where: str) -> Path | None:
    p = safe_join(root, file_path, src, "file_path")
    if p.is_file():
        return p
    if p.suffix.lower() not in {s.lower() for s in IMAGE_SUFFIXES}:
        for suf in IMAGE_SUFFIXES:  # Blender scenes omit the extension
            q = p.with_name(p.name + suf)
            if q.is_file():
                return q
    return None


def _num(v: Any, where: str, key: str) -> float | None:
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise SplatError(f"{where}: `{key}` must be a finite number, got {v!r}")
    return float(v)


def _intrinsics(frame: dict[str, Any], data: dict[str, Any], where: str) -> Intrinsics:
    def get(key: str) -> float | None:
        if key in frame:
            return _num(frame[key], where, key)
        return _num(data.get(key), where, key)

    fl_x, fl_y, angle_x = get("fl_x"), get("fl_y"), get("camera_angle_x")
    if fl_x is None and angle_x is None:
        raise SplatError(f"{where}: no focal length (needs `fl_x` or `camera_angle_x`)")
    if (fl_x is not None and fl_x <= 0) or (angle_x is not None and not 0 < angle_x < math.pi):
        raise SplatError(f"{where}: focal length must be positive (fl_x={fl_x}, camera_angle_x={angle_x})")
    w, h = get("w"), get("h")
    if (w is None) != (h is None) or (w is not None and (w <= 0 or h <= 0)):
        raise SplatError(f"{where}: `w` and `h` must both be given and positive")
    model = frame.get("camera_model", data.get("camera_model", "OPENCV"))
    if not isinstance(model, str) or model.upper() not in ("OPENCV", "PINHOLE", "OPENCV_FISHEYE", "SIMPLE_PINHOLE"):
        raise SplatError(f"{where}: camera_model {model!r} is not supported (OPENCV, OPENCV_FISHEYE or PINHOLE)")
    fisheye = model.upper() == "OPENCV_FISHEYE" or bool(frame.get("is_fisheye", data.get("is_fisheye", False)))
    k = tuple(get(f"k{i}") or 0.0 for i in range(1, 5))
    p = tuple(get(f"p{i}") or 0.0 for i in range(1, 3))
    angle_y = get("camera_angle_y") if fl_x is None else None
    return Intrinsics(
        fl_x=fl_x, fl_y=fl_y, cx=get("cx"), cy=get("cy"), w=w, h=h,
        angle_x=angle_x, angle_y=angle_y, k=k, p=p, fisheye=fisheye,  # type: ignore[arg-type]
    )


def _viewmat(m: Any, where: str) -> np.ndarray:  # [4, 4]
    """OpenGL camera-to-world (3x4 or 4x4) -> OpenCV world-to-camera 4x4."""
    try:
        a = np.asarray(m, dtype=np.float64)
    except (TypeError, ValueError):
        raise SplatError(f"{where}: transform_matrix is not a matrix of numbers") from None
    if m is None or a.shape not in ((4, 4), (3, 4)) or not np.isfinite(a).all():
        raise SplatError(f"{where}: transform_matrix must be a finite 4x4 (or 3x4) matrix")
    c2w = np.eye(4)
    c2w[:3, :4] = a[:3, :4]
    # Some writers leave a scale in the rotation; keep the closest rotation.
    U, S, Vt = np.linalg.svd(c2w[:3, :3])
    if S.min() < 1e-6 * max(S.max(), 1e-300):
        raise SplatError(f"{where}: transform_matrix has a degenerate rotation")
    R = U @ Vt
    if np.linalg.det(R) < 0:
        raise SplatError(f"{where}: transform_matrix is a reflection, not a rotation")
    c2w[:3, :3] = R
    c2w_cv = c2w @ _GL_TO_CV
    w2c = np.eye(4)
    w2c[:3, :3] = c2w_cv[:3, :3].T
    w2c[:3, 3] = -c2w_cv[:3, :3].T @ c2w_cv[:3, 3]
    return w2c


def _unique_names(images: list[Path], root: Path) -> list[str]:
    """Base names when they are unique, else the path below `root` with '/' -> '_'."""
    base = [p.name for p in images]
    if len(set(base)) == len(base):
        return base
    out = []
    for p in images:
        try:
            rel = p.relative_to(root)
        except ValueError:
            rel = Path(p.name)
        out.append("_".join(rel.parts))
    return out
