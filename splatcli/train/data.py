"""Training data: cameras at the training resolution and their images, cached.

Images are read once, resized to the training resolution (area filter) and kept
as uint8 tensors on the training device, [H, W, 3]; a step converts one to float
(cheaper than keeping float copies of a large capture). Images in the project are
already composited over the scene background by `process`.

Only the training split is ever fitted; the test split is measured.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..camera import Camera, scene_extent
from ..errors import SplatError
from ..project import Project
from ..sfm.model import read_scene


@dataclass
class View:
    camera: Camera  # at the training resolution
    image: Tensor  # [H, W, 3] uint8 on the training device
    viewmat: Tensor  # [4, 4] float32
    K: Tensor  # [3, 3] float32

    def target(self) -> Tensor:  # [H, W, 3] float32 in [0, 1]
        return self.image.to(torch.float32) / 255.0


@dataclass
class TrainData:
    train: list[View]
    test: list[View]
    background: Tensor  # [3] float32 in [0, 1]
    extent: float  # 3DGS "cameras_extent": scales position lr and size thresholds
    points: np.ndarray  # [P, 3] float64 SfM points (may be empty)
    colors: np.ndarray  # [P, 3] uint8
    bounds_min: np.ndarray  # [3] scene box (random initialisation)
    bounds_max: np.ndarray  # [3]


def training_camera(cam: Camera, downscale: float, max_size: int | None) -> Camera:
    """Divide the size by `downscale`, then cap the longest side at `max_size`
    (the same rule eval uses, so it measures at the resolution trained)."""
    c = cam.scaled(1.0 / downscale) if downscale != 1.0 else cam
    if max_size and max(c.width, c.height) > max_size:
        c = c.scaled(max_size / max(c.width, c.height))
    return c


def read_rgb(path: Path, width: int, height: int) -> np.ndarray:  # -> [H, W, 3] uint8
    """An image file as RGB uint8 at width x height (INTER_AREA when shrinking)."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SplatError(f"{path}: cannot read image (missing or not an image)")
    if img.dtype == np.uint16:
        img = (img.astype(np.float32) / 257.0).round().astype(np.uint8)
    elif img.dtype != np.uint8:
        raise SplatError(f"{path}: unsupported image type {img.dtype}")
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    elif img.shape[2] == 4:  # process writes RGB; an RGBA file here means someone added one
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    else:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    if (img.shape[1], img.shape[0]) != (width, height):
        shrink = width < img.shape[1]
        img = cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    return np.ascontiguousarray(img)


def load_train_data(
    project: Project,
    downscale: float,
    max_size: int | None,
    device: torch.device,
    eval_max_views: int = 0,
) -> TrainData:
    """Cameras of the project's splits at the training resolution, images cached."""
    project.require_processed()
    scene = read_scene(project.sparse_dir)
    facts = project.manifest().get("scene") or {}
    splits = project.splits()
    by_name = {c.name: c for c in scene.cameras}
    train_names = [n for n in splits["train"] if n in by_name]
    test_names = [n for n in splits["test"] if n in by_name]
    if not splits["train"] and not splits["test"]:  # no recorded split: every 8th image is held out
        names = sorted(by_name)
        train_names = [n for i, n in enumerate(names) if i % 8 != 0] or names
        test_names = [n for i, n in enumerate(names) if i % 8 == 0 and len(names) > 1]
    if not train_names:
        raise SplatError(f"{project.manifest_path}: the train split names no registered image")
    if eval_max_views and len(test_names) > eval_max_views:
        idx = np.linspace(0, len(test_names) - 1, eval_max_views).round().astype(int)
        test_names = [test_names[i] for i in idx]

    def view(name: str) -> View:
        cam = training_camera(by_name[name], downscale, max_size)
        path = project.images_dir / name
        img = torch.from_numpy(read_rgb(path, cam.width, cam.height)).to(device)
        vm, K = cam.torch(device)
        return View(cam, img, vm, K)

    with ThreadPoolExecutor(max_workers=2) as pool:  # cv2 decodes without the GIL
        train = list(pool.map(view, train_names))
        test = list(pool.map(view, test_names))
    _, extent = scene_extent([v.camera for v in train])
    bg = facts.get("background") or [0.0, 0.0, 0.0]
    lo = np.asarray(facts.get("bounds_min") or _camera_box(scene.cameras)[0], np.float64)
    hi = np.asarray(facts.get("bounds_max") or _camera_box(scene.cameras)[1], np.float64)
    return TrainData(
        train=train,
        test=test,
        background=torch.tensor([float(c) for c in bg], dtype=torch.float32, device=device),
        extent=extent,
        points=scene.points,
        colors=scene.colors,
        bounds_min=lo,
        bounds_max=hi,
    )


def _camera_box(cams: list[Camera]) -> tuple[np.ndarray, np.ndarray]:
    """Fallback scene box when the manifest has none: the camera centres' sphere."""
    mid, r = scene_extent(cams)
    return mid - r, mid + r
