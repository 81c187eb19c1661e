"""What kind of input did the user give `process`?

    folder of images      photos/*.jpg, or a folder with an images/ subfolder
    video                 capture.mp4 (any extension OpenCV commonly reads)
    COLMAP workspace      sparse/0/ or sparse/ (.bin or .txt) beside images/,
                          or the model folder itself
    transforms.json       nerfstudio, instant-ngp; transforms_train.json (+ _test,
                          _val) for NeRF Blender scenes; the file or its folder
    LLFF                  poses_bounds.npy beside images/ (or images_N/); the file or its folder
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..errors import SplatError
from ..inputs.images import is_image_name
from ..inputs.llff import POSES_NAME, find_poses
from ..inputs.transforms import find_transforms
from ..sfm.colmap_files import model_format
from .video import is_video_name

INPUT_TYPES = ("auto", "images", "video", "colmap", "transforms", "llff")


@dataclass(frozen=True)
class InputSpec:
    kind: str  # "images" | "video" | "colmap" | "transforms" | "llff"
    path: Path  # the input as given
    root: Path  # the folder file paths inside the input may not leave
    images_dir: Path | None = None  # images, colmap
    model_dir: Path | None = None  # colmap
    transforms: Path | None = None  # transforms
    poses: Path | None = None  # llff: the poses_bounds.npy


def find_colmap_model(path: Path) -> tuple[Path, Path] | None:
    """(model folder, images folder) of a COLMAP workspace, or None."""
    for model in (path / "sparse" / "0", path / "sparse"):
        if model.is_dir() and model_format(model):
            return model, path / "images"
    if model_format(path):  # the model folder itself: .../sparse/0 or .../sparse
        for ws in (path.parent.parent, path.parent):
            if (ws / "images").is_dir():
                return path, ws / "images"
        return path, path.parent / "images"
    return None


def _has_images(folder: Path) -> bool:
    return folder.is_dir() and any(is_image_name(p) and p.is_file() for p in folder.iterdir())


def detect_input(path: Path, input_type: str = "auto") -> InputSpec:
    path = Path(path)
    if input_type not in INPUT_TYPES:
        raise SplatError(f"--input-type {input_type!r}: expected one of {', '.join(INPUT_TYPES)}")
    if not path.exists():
        raise SplatError(f"{path}: no such file or folder")
    if input_type == "auto":
        input_type = _guess(path)
    if input_type == "video":
        if not path.is_file():
            raise SplatError(f"{path}: --input-type video needs a video file, not a folder")
        return InputSpec("video", path, path.parent)
    if input_type == "transforms":
        tf = find_transforms(path) if path.is_dir() else path
        if tf is None or not tf.is_file():
            raise SplatError(f"{path}: no transforms.json or transforms_train.json here")
        return InputSpec("transforms", path, tf.parent, transforms=tf)
    if input_type == "llff":
        pb = find_poses(path)
        if pb is None:
            raise SplatError(f"{path}: no {POSES_NAME} here")
        return InputSpec("llff", path, pb.parent, poses=pb)
    if input_type == "colmap":
        found = find_colmap_model(path) if path.is_dir() else None
        if found is None:
            raise SplatError(
                f"{path}: no COLMAP model (looked for sparse/0 and sparse with cameras.bin or cameras.txt)"
            )
        model, images = found
        if not images.is_dir():
            raise SplatError(f"{images}: the COLMAP workspace has no images folder")
        return InputSpec("colmap", path, images, images_dir=images, model_dir=model)
    # images
    if not path.is_dir():
        if is_image_name(path):
            raise SplatError(f"{path}: a single image; structure from motion needs a folder of at least 2 photos")
        raise SplatError(
            f"{path}: not a folder of images, a video, a COLMAP workspace or a transforms.json "
            "(use --input-type to say which)"
        )
    images = path / "images" if (path / "images").is_dir() and not _has_images(path) else path
    return InputSpec("images", path, images, images_dir=images)


def _guess(path: Path) -> str:
    if path.is_file():
        if path.suffix.lower() == ".json":
            return "transforms"
        if path.name == POSES_NAME:
            return "llff"
        if is_video_name(path):
            return "video"
        return "images"  # refused with a clear message in detect_input
    if find_colmap_model(path) is not None:
        return "colmap"
    if find_transforms(path) is not None:
        return "transforms"
    if find_poses(path) is not None:
        return "llff"
    return "images"


__all__ = ["INPUT_TYPES", "InputSpec", "detect_input", "find_colmap_model"]
