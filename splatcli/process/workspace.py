"""A COLMAP workspace: its model and images imported as they are."""

from __future__ import annotations

import shutil
from pathlib import Path

from ..errors import SplatError
from ..events import Stages
from ..project import Project
from ..sfm import colmap
from ..sfm.colmap_files import check_image_name, check_model
from .config import ProcessConfig
from .dataset import Dataset, finish_model, stage_posed
from .detect import InputSpec
from .masks import find_masks_dir, mask_file, stage_all


def from_colmap(spec: InputSpec, stage: Path, cfg: ProcessConfig, background: tuple[float, float, float] | None,
                 run: Stages) -> Dataset:
    assert spec.model_dir is not None and spec.images_dir is not None
    work = stage / "work"
    st = Project(stage)
    summary = check_model(spec.model_dir)  # before any progress: a bad model is the only thing said
    with run.stage("read model", 1) as s:
        # Read a copy of only the three files we checked (rigs/frames are ignored).
        copy = work / "model_in"
        copy.mkdir(parents=True)
        for stem in ("cameras", "images", "points3D"):
            shutil.copyfile(spec.model_dir / f"{stem}.{summary.format}", copy / f"{stem}.{summary.format}")
        model = colmap.read_model(copy)
        s.progress(1)
    names = model.registered_names()
    if not names:
        raise SplatError(f"{spec.model_dir}: the COLMAP model has no posed images")
    present, missing = [], []
    for n in names:
        check_image_name(n, spec.model_dir)
        (present if (spec.images_dir / n).is_file() else missing).append(n)
    if not present:
        raise SplatError(f"{spec.images_dir}: none of the model's {len(names)} images exists here "
                         f"(first: {names[0]})")
    sizes = model.camera_sizes()
    staged, bad = stage_posed([(spec.images_dir / n, n) for n in present], work, run, cfg, where=spec.images_dir,
                              what="the model's images", background=background, expect=sizes)
    if missing:
        run.note(f"{len(missing)} image(s) of the model are missing from {spec.images_dir} and were skipped "
                 f"(first: {missing[0]})", "warning")
    for b in bad:
        run.note(f"skipped {b}", "warning")
    keep = [s.name for s in staged]
    model.keep_images(keep)
    mdir = find_masks_dir(spec.images_dir)
    found = {n: mask_file(mdir, n) for n in keep} if mdir is not None else {}
    mask_source = stage_all(found, staged, work, run, invert=cfg.invert_masks, where=mdir)
    undistorted = finish_model(model, st, work, cfg, run, masks=mask_source)
    has_points = model.num_points > 0
    return Dataset(registered=len(keep), total=len(names), undistorted=undistorted,
                    masks=mask_source is not None, mask_source=mask_source,
                    background=background, skipped=bad, missing=len(missing),
                    mean_reprojection_error=model.mean_reprojection_error() if has_points else None,
                    mean_track_length=model.mean_track_length() if has_points else None)
