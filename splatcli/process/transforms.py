"""A transforms.json (nerfstudio, instant-ngp, Blender): poses imported as they are,
through the one reader inputs/transforms.py."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..events import Stages
from ..inputs.transforms import read_transforms
from ..project import Project
from ..sfm import colmap
from ..sfm.colmap import CameraSpec
from .config import ProcessConfig
from .dataset import Dataset
from .detect import InputSpec
from .masks import stage_all
from .posed import finish_posed, stage_frames


def from_transforms(spec: InputSpec, stage: Path, cfg: ProcessConfig,
                     background: tuple[float, float, float] | None, run: Stages) -> Dataset:
    assert spec.transforms is not None
    work = stage / "work"
    scene = read_transforms(spec.transforms)
    staged, frames, bad = stage_frames(scene.frames, work, run, cfg, where=spec.transforms, what="the listed images",
                                       background=background)
    specs = []
    for s, f in zip(staged, frames):
        model_name, params = f.intrinsics.resolve(s.width, s.height, f"{spec.transforms}: {f.source.name}")
        specs.append(CameraSpec(s.name, s.width, s.height, model_name, params, f.viewmat))
    # Notes once the input is known to be usable: a failed run says one line.
    for n in scene.notes:
        run.note(n)
    if scene.missing:
        run.note(f"{len(scene.missing)} image(s) listed in {spec.transforms.name} do not exist and were skipped "
                 f"(first: {scene.missing[0]})", "warning")
    for b in bad:
        run.note(f"skipped {b}", "warning")
    points = colors = None
    if scene.ply_path is not None:
        points, colors = _read_ply_points(scene.ply_path, run)
    model = colmap.build_model(specs, points, colors)
    found = {f.name: f.mask for f in scene.frames if f.mask is not None}
    mask_source = stage_all(found, staged, work, run, invert=cfg.invert_masks, where=None)
    has_masks = mask_source is not None
    undistorted, facts = finish_posed(model, staged, work, Project(stage), cfg, run, mask_source=mask_source)
    kept = {s.name for s in staged}
    test = sorted(f.name for f in scene.frames if f.split == "test" and f.name in kept) if scene.has_test_split else None
    bg = background
    if bg is None and mask_source == "alpha":
        bg = (1.0, 1.0, 1.0)
    return Dataset(registered=len(staged), total=len(scene.frames) + len(scene.missing), undistorted=undistorted,
                    masks=has_masks, mask_source=mask_source, test=test or None, background=bg, skipped=bad,
                    missing=len(scene.missing), **facts)


def _read_ply_points(path: Path, run: Stages) -> tuple[np.ndarray | None, np.ndarray | None]:
    """x, y, z and red, green, blue of a point cloud shipped with a transforms file."""
    try:
        from plyfile import PlyData

        v = PlyData.read(str(path))["vertex"]
        pts = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64)
        if all(k in v.data.dtype.names for k in ("red", "green", "blue")):
            cols = np.stack([v["red"], v["green"], v["blue"]], 1).astype(np.uint8)
        else:
            cols = np.full((len(pts), 3), 128, np.uint8)
        ok = np.isfinite(pts).all(1)
        return pts[ok], cols[ok]
    except Exception as exc:  # a broken optional extra: import the poses anyway
        run.note(f"{path}: cannot read the point cloud ({type(exc).__name__}); no sparse points", "warning")
        return None, None
