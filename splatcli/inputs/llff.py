"""Read LLFF's `poses_bounds.npy` (the forward-facing NeRF captures: fern, flower, ...).

The file is a float array of N rows of 17, one row per image in the sorted order of
the images folder. A row is a 3x5 matrix, row-major, then two depths:

    [ R (3x3) | c (3x1) | (h, w, f) ]   near, far

R's columns are the camera's down, right and back axes in the world ([down, right,
back], LLFF's convention) and c is the camera's centre: a camera-to-world pose. h, w
are the image size the poses were made at, f its focal length in pixels (the
principal point is the centre). near and far bound the depths the image sees.

We convert to our OpenCV world-to-camera `viewmat` (x right, y down, z forward) and
keep the world frame. Images come from `images/`, else the sharpest `images_N/`
the capture ships (LLFF's loaders read `images_N/` for a factor N: the same poses,
intrinsics divided by N); `Frame.focal` is scaled to the images actually read.

No pycolmap here: this module only parses and validates.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import SplatError

POSES_NAME = "poses_bounds.npy"
# 17 float64 per image: 1 MiB holds ~7,700 images, far beyond any LLFF capture.
MAX_POSES_BYTES = 16 * 1024 * 1024
_IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")  # what LLFF's loaders read (case-insensitive)

# LLFF camera axes [down, right, back] -> OpenCV [right, down, forward]: R_cv = R_llff @ _LLFF_TO_CV.
_LLFF_TO_CV = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


@dataclass(frozen=True)
class LlffFrame:
    source: Path  # the image file
    name: str  # its name in the project
    viewmat: np.ndarray  # [4, 4] float64 world-to-camera, OpenCV axes
    height: float  # pixels, as the file says (of the full-resolution images)
    width: float
    focal: float  # pixels, for an image `width` pixels wide
    near: float  # depths, world units
    far: float


@dataclass
class LlffScene:
    frames: list[LlffFrame]  # in the file's (= the sorted images') order
    images_dir: Path
    notes: list[str]


def find_poses(path: Path) -> Path | None:
    """The poses_bounds.npy `path` names or holds, or None."""
    if path.is_file():
        return path if path.name == POSES_NAME else None
    if path.is_dir() and (path / POSES_NAME).is_file():
        return path / POSES_NAME
    return None


def _factor(folder: Path) -> int | None:
    m = re.fullmatch(r"images(?:_(\d+))?", folder.name)
    if m is None or not folder.is_dir():
        return None
    return int(m.group(1)) if m.group(1) else 1


def images_folder(root: Path) -> Path | None:
    """`images/`, else the `images_N/` of the smallest N (the most pixels)."""
    found = [(f, p) for p in root.iterdir() if (f := _factor(p)) is not None and f > 0] if root.is_dir() else []
    return min(found)[1] if found else None


def list_images(folder: Path) -> list[Path]:
    """The images of an LLFF folder in the order its poses are listed (sorted names)."""
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in _IMAGE_SUFFIXES
                  and not p.name.startswith("."))


def read_poses_bounds(path: Path) -> np.ndarray:  # [N, 17] float64
    """The array of a poses_bounds.npy, checked: N x 17 finite numbers, no pickles."""
    path = Path(path)
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise SplatError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if size > MAX_POSES_BYTES:
        raise SplatError(f"{path}: {size} bytes, more than the {MAX_POSES_BYTES} allowed for a poses file")
    try:
        with open(path, "rb") as f:
            a = np.load(f, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:  # pickles, truncation, not an .npy at all
        why = " ".join(str(exc).split())[:120] or type(exc).__name__
        raise SplatError(f"{path}: not a readable .npy array ({why})") from None
    if not isinstance(a, np.ndarray) or a.dtype.kind not in "fiu":
        raise SplatError(f"{path}: holds {getattr(a, 'dtype', type(a).__name__)} values, expected numbers")
    if a.ndim != 2 or a.shape[1] != 17 or a.shape[0] < 1:
        raise SplatError(f"{path}: array of shape {tuple(a.shape)}, expected (N, 17): one row of 3x5 pose "
                         "and near, far per image")
    a = a.astype(np.float64)
    bad = np.flatnonzero(~np.isfinite(a).all(1))
    if len(bad):
        raise SplatError(f"{path}: row {int(bad[0])} holds NaN or infinity")
    return a


def _viewmat(m: np.ndarray, where: str) -> np.ndarray:  # [3, 4] LLFF camera-to-world -> [4, 4]
    R = m[:, :3]
    U, S, Vt = np.linalg.svd(R)
    if S.min() < 1e-6 * max(S.max(), 1e-300) or abs(S.max() / S.min() - 1.0) > 1e-2:
        raise SplatError(f"{where}: the pose's 3x3 part is not a rotation (singular values "
                         f"{', '.join(f'{s:.3g}' for s in S)})")
    R = U @ Vt
    if np.linalg.det(R) < 0:
        raise SplatError(f"{where}: the pose is a reflection, not a rotation")
    R_cv = R @ _LLFF_TO_CV  # camera-to-world, OpenCV axes
    v = np.eye(4)
    v[:3, :3] = R_cv.T
    v[:3, 3] = -R_cv.T @ m[:, 3]
    return v


def read_llff(path: Path) -> LlffScene:
    """Parse a capture's poses_bounds.npy and pair its rows with the images.
    Raises SplatError naming the file for anything malformed or inconsistent."""
    path = Path(path)
    root = path.parent
    a = read_poses_bounds(path)
    folder = images_folder(root)
    if folder is None:
        raise SplatError(f"{path}: no images/ (or images_N/) folder beside it")
    images = list_images(folder)
    if len(images) != len(a):
        raise SplatError(f"{path}: {len(a)} poses but {len(images)} images in {folder} "
                         "(LLFF pairs them in sorted order, so the counts must agree)")
    notes = []
    if folder.name != "images":
        notes.append(f"images read from {folder.name}/ (no images/ folder)")
    frames = []
    for i, (row, img) in enumerate(zip(a, images)):
        where = f"{path}: row {i} ({img.name})"
        m = row[:15].reshape(3, 5)
        h, w, f = (float(v) for v in m[:, 4])
        near, far = float(row[15]), float(row[16])
        if not (h >= 1 and w >= 1):
            raise SplatError(f"{where}: image size {w:g} x {h:g} must be positive")
        if not f > 0:
            raise SplatError(f"{where}: focal length {f:g} must be positive")
        if not 0 < near < far:
            raise SplatError(f"{where}: near {near:g} and far {far:g} bounds must satisfy 0 < near < far")
        frames.append(LlffFrame(source=img, name=img.name, viewmat=_viewmat(m[:, :4], where), height=h, width=w,
                                focal=f, near=near, far=far))
    return LlffScene(frames=frames, images_dir=folder, notes=notes)


def scaled_focal(frame: LlffFrame, width: int, height: int, where: str) -> float:
    """The focal length for the image as read (`width` x `height`): the file's,
    scaled when the image is a uniformly rescaled copy (images_N)."""
    sx, sy = width / frame.width, height / frame.height
    if abs(sx - sy) > 0.02 * max(sx, sy):
        raise SplatError(f"{where}: image is {width}x{height} but poses_bounds.npy says "
                         f"{frame.width:g}x{frame.height:g} (not a uniform rescale)")
    return frame.focal * sx


def to_poses_bounds(viewmats: list[np.ndarray], hwf: list[tuple[float, float, float]],
                    bounds: list[tuple[float, float]]) -> np.ndarray:  # [N, 17]
    """The inverse of `read_llff`'s conversion: OpenCV world-to-camera matrices [4, 4],
    (h, w, f) and (near, far) per image -> LLFF's rows (for tests and benchmarks)."""
    rows = []
    for v, (h, w, f), (near, far) in zip(viewmats, hwf, bounds):
        R_cv = v[:3, :3].T  # camera-to-world
        c = -R_cv @ v[:3, 3]
        m = np.concatenate([R_cv @ _LLFF_TO_CV.T, c[:, None], np.array([[h], [w], [f]])], 1)
        rows.append(np.concatenate([m.reshape(-1), [near, far]]))
    return np.asarray(rows, np.float64)
