"""Publishing a finished stage folder as the project: splits, scene facts, the
manifest and the process report, in an order an interrupt cannot make look finished."""

from __future__ import annotations

import os
import shutil
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from ..camera import Camera
from ..events import Stages
from ..files.atomic import atomic_write_json
from ..project import Project, holdout_split
from ..sfm.colmap import model_digest, read_scene
from .bounds import frustum_bounds, points_bounds
from .config import ProcessConfig, ProcessResult
from .dataset import Dataset
from .detect import InputSpec


def scene_facts(cameras: list[Camera], points: np.ndarray, background: tuple[float, float, float],
                bounds: tuple[np.ndarray, np.ndarray] | None = None) -> dict[str, Any]:
    """`bounds`: the box the input states (LLFF's near/far), used when there are no points."""
    if len(points):
        lo, hi = points_bounds(points)
        init = "sfm"
    elif bounds is not None:
        lo, hi = bounds
        init = "random"
    else:
        lo, hi = frustum_bounds(cameras)
        init = "random"
    return {
        "has_points": bool(len(points)),
        "init": init,
        "background": [float(c) for c in background],
        "bounds_min": [float(v) for v in lo],
        "bounds_max": [float(v) for v in hi],
        "num_points": int(len(points)),
    }


def _move_in(root: Path, stage: Path, spec: InputSpec) -> Project:
    """The project at `root`, made anew (the output was checked before any work), with the staged
    images, masks and model moved in and the stage removed."""
    proj = Project.create(root, source={"path": str(spec.path.absolute()), "kind": spec.kind}, overwrite=True)
    for d in (proj.images_dir, proj.masks_dir, proj.sfm_dir, proj.checkpoints_dir, proj.renders_dir,
              proj.exports_dir, proj.reports_dir):
        if d.exists():
            shutil.rmtree(d)
    st = Project(stage)
    for d in (st.images_dir, st.masks_dir, st.sfm_dir):
        if d.exists():
            os.replace(d, root / d.name)
    shutil.rmtree(stage, ignore_errors=True)
    return proj


def publish(root: Path, stage: Path, spec: InputSpec, cfg: ProcessConfig, ds: Dataset, run: Stages,
             t_start: float) -> ProcessResult:
    st = Project(stage)
    scene = read_scene(st.sparse_dir)  # also proves the model is readable and PINHOLE
    names = [c.name for c in scene.cameras]
    missing_files = [n for n in names if not (st.images_dir / n).is_file()]
    if missing_files:  # our own bug if it happens; never publish an inconsistent project
        raise RuntimeError(f"staged model lists images that were not written: {missing_files[:3]}")
    background = ds.background if ds.background is not None else ((1.0, 1.0, 1.0) if ds.mask_source == "alpha" else (0.0, 0.0, 0.0))
    splits = holdout_split(names, ds.test)
    facts = scene_facts(scene.cameras, scene.points, background, ds.bounds)
    facts["masks"] = ds.masks
    facts["mask_source"] = ds.mask_source
    facts["model_sha256"] = model_digest(st.sparse_dir)  # later reads of this model skip the file walk
    if facts["init"] == "random":
        run.note("no sparse points: training will initialise Gaussians randomly inside the camera frustums")

    proj = _move_in(root, stage, spec)

    seconds = dict(run.seconds)
    seconds["total"] = time.perf_counter() - t_start
    result = ProcessResult(
        project=root, input=spec.path, input_kind=spec.kind, registered=len(names), total=ds.total,
        points=int(len(scene.points)), mean_reprojection_error=ds.mean_reprojection_error,
        mean_track_length=ds.mean_track_length, seconds={k: round(v, 3) for k, v in seconds.items()},
        train=len(splits["train"]), test=len(splits["test"]), init=facts["init"], undistorted=ds.undistorted,
        masks=ds.masks, mask_source=ds.mask_source, matcher=ds.matcher, pairs=ds.pairs,
        keypoints_median=ds.keypoints_median, model_sizes=ds.model_sizes, unregistered=ds.unregistered,
        left_out_models=ds.left_out_models, sfm_tried=ds.sfm_tried, consistency=ds.consistency,
        placed_apart=ds.placed_apart, repeatable=ds.repeatable, skipped=ds.skipped, missing=ds.missing,
        dropped_blurry=ds.dropped_blurry, triangulated=ds.triangulated, camera_grouping=ds.camera_grouping,
        cameras=ds.cameras, warnings=list(run.warnings),
    )
    config = asdict(cfg)
    config["background_rgb"] = list(background)

    proj.update_manifest(splits=splits, scene=facts)
    proj.record_step("process", config=config, summary=result.summary())  # marks the project processed
    # The report copy comes after the step record: batch Makefiles take it as
    # "process finished", so it must never exist for an unfinished project.
    atomic_write_json(proj.process_report_path, result.summary())
    return result
