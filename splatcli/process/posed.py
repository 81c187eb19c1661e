"""Posed captures (transforms.json, LLFF): real points from their photos.

The poses and intrinsics are known, so no mapping runs: SIFT as for photos, the
pairs the poses say overlap are matched, and COLMAP's point triangulator makes
points with every camera held fixed (sfm/reconstruct.triangulate_posed). Training
then starts from those points, as it does after structure from motion. When too
few points come out (a featureless synthetic object, photos that do not match the
poses), the model keeps none and training starts from random points, with a note.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..events import Stages
from ..inputs.images import StagedImage, fit_size
from ..project import Project
from ..sfm.check import check_model
from ..sfm.colmap import Model
from ..sfm.reconstruct import SfmOptions, triangulate_posed
from .config import ProcessConfig, sift_max_size
from .dataset import finish_model, stage_posed
from .masks import MASKS_DIR

MIN_POINTS = 1000  # fewer triangulated points than this: random points serve training better
NEIGHBOURS = 10  # images each image is matched with (nearest centres among those facing its way)


@dataclass
class PosedPoints:
    """What triangulation gave, for the process summary."""

    points: int  # triangulated points (kept or not)
    kept: bool  # the model carries them (else random initialisation)
    pairs: int
    keypoints_median: float
    mean_reprojection_error: float | None  # pixels
    mean_track_length: float | None
    consistency: dict[str, Any]  # the given poses against the photos' pairs (sfm/check.py)


def add_points(model: Model, staged: list[StagedImage], work: Path, st: Project, cfg: ProcessConfig, run: Stages,
               *, mask_source: str | None) -> tuple[Model, PosedPoints]:
    """`model` (the posed images in work/input) with triangulated points, or unchanged
    when too few triangulate. The SfM database ends in the stage project's sfm/."""
    max_size = sift_max_size(cfg, posed=True)
    sift_side = min(min(fit_size(s.width, s.height, max_size)) for s in staged)
    opts = SfmOptions(max_image_size=max_size, max_features=cfg.max_features, first_octave=cfg.first_octave,
                      seed=cfg.seed, num_threads=cfg.num_threads)
    res = triangulate_posed(work / "input", model, work, opts, neighbours=NEIGHBOURS, min_side=sift_side,
                            on_event=run.sink, mask_dir=work / MASKS_DIR if mask_source else None)
    for k, v in res.seconds.items():
        run.seconds[k] = run.seconds.get(k, 0.0) + v
    st.sfm_dir.mkdir(parents=True, exist_ok=True)
    os.replace(work / "database.db", st.database_path)
    check = check_model(st.database_path, model)
    if check.consistent:
        run.note(f"poses checked: {check.line()}")
    else:
        run.note(f"the capture's poses disagree with its photos: {check.line()}", "warning")
    out = res.model
    n = out.num_points
    kept = n >= MIN_POINTS
    info = PosedPoints(points=n, kept=kept, pairs=res.num_pairs, keypoints_median=res.keypoints_median,
                       mean_reprojection_error=out.mean_reprojection_error() if kept else None,
                       mean_track_length=out.mean_track_length() if kept else None, consistency=check.summary())
    if not kept:
        run.note(f"only {n} point(s) triangulated from the photos with the given poses (fewer than {MIN_POINTS}: "
                 "too little texture, or photos that disagree with the poses); training starts from random points")
        return model, info
    run.note(f"triangulated {n} points from {res.num_pairs} image pairs with the given poses held fixed "
             f"(reprojection error {info.mean_reprojection_error:.2f} px, track length "
             f"{info.mean_track_length:.1f}); training starts from them")
    return out, info


def stage_frames(frames: list[Any], work: Path, run: Stages, cfg: ProcessConfig, *, where: Path, what: str,
                 background: tuple[float, float, float] | None) -> tuple[list[StagedImage], list[Any], list[str]]:
    """stage_posed for the frames of a posed capture (inputs/llff.py's or inputs/transforms.py's: an image
    `source` and its `name`): the images staged, the frame of each, and the skipped ones."""
    staged, bad = stage_posed([(f.source, f.name) for f in frames], work, run, cfg, where=where, what=what,
                              background=background)
    by_name = {f.name: f for f in frames}
    return staged, [by_name[s.name] for s in staged], bad


def finish_posed(model: Model, staged: list[StagedImage], work: Path, st: Project, cfg: ProcessConfig, run: Stages,
                 *, mask_source: str | None) -> tuple[bool, dict]:
    """Points triangulated from the photos (`add_points`; not when the input brought its own,
    with --no-triangulate, or under two images), then the model written (dataset.finish_model):
    whether it was undistorted, and the Dataset fields triangulation fills (`posed_facts`)."""
    tri = None
    if cfg.triangulate and not model.num_points and len(staged) >= 2:
        model, tri = add_points(model, staged, work, st, cfg, run, mask_source=mask_source)
    return finish_model(model, st, work, cfg, run, masks=mask_source), posed_facts(tri)


def posed_facts(info: PosedPoints | None) -> dict:
    """The Dataset fields triangulation fills (none without it)."""
    if info is None:
        return {}
    return {"matcher": "posed", "pairs": info.pairs, "keypoints_median": info.keypoints_median,
            "mean_reprojection_error": info.mean_reprojection_error, "mean_track_length": info.mean_track_length,
            "triangulated": info.points, "consistency": info.consistency}
