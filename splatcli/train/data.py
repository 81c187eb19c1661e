"""Training data: cameras at the training resolution and their images, cached.

Images are read once, resized to the training resolution (area filter) and kept
as uint8 tensors on the training device, [H, W, 3]; a step converts one to float
(cheaper than keeping float copies of a large capture). Images in the project are
already composited over the scene background by `process`.

Images and masks come through eval/score.load_target, the rule the scores use
too (--mask-mode, Project.mask_mode): "ignore" keeps each view's mask beside its
image ([H, W] bool, resized like the image, then cut at half); "background" with
mask files paints the masked pixels in the background colour once, at load (with
alpha masks the images already are); "off" loads none, and a view without a mask
costs nothing more.

Only the training split is ever fitted; the test split is measured.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ..camera import Camera, scene_extent
from ..errors import SplatError
from ..eval.score import load_target
from ..project import Project
from ..render.projection import in_frustum
from ..sfm.colmap import read_project_scene


@dataclass
class TrainView:
    camera: Camera  # at the training resolution
    image: Tensor  # [H, W, 3] uint8 on the training device
    viewmat: Tensor  # [4, 4] float32
    K: Tensor  # [3, 3] float32
    keep: Tensor | None = None  # [H, W] bool: pixels the loss and the scores see (--mask-mode ignore); None: all
    sparse: Tensor | None = None  # [M, 3] float32 world points this view observed in SfM (--depth-weight); None: none

    _scaled: dict[float, TrainView] = field(default_factory=dict, repr=False, compare=False)

    def target(self) -> Tensor:  # [H, W, 3] float32 in [0, 1]
        return self.image.to(torch.float32) / 255.0

    def at_scale(self, scale: float) -> TrainView:
        """This view at `scale` times the training resolution (area-filtered image,
        K scaled with the size). Coarse-to-fine training renders these. One coarse level
        is cached at a time, since the schedule only rises: at most 0.77x the images'
        memory more (level 7/8), and none once training is at full resolution."""
        if scale >= 1.0:
            self._scaled.clear()
            return self
        if scale not in self._scaled:
            self._scaled.clear()
            cam = self.camera.scaled(scale)
            img = F.interpolate(self.image.permute(2, 0, 1)[None].to(torch.float32), size=(cam.height, cam.width),
                                mode="area")[0].permute(1, 2, 0).round().clamp(0, 255).to(torch.uint8).contiguous()
            vm, K = cam.torch(self.image.device)
            keep = None
            if self.keep is not None:  # the same area filter, cut at half
                keep = F.interpolate(self.keep[None, None].to(torch.float32), size=(cam.height, cam.width),
                                     mode="area")[0, 0] >= 0.5
            self._scaled[scale] = TrainView(cam, img, vm, K, keep, self.sparse)
        return self._scaled[scale]


@torch.no_grad()
def views_seeing(views: list[TrainView], means: Tensor) -> Tensor:  # means [N, 3] -> [N] int
    """How many of `views` hold each point in their frustum (in front of the rasterizer's
    near plane, inside the image)."""
    count = torch.zeros(means.shape[0], dtype=torch.int32, device=means.device)
    for v in views:
        count += in_frustum(means, v.viewmat, v.K, v.camera.width, v.camera.height)[2].to(torch.int32)
    return count


def subset(items: list, k: int) -> list:
    """`k` evenly spaced items (all when k <= 0 or there are fewer)."""
    if k <= 0 or len(items) <= k:
        return list(items)
    return [items[i] for i in np.linspace(0, len(items) - 1, k).round().astype(int)]


@dataclass
class TrainData:
    train: list[TrainView]
    test: list[TrainView]
    background: Tensor  # [3] float32 in [0, 1]
    extent: float  # 3DGS "cameras_extent": scales position lr and size thresholds
    center: np.ndarray  # [3] the training cameras' centre (camera.scene_extent)
    points: np.ndarray  # [P, 3] float64 SfM points (may be empty)
    colors: np.ndarray  # [P, 3] uint8
    bounds_min: np.ndarray  # [3] scene box (random initialisation)
    bounds_max: np.ndarray  # [3]
    mask_mode: str = "off"  # resolved: ignore | background | off


def load_train_data(
    project: Project,
    downscale: float,
    max_size: int | None,
    device: torch.device,
    eval_max_views: int = 0,
    mask_mode: str = "auto",
) -> TrainData:
    """Cameras of the project's splits at the training resolution, images (and masks,
    per `mask_mode`: module docstring) cached."""
    scene = read_project_scene(project)
    facts = project.manifest().get("scene") or {}
    bg = project.background() or (0.0, 0.0, 0.0)
    by_name = {c.name: c for c in scene.cameras}
    splits = project.splits(list(by_name))  # none recorded: the hold-out rule (project.holdout_split)
    train_names = [n for n in splits["train"] if n in by_name]
    test_names = [n for n in splits["test"] if n in by_name]
    if not train_names:
        raise SplatError(f"{project.manifest_path}: the train split names no registered image")
    test_names = subset(test_names, eval_max_views)
    mode = project.mask_mode(mask_mode)

    def view(name: str) -> TrainView:
        cam = by_name[name].at_resolution(downscale, max_size)
        rgb, keep = load_target(project, name, (cam.width, cam.height), bg, mode)
        img = torch.from_numpy(np.ascontiguousarray(rgb)).to(device)
        vm, K = cam.torch(device)
        seen = scene.observed.get(name)
        sparse = (torch.from_numpy(scene.points[seen]).to(device=device, dtype=torch.float32)
                  if seen is not None and len(seen) else None)
        return TrainView(cam, img, vm, K, torch.from_numpy(keep).to(device) if keep is not None else None, sparse)

    with ThreadPoolExecutor(max_workers=2) as pool:  # cv2 decodes without the GIL
        train = list(pool.map(view, train_names))
        test = list(pool.map(view, test_names))
    center, extent = scene_extent([v.camera for v in train])
    lo = np.asarray(facts.get("bounds_min") or _camera_box(scene.cameras)[0], np.float64)
    hi = np.asarray(facts.get("bounds_max") or _camera_box(scene.cameras)[1], np.float64)
    return TrainData(
        train=train,
        test=test,
        background=torch.tensor([float(c) for c in bg], dtype=torch.float32, device=device),
        extent=extent,
        center=center,
        points=scene.points,
        colors=scene.colors,
        bounds_min=lo,
        bounds_max=hi,
        mask_mode=mode,
    )


def _camera_box(cams: list[Camera]) -> tuple[np.ndarray, np.ndarray]:
    """Fallback scene box when the manifest has none: the camera centres' sphere."""
    mid, r = scene_extent(cams)
    return mid - r, mid + r
