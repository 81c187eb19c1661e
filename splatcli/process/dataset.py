"""What every input kind ends with: its images staged, and the model written as
images/, masks/ and sfm/sparse/0 (undistorted to PINHOLE when needed) in the stage folder."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import SplatError
from ..events import Stages
from ..inputs.images import MASK_KEEP, ImageError, StagedImage, read_mask, stage_image, write_image
from ..project import Project
from ..sfm import colmap
from ..sfm.colmap import Model
from .config import ProcessConfig
from .masks import MASKS_DIR, fill_masks, staged_mask


@dataclass
class Dataset:
    """What a stage folder holds once an input is converted."""

    registered: int
    total: int
    undistorted: bool
    masks: bool
    mask_source: str | None = None  # "alpha" or "files" (masks/ folder, transforms mask_path); None: no masks
    test: list[str] | None = None  # the input's own held-out images
    background: tuple[float, float, float] | None = None  # None: decided from alpha
    mean_reprojection_error: float | None = None  # pixels, of the model's points (None without points)
    mean_track_length: float | None = None
    skipped: list[str] = field(default_factory=list)  # "file: reason"
    missing: int = 0
    matcher: str | None = None  # SfM only, from here on
    pairs: int = 0
    keypoints_median: float | None = None
    model_sizes: list[int] = field(default_factory=list)
    unregistered: list[str] = field(default_factory=list)
    dropped_blurry: int = 0
    triangulated: int | None = None  # posed captures: points triangulated with the poses fixed (kept or not)
    left_out_models: dict[str, int | None] = field(default_factory=dict)  # SfM: unregistered -> model it fell into
    sfm_tried: list[dict] = field(default_factory=list)  # SfM: the mapping attempts made (reconstruct.Tried.summary)
    consistency: dict | None = None  # SfM: the kept model against its pairs' geometry (sfm/check.py)
    placed_apart: list[str] = field(default_factory=list)  # SfM: registered where no model agreed with their pairs: left out
    repeatable: bool = True  # SfM under reconstruct.LARGE_CAPTURE photos (mapping on one thread)
    camera_grouping: str | None = None  # SfM: process/cameras.py's rule
    cameras: list[dict] = field(default_factory=list)  # SfM: each camera's images and EXIF facts
    bounds: tuple[np.ndarray, np.ndarray] | None = None  # the scene box the input states (LLFF's near/far), for want of points


def refuse_if_strict(where: Path | str, skipped: list[str], strict: bool) -> None:
    """--strict: any unreadable image or video frame is an error naming the first few."""
    if strict and skipped:
        shown = "; ".join(skipped[:3]) + (f"; and {len(skipped) - 3} more" if len(skipped) > 3 else "")
        raise SplatError(f"{where}: {len(skipped)} unreadable input(s) and --strict: {shown}")


def stage_images(files: list[tuple[Path, str]], work: Path, run: Stages, *,
                  background: tuple[float, float, float] | None, orient: bool,
                  expect: dict[str, tuple[int, int]] | None = None) -> tuple[list[StagedImage], list[str]]:
    """Stage (source, name) pairs into work/input, alpha masks into work/masks (masks.staged_mask).

    Unusable images are skipped and returned as "name: reason". RGBA images are
    composited over `background` (white when None)."""
    bg = background if background is not None else (1.0, 1.0, 1.0)
    out: list[StagedImage] = []
    bad: list[str] = []
    with run.stage("read images", len(files)) as s:
        for i, (src, name) in enumerate(files):
            try:
                out.append(stage_image(
                    src, name, work / "input" / name, staged_mask(work, name),
                    background=bg, orient=orient, expect_size=(expect or {}).get(name),
                ))
            except ImageError as exc:
                bad.append(f"{src.name}: {exc}")
            s.progress(i + 1)
    return out, bad


def stage_posed(files: list[tuple[Path, str]], work: Path, run: Stages, cfg: ProcessConfig, *, where: Path,
                what: str, background: tuple[float, float, float] | None,
                expect: dict[str, tuple[int, int]] | None = None) -> tuple[list[StagedImage], list[str]]:
    """stage_images for an input that brings its poses (a COLMAP model, transforms.json, LLFF),
    images as they are stored: --strict refuses any unreadable one, and none readable is an
    error naming `where` (`what`: the images as the message calls them, "the model's images")."""
    staged, bad = stage_images(files, work, run, background=background, orient=False, expect=expect)
    refuse_if_strict(where, bad, cfg.strict)
    if not staged:  # before any note: a failed run says one line
        raise SplatError(f"{where}: none of {what} could be read ({bad[0]})")
    return staged, bad


def finish_model(model: Model, st: Project, work: Path, cfg: ProcessConfig, run: Stages, *,
                 masks: str | None) -> bool:
    """Write images/, masks/ and sfm/sparse/0 (PINHOLE) into the stage folder; `masks`
    is the mask source (file masks stay 0 or 255 through undistortion).
    Returns whether undistortion happened."""
    names = model.registered_names()
    if masks:  # some images have a mask: give the others an opaque one, so every image has one
        fill_masks(work, model.camera_sizes())
    if model.is_pinhole():
        model.to_pinhole()
        with run.stage("copy images", len(names)) as s:
            for i, name in enumerate(names):
                _move(work / "input" / name, st.images_dir / name)
                if masks:
                    _move(staged_mask(work, name), st.mask_path(name))
                s.progress(i + 1)
        model.write(st.sparse_dir)
        return False
    model.write(st.distorted_dir)
    with run.stage("undistort", len(names)) as s:
        out = colmap.undistort(model, work / "input", work / "undistorted", num_threads=cfg.num_threads,
                               on_progress=s.progress)
        st.sparse_dir.parent.mkdir(parents=True, exist_ok=True)
        os.replace(out, st.sparse_dir)
        os.replace(work / "undistorted" / "images", st.images_dir)
        if masks:
            by_name = work / f"{MASKS_DIR}_by_name"  # undistortion reads each mask under its image's name
            for name in names:
                _move(staged_mask(work, name), by_name / name)  # PNG inside whatever the name says
            mdir = colmap.undistort_masks(model, by_name, work / "undistorted_masks", num_threads=cfg.num_threads)
            for name in names:
                if (mdir / name).exists():
                    _convert_mask(mdir / name, st.mask_path(name), binary=masks == "files")
        s.progress(len(names))
    return True


def _move(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    os.replace(src, dst)


def _convert_mask(src: Path, dst: Path, *, binary: bool) -> None:
    """An undistorted mask as PNG (`binary`: interpolated edges cut back to 0 or 255)."""
    m = read_mask(src)
    write_image(dst, np.where(m >= MASK_KEEP, 255, 0).astype(np.uint8) if binary else m)
