"""An LLFF capture (poses_bounds.npy beside images/): poses imported through the one
reader inputs/llff.py, points triangulated from the photos (posed.py), the scene box
from the near and far bounds when no points come out."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import Camera
from ..events import Stages
from ..inputs.llff import read_llff, scaled_focal
from ..project import Project
from ..sfm import colmap
from ..sfm.colmap import CameraSpec
from .bounds import depth_bounds
from .config import ProcessConfig
from .dataset import Dataset
from .detect import InputSpec
from .masks import find_masks_dir, mask_file, stage_all
from .posed import finish_posed, stage_frames


def from_llff(spec: InputSpec, stage: Path, cfg: ProcessConfig, background: tuple[float, float, float] | None,
              run: Stages) -> Dataset:
    assert spec.poses is not None
    work = stage / "work"
    scene = read_llff(spec.poses)
    staged, frames, bad = stage_frames(scene.frames, work, run, cfg, where=scene.images_dir,
                                       what="the capture's images", background=background)
    specs, cams = [], []
    for s, f in zip(staged, frames):
        focal = scaled_focal(f, s.width, s.height, f"{spec.poses}: {s.name}")
        params = [focal, focal, s.width / 2.0, s.height / 2.0]
        specs.append(CameraSpec(s.name, s.width, s.height, "PINHOLE", params, f.viewmat))
        K = np.array([[focal, 0.0, s.width / 2.0], [0.0, focal, s.height / 2.0], [0.0, 0.0, 1.0]])
        cams.append(Camera(s.name, s.width, s.height, K, f.viewmat))
    for n in scene.notes:
        run.note(n)
    for b in bad:
        run.note(f"skipped {b}", "warning")
    model = colmap.build_model(specs)
    mdir = find_masks_dir(scene.images_dir)
    found = {s.name: mask_file(mdir, s.name) for s in staged} if mdir is not None else {}
    mask_source = stage_all(found, staged, work, run, invert=cfg.invert_masks, where=mdir)
    undistorted, facts = finish_posed(model, staged, work, Project(stage), cfg, run, mask_source=mask_source)
    near = np.array([f.near for f in frames])
    far = np.array([f.far for f in frames])
    return Dataset(registered=len(staged), total=len(scene.frames), undistorted=undistorted,
                   masks=mask_source is not None, mask_source=mask_source, background=background, skipped=bad,
                   bounds=depth_bounds(cams, near, far), **facts)
