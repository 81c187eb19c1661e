"""Photos or a video: structure from motion with pycolmap (sfm/reconstruct.py)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import SplatError
from ..events import Stages
from ..inputs.images import IMAGE_EXTS, StagedImage, fit_size, list_folder
from ..project import Project
from ..sfm.reconstruct import LARGE_CAPTURE, SfmOptions, SfmResult, Tried, octave, run_sfm
from . import features
from .cameras import Grouping, group_cameras
from .config import MIN_IMAGES, ProcessConfig, sift_max_size
from .dataset import Dataset, finish_model, refuse_if_strict, stage_images
from .detect import InputSpec
from .masks import MASKS_DIR, find_masks_dir, mask_file, stage_all
from .video import extract_frames


def safe_names(names: list[str]) -> list[str]:
    """Names COLMAP's pair lists can carry: whitespace becomes '_' (a pair list
    is space-separated), kept unique."""
    out: list[str] = []
    taken = set(names)
    for n in names:
        safe = "_".join(n.split())
        if safe != n:
            stem, dot, ext = safe.rpartition(".")
            k = 1
            while safe in taken:
                safe = f"{stem}_{k}.{ext}" if dot else f"{safe}_{k}"
                k += 1
            taken.add(safe)
        out.append(safe)
    return out


def left_out_warning(unregistered: list[str], fell_into: dict[str, int | None], sizes: list[int],
                     shown: int = 20) -> str:
    """One line naming the images the kept model lacks and the model each fell into."""
    def where(n: str) -> str:
        k = fell_into.get(n)
        return f"model {k} ({sizes[k - 1]} images)" if k is not None and k <= len(sizes) else "no model"

    split = (f"mapping split into {len(sizes)} models of {', '.join(map(str, sizes))} images; keeping the largest; "
             if len(sizes) > 1 else "")
    named = ", ".join(f"{n} ({where(n)})" for n in unregistered[:shown])
    more = f", and {len(unregistered) - shown} more (the manifest lists them all)" if len(unregistered) > shown else ""
    return f"{split}{len(unregistered)} image(s) did not register in it: {named}{more}"


def _say_left_out(res: SfmResult, run: Stages) -> None:
    """The warnings for images the model lacks (those placed apart have had their own)."""
    apart = set(res.placed_apart)
    missing = [n for n in res.unregistered if n not in apart]
    if missing:
        run.note(left_out_warning(missing, res.left_out_models, res.model_sizes), "warning")
    if res.model.num_registered < len(res.names) / 2:
        run.note(f"only {res.model.num_registered} of {len(res.names)} images registered; the photos may overlap "
                 "too little or be too blurry", "warning")


@dataclass
class _Staged:
    """The photos or frames staged under work/input, and their cameras."""

    images: list[StagedImage]
    grouping: Grouping
    pairs: list[tuple[Path, str]] = field(default_factory=list)  # (photo, its name in the project); none for video
    skipped: list[str] = field(default_factory=list)
    dropped: int = 0  # blurry video frames


def _stage_video(spec: InputSpec, work: Path, cfg: ProcessConfig, run: Stages) -> _Staged:
    with run.stage("video frames", None) as s:
        frames = extract_frames(
            spec.path, work / "input", every_fps=cfg.fps, num_frames=None if cfg.fps else cfg.num_frames,
            blur_ratio=cfg.blur_ratio,
            on_progress=lambda k, n: s.progress(k, n),
        )
    skipped = [f"frame {i}: could not be decoded (corrupt or truncated video)" for i in frames.unreadable]
    refuse_if_strict(spec.path, skipped, cfg.strict)
    run.note(f"extracted {frames.sampled} of {frames.total_frames} frames; dropped {len(frames.dropped)} blurry frame(s)")
    if skipped:
        shown = ", ".join(str(i) for i in frames.unreadable[:10]) + (", ..." if len(skipped) > 10 else "")
        run.note(f"skipped {len(skipped)} frame(s) that could not be decoded: {shown}", "warning")
    if len(frames.names) < MIN_IMAGES:
        raise SplatError(f"{spec.path}: only {len(frames.names)} usable frame(s); need at least {MIN_IMAGES}")
    staged = [StagedImage(n, frames.width, frames.height, False) for n in frames.names]
    return _Staged(staged, group_cameras(staged, None, cfg.cameras, video=True), skipped=skipped,
                   dropped=len(frames.dropped))


def _stage_folder(spec: InputSpec, work: Path, cfg: ProcessConfig, background: tuple[float, float, float] | None,
                  run: Stages) -> _Staged:
    assert spec.images_dir is not None
    files, others = list_folder(spec.images_dir)
    if not files:
        raise SplatError(f"{spec.images_dir}: no images found (looked for {', '.join(IMAGE_EXTS)})")
    pairs = list(zip(files, safe_names([p.name for p in files])))
    staged, bad = stage_images(pairs, work, run, background=background, orient=True)
    refuse_if_strict(spec.images_dir, bad, cfg.strict)
    if len(staged) < MIN_IMAGES:  # before the notes: a failed run says one line
        why = f" ({'; '.join(bad[:3])})" if bad else ""
        raise SplatError(
            f"{spec.images_dir}: structure from motion needs at least {MIN_IMAGES} readable images, "
            f"found {len(staged)}{why}"
        )
    by_name = {name: src for src, name in pairs}
    grouping = group_cameras(staged, {s.name: by_name[s.name] for s in staged}, cfg.cameras, video=False)
    if others:
        shown = ", ".join(p.name for p in others[:5]) + (", ..." if len(others) > 5 else "")
        run.note(f"skipped {len(others)} file(s) that are not images: {shown}")
    for b in bad:
        run.note(f"skipped {b}", "warning")
    return _Staged(staged, grouping, pairs=pairs, skipped=bad)


def _say_grouping(grouping: Grouping, run: Stages) -> None:
    run.note(grouping.reason)
    for p in grouping.problems[:3]:
        run.note(f"EXIF ignored: {p}", "warning")
    if len(grouping.problems) > 3:
        run.note(f"EXIF ignored in {len(grouping.problems) - 3} more image(s)", "warning")


def _pose(spec: InputSpec, got: _Staged, stage: Path, cfg: ProcessConfig, mask_dir: Path | None,
          run: Stages) -> SfmResult:
    """Structure from motion on the staged images, reusing a sibling's features where the key matches."""
    work = stage / "work"
    names = [s.name for s in got.images]
    max_size = sift_max_size(cfg, posed=False)
    sfm_opts = SfmOptions(
        matcher=cfg.matcher, ordered=spec.kind == "video", max_image_size=max_size,
        max_features=cfg.max_features, first_octave=cfg.first_octave,
        sequential_overlap=cfg.sequential_overlap, seed=cfg.seed, num_threads=cfg.num_threads,
        camera_model=cfg.camera_model,
    )
    sift_side = min(min(fit_size(s.width, s.height, max_size)) for s in got.images)  # smallest side SIFT will see
    split = got.grouping.split() if cfg.cameras == "auto" else None
    cameras = [g.names for g in got.grouping.groups]
    key = features.features_key(work / "input", names, mask_dir, {
        "max_image_size": max_size, "max_features": cfg.max_features, "octave": octave(sfm_opts, sift_side),
        "camera_model": cfg.camera_model, "cameras": cameras})
    found = features.reuse(stage.parent, work, key)
    if found:
        run.note(f"reusing the features and matches of {found} (the same photos and feature options)")
    res = run_sfm(work / "input", names, work, sfm_opts, cameras=cameras,
                  split_cameras=[g.names for g in split.groups] if split else None, min_side=sift_side,
                  where=spec.images_dir or spec.path, on_event=run.sink, mask_dir=mask_dir,
                  features_ready=found is not None, on_features=lambda: features.mark(work, key))
    if found:
        res.tried.insert(0, Tried(f"features and matches reused from {found}", "the same photos and feature options"))
    for k, v in res.seconds.items():
        run.seconds[k] = run.seconds.get(k, 0.0) + v
    if split is not None and res.cameras == [g.names for g in split.groups]:
        got.grouping = split
        run.note(split.reason)
    return res


def from_capture(spec: InputSpec, stage: Path, cfg: ProcessConfig, background: tuple[float, float, float] | None,
                 run: Stages) -> Dataset:
    work = stage / "work"
    st = Project(stage)
    got = _stage_video(spec, work, cfg, run) if spec.kind == "video" else _stage_folder(spec, work, cfg, background, run)
    mdir = find_masks_dir(spec.images_dir) if spec.images_dir is not None else None
    found = {name: mask_file(mdir, src.name) for src, name in got.pairs} if mdir is not None else {}
    mask_source = stage_all(found, got.images, work, run, invert=cfg.invert_masks, where=mdir)
    _say_grouping(got.grouping, run)
    res = _pose(spec, got, stage, cfg, work / MASKS_DIR if mask_source else None, run)
    model = res.model
    _say_left_out(res, run)
    st.sfm_dir.mkdir(parents=True, exist_ok=True)
    os.replace(work / "database.db", st.database_path)
    if (work / features.KEY_FILE).is_file() and not res.features_changed:
        # (a database remade on the upsampled octave is not what the key's options make)
        os.replace(work / features.KEY_FILE, st.sfm_dir / features.KEY_FILE)
    registered = set(model.registered_names())
    if mask_source == "alpha" and not any(s.has_alpha for s in got.images if s.name in registered):
        mask_source = None
    undistorted = finish_model(model, st, work, cfg, run, masks=mask_source)
    return Dataset(registered=model.num_registered, total=len(got.images), undistorted=undistorted,
                   masks=mask_source is not None, mask_source=mask_source,
                   background=background, mean_reprojection_error=model.mean_reprojection_error(),
                   mean_track_length=model.mean_track_length(), skipped=got.skipped, matcher=res.matcher,
                   pairs=res.num_pairs, keypoints_median=res.keypoints_median, model_sizes=res.model_sizes,
                   unregistered=res.unregistered, left_out_models=res.left_out_models,
                   sfm_tried=[t.summary() for t in res.tried],
                   consistency=res.consistency.summary() if res.consistency is not None else None,
                   placed_apart=res.placed_apart, repeatable=len(got.images) < LARGE_CAPTURE,
                   dropped_blurry=got.dropped, camera_grouping=got.grouping.rule,
                   cameras=[g.summary() for g in got.grouping.groups])
