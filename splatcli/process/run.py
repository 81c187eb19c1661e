"""`process`: from what the user has to a posed dataset `train` can use.

Inputs (see splatcli/sfm/detect.py): a folder of photos or a video (structure
from motion with pycolmap), a COLMAP workspace or a transforms.json (imported
as they are). Every path ends the same way:

    PROJECT/images/<name>           RGB images, exactly those of the model
    PROJECT/masks/<name>.png        alpha, when the input had one
    PROJECT/sfm/sparse/0            PINHOLE COLMAP model of images/
    PROJECT/sfm/distorted           the raw model, when undistortion happened
    PROJECT/sfm/database.db         the SfM database (SfM inputs only)
    PROJECT/splatcli.json           splits, scene facts, and the `process` step

All work happens in PROJECT/.process-tmp; the project is only touched once the
dataset is complete, so a failed or interrupted run leaves an existing project
as it was, and the `process` step is written last, so an interrupted publish
never looks finished. A rerun deletes a stale temp folder first.
"""

from __future__ import annotations

import contextlib
import math
import os
import shutil
import signal
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from ..camera import Camera
from ..errors import Interrupted, SplatError
from ..events import EventSink, Note, Progress, Stage, StageDone, emit
from ..io.atomic import atomic_write_json
from ..project import Project, is_project
from ..sfm import colmap
from .bounds import frustum_bounds, points_bounds
from ..sfm.colmap import CameraSpec, Model
from ..sfm.colmap_files import check_image_name, check_model
from .detect import InputSpec, detect_input
from ..io.images import IMAGE_EXTS, ImageError, StagedImage, fit_size, list_folder, stage_image, write_image
from ..sfm.model import read_scene
from ..sfm.reconstruct import MATCHERS, SfmOptions, run_sfm
from ..io.transforms import read_transforms
from .video import extract_frames

STAGE_DIR = ".process-tmp"
MIN_IMAGES = 2


@dataclass(frozen=True)
class ProcessConfig:
    input_type: str = "auto"  # auto | images | video | colmap | transforms
    max_size: int = 1600  # SfM: longest side, pixels, of the image SIFT sees (the dataset keeps full resolution)
    matcher: str = "auto"  # auto | exhaustive | sequential
    fps: float | None = None  # video: frames per second of video to extract
    num_frames: int = 100  # video: frames to extract when fps is not given
    background: str = "auto"  # auto (white for RGBA inputs, else black) | white | black | R,G,B in [0, 1]
    overwrite: bool = False
    seed: int = 0
    max_features: int = 4096  # SIFT features per image
    first_octave: int | None = None  # SIFT: None picks 0, or -1 (upsampled) for images under 400 px
    sequential_overlap: int = 5  # neighbours each image is matched with (plus 2^k further ones)
    blur_ratio: float = 0.6  # video: drop frames less sharp than this x their neighbours' median
    num_threads: int = -1  # -1: all cores


@dataclass
class ProcessResult:
    project: Path
    input: Path
    input_kind: str
    registered: int  # images in the dataset
    total: int  # images the input offered (after skipping unreadable files)
    points: int  # sparse 3D points
    mean_reprojection_error: float | None  # pixels; None without points
    mean_track_length: float | None
    seconds: dict[str, float]  # per stage, and "total"
    train: int
    test: int
    init: str  # "sfm" (from points) or "random"
    undistorted: bool
    masks: bool
    matcher: str | None = None  # the image pairs matched (SfM only)
    pairs: int = 0
    keypoints_median: float | None = None  # SIFT features per image (SfM only)
    model_sizes: list[int] = field(default_factory=list)  # images per SfM model, largest first
    unregistered: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)  # "name: reason"
    missing: int = 0  # files listed by the input but absent
    dropped_blurry: int = 0
    warnings: list[str] = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        d = asdict(self)
        d["project"] = str(self.project)
        d["input"] = str(self.input)
        return d


def parse_background(text: str) -> tuple[float, float, float] | None:
    """None for "auto", else RGB in [0, 1]."""
    t = text.strip().lower()
    if t == "auto":
        return None
    named = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0), "grey": (0.5, 0.5, 0.5), "gray": (0.5, 0.5, 0.5)}
    if t in named:
        return named[t]
    try:
        vals = tuple(float(v) for v in t.split(","))
    except ValueError:
        vals = ()
    if len(vals) != 3 or not all(math.isfinite(v) for v in vals):
        raise SplatError(f"--background {text!r}: expected auto, white, black or R,G,B")
    if max(vals) > 1.0:  # 0-255 given
        vals = tuple(v / 255.0 for v in vals)
    if min(vals) < 0 or max(vals) > 1:
        raise SplatError(f"--background {text!r}: components must be in [0, 1] (or 0-255)")
    return vals  # type: ignore[return-value]


def _check_config(cfg: ProcessConfig) -> None:
    if cfg.matcher not in MATCHERS:
        raise SplatError(f"--matcher {cfg.matcher!r}: expected one of {', '.join(MATCHERS)}")
    if cfg.max_size < 32:
        raise SplatError(f"--max-size {cfg.max_size}: must be at least 32 pixels")
    if cfg.fps is not None and not (cfg.fps > 0 and math.isfinite(cfg.fps)):
        raise SplatError(f"--fps {cfg.fps}: must be a positive number")
    if cfg.num_frames < MIN_IMAGES:
        raise SplatError(f"--num-frames {cfg.num_frames}: must be at least {MIN_IMAGES}")
    if cfg.max_features < 64:
        raise SplatError(f"max_features {cfg.max_features}: must be at least 64")


def _check_output(root: Path, spec: InputSpec, overwrite: bool) -> None:
    """Refuse outputs that would clobber something, before doing any work."""
    if root.exists() and not root.is_dir():
        raise SplatError(f"{root}: exists and is not a directory")
    r = Path(os.path.abspath(root))
    for p in {spec.path, spec.root, spec.images_dir or spec.path}:
        q = Path(os.path.abspath(p))
        if q == r or r in q.parents:
            raise SplatError(f"{root}: the output folder holds the input ({p}); choose another -o")
    if not root.is_dir() or not any(p.name != STAGE_DIR for p in root.iterdir()):
        return
    if not is_project(root):
        if not overwrite:
            raise SplatError(
                f"{root}: folder exists, is not empty and is not a splatcli project; "
                "choose another -o or pass --overwrite"
            )
        return
    if overwrite:
        return
    try:
        done = Project(root).step("process") is not None
    except SplatError:
        done = True  # an unreadable manifest: do not guess, ask
    if done:
        raise SplatError(
            f"{root}: already holds a processed dataset; pass --overwrite to replace it "
            "(its checkpoints, renders and exports are deleted)"
        )


class _Run:
    """Events, timings and notes of one run."""

    def __init__(self, on_event: EventSink | None) -> None:
        self.on_event = on_event
        self.seconds: dict[str, float] = {}
        self.warnings: list[str] = []

    def note(self, message: str, level: str = "note") -> None:
        if level == "warning":
            self.warnings.append(message)
        emit(self.on_event, Note(message, level))

    def stage(self, name: str, total: int | None = None) -> "_Timed":
        return _Timed(self, name, total)


class _Timed:
    def __init__(self, run: _Run, name: str, total: int | None) -> None:
        self.run, self.name, self.total = run, name, total

    def __enter__(self) -> "_Timed":
        emit(self.run.on_event, Stage(self.name, self.total))
        self.t0 = time.perf_counter()
        return self

    def progress(self, done: int, total: int | None = None, **info: Any) -> None:
        emit(self.run.on_event, Progress(self.name, done, total if total is not None else self.total, info))

    def __exit__(self, *exc: Any) -> None:
        dt = time.perf_counter() - self.t0
        self.run.seconds[self.name] = self.run.seconds.get(self.name, 0.0) + dt
        if exc[0] is None:
            emit(self.run.on_event, StageDone(self.name, dt))


@dataclass
class _Dataset:
    """What a stage folder holds once an input is converted."""

    registered: int
    total: int
    undistorted: bool
    masks: bool
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


def process(input: str | Path, project_dir: str | Path, cfg: ProcessConfig = ProcessConfig(),
            on_event: EventSink | None = None) -> ProcessResult:
    """Turn `input` into a posed dataset in `project_dir`. Raises SplatError
    (one line naming the file and problem) for anything wrong with the input."""
    t_start = time.perf_counter()
    input = Path(input)
    root = Path(project_dir)
    _check_config(cfg)
    background = parse_background(cfg.background)
    spec = detect_input(input, cfg.input_type)
    _check_output(root, spec, cfg.overwrite)
    with _terminate_as_interrupt():
        return _process(spec, root, cfg, background, on_event, t_start)


@contextlib.contextmanager
def _terminate_as_interrupt() -> Iterator[None]:
    """SIGTERM (a batch scheduler stopping us) cleans up like Ctrl-C does."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: Any) -> None:
        raise Interrupted("process terminated; run it again to start over")

    colmap.load()  # glog takes SIGTERM when pycolmap is imported: import first, then take it back
    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _process(spec: InputSpec, root: Path, cfg: ProcessConfig, background: tuple[float, float, float] | None,
             on_event: EventSink | None, t_start: float) -> ProcessResult:
    run = _Run(on_event)
    created = not root.exists()
    stage = root / STAGE_DIR
    root.mkdir(parents=True, exist_ok=True)
    try:
        if stage.exists():
            shutil.rmtree(stage)  # left by an interrupted run: never reuse its database
        stage.mkdir()
        if spec.kind in ("images", "video"):
            ds = _from_capture(spec, stage, cfg, background, run)
        elif spec.kind == "colmap":
            ds = _from_colmap(spec, stage, cfg, background, run)
        else:
            ds = _from_transforms(spec, stage, cfg, background, run)
        result = _publish(root, stage, spec, cfg, ds, run, t_start)
    except BaseException as exc:
        shutil.rmtree(stage, ignore_errors=True)
        if created:
            shutil.rmtree(root, ignore_errors=True)
        if isinstance(exc, OSError):  # disk full, permissions: the user's to fix, not a bug
            raise SplatError(f"{exc.filename or root}: {exc.strerror or exc}") from exc
        raise
    return result


# ---- images and video: structure from motion ---------------------------------


def _stage_images(files: list[tuple[Path, str]], work: Path, run: _Run, *,
                  background: tuple[float, float, float] | None, orient: bool,
                  expect: dict[str, tuple[int, int]] | None = None) -> tuple[list[StagedImage], list[str]]:
    """Stage (source, name) pairs into work/input, masks into work/masks.

    Unusable images are skipped and returned as "name: reason". RGBA images are
    composited over `background` (white when None)."""
    bg = background if background is not None else (1.0, 1.0, 1.0)
    out: list[StagedImage] = []
    bad: list[str] = []
    with run.stage("read images", len(files)) as s:
        for i, (src, name) in enumerate(files):
            try:
                out.append(stage_image(
                    src, name, work / "input" / name, work / "masks" / name,
                    max_size=None,  # the dataset keeps full resolution; train caps what it loads
                    background=bg, orient=orient, expect_size=(expect or {}).get(name),
                ))
            except ImageError as exc:
                bad.append(f"{src.name}: {exc}")
            s.progress(i + 1)
    return out, bad


def _safe_names(names: list[str]) -> list[str]:
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


def _from_capture(spec: InputSpec, stage: Path, cfg: ProcessConfig, background: tuple[float, float, float] | None,
                  run: _Run) -> _Dataset:
    work = stage / "work"
    st = Project(stage)
    skipped: list[str] = []
    dropped = 0
    if spec.kind == "video":
        with run.stage("video frames", None) as s:
            frames = extract_frames(
                spec.path, work / "input", every_fps=cfg.fps, num_frames=None if cfg.fps else cfg.num_frames,
                max_size=None, blur_ratio=cfg.blur_ratio,
                on_progress=lambda k, n: s.progress(k, n),
            )
        dropped = len(frames.dropped)
        run.note(f"extracted {frames.sampled} of {frames.total_frames} frames; dropped {dropped} blurry frame(s)")
        if len(frames.names) < MIN_IMAGES:
            raise SplatError(f"{spec.path}: only {len(frames.names)} usable frame(s); need at least {MIN_IMAGES}")
        w, h = frames.width, frames.height
        staged = [StagedImage(n, w, h, w, h, False) for n in frames.names]
    else:
        assert spec.images_dir is not None
        files, others = list_folder(spec.images_dir)
        if not files:
            raise SplatError(f"{spec.images_dir}: no images found (looked for {', '.join(IMAGE_EXTS)})")
        staged, bad = _stage_images(list(zip(files, _safe_names([p.name for p in files]))), work, run,
                                    background=background, orient=True)
        skipped = bad
        if len(staged) < MIN_IMAGES:  # before the notes: a failed run says one line
            why = f" ({'; '.join(bad[:3])})" if bad else ""
            raise SplatError(
                f"{spec.images_dir}: structure from motion needs at least {MIN_IMAGES} readable images, "
                f"found {len(staged)}{why}"
            )
        if others:
            shown = ", ".join(p.name for p in others[:5]) + (", ..." if len(others) > 5 else "")
            run.note(f"skipped {len(others)} file(s) that are not images: {shown}")
        for b in bad:
            run.note(f"skipped {b}")
    names = [s.name for s in staged]
    sizes = {(s.width, s.height) for s in staged}
    if len(sizes) > 1:
        run.note(f"images come in {len(sizes)} sizes; using one camera per image")
    sfm_opts = SfmOptions(
        matcher=cfg.matcher, ordered=spec.kind == "video", max_image_size=cfg.max_size,
        max_features=cfg.max_features, first_octave=cfg.first_octave,
        sequential_overlap=cfg.sequential_overlap, seed=cfg.seed, num_threads=cfg.num_threads,
    )
    sift_side = min(min(fit_size(w, h, cfg.max_size)) for w, h in sizes)  # smallest side SIFT will see
    res = run_sfm(work / "input", names, work, sfm_opts, single_camera=len(sizes) == 1, min_side=sift_side,
                  where=spec.images_dir or spec.path, on_event=run.on_event)
    for k, v in res.seconds.items():
        run.seconds[k] = run.seconds.get(k, 0.0) + v
    model = res.model
    if len(res.model_sizes) > 1:
        run.note(f"mapping split into {len(res.model_sizes)} models of {', '.join(map(str, res.model_sizes))} "
                 f"images; keeping the largest")
    if res.unregistered:
        shown = ", ".join(res.unregistered[:10]) + (", ..." if len(res.unregistered) > 10 else "")
        run.note(f"{len(res.unregistered)} image(s) did not register: {shown}")
    if model.num_registered < len(names) / 2:
        run.note(f"only {model.num_registered} of {len(names)} images registered; the photos may overlap too "
                 "little or be too blurry", "warning")
    st.sfm_dir.mkdir(parents=True, exist_ok=True)
    os.replace(work / "database.db", st.database_path)
    has_masks = any(s.has_alpha for s in staged if s.name in set(model.registered_names()))
    undistorted = _finish_model(model, st, work, cfg, run, masks=has_masks)
    return _Dataset(registered=model.num_registered, total=len(names), undistorted=undistorted, masks=has_masks,
                    background=background, mean_reprojection_error=model.mean_reprojection_error(),
                    mean_track_length=model.mean_track_length(), skipped=skipped, matcher=res.matcher,
                    pairs=res.num_pairs, keypoints_median=res.keypoints_median, model_sizes=res.model_sizes,
                    unregistered=res.unregistered, dropped_blurry=dropped)


# ---- the common ending: undistort (or not) into images/ and sfm/sparse/0 ------


def _finish_model(model: Model, st: Project, work: Path, cfg: ProcessConfig, run: _Run, *, masks: bool) -> bool:
    """Write images/, masks/ and sfm/sparse/0 (PINHOLE) into the stage folder.
    Returns whether undistortion happened."""
    names = model.registered_names()
    if masks:  # some images had alpha: give the others an opaque mask, so every image has one
        for name, (w, h) in model.camera_sizes().items():
            if not (work / "masks" / name).exists():
                write_image(work / "masks" / name, np.full((h, w), 255, np.uint8))
    if model.is_pinhole():
        model.to_pinhole()
        with run.stage("copy images", len(names)) as s:
            for i, name in enumerate(names):
                _move(work / "input" / name, st.images_dir / name)
                if masks and (work / "masks" / name).exists():
                    _move(work / "masks" / name, _mask_path(st, name))
                s.progress(i + 1)
        model.write(st.sparse_dir)
        return False
    model.write(st.distorted_dir)
    with run.stage("undistort", len(names)) as s:
        out = colmap.undistort(model, work / "input", work / "undistorted", num_threads=cfg.num_threads)
        st.sparse_dir.parent.mkdir(parents=True, exist_ok=True)
        os.replace(out, st.sparse_dir)
        os.replace(work / "undistorted" / "images", st.images_dir)
        if masks and (work / "masks").is_dir():
            mdir = colmap.undistort_masks(model, work / "masks", work / "undistorted_masks",
                                          num_threads=cfg.num_threads)
            for name in names:
                if (mdir / name).exists():
                    _convert_mask(mdir / name, _mask_path(st, name))
        s.progress(len(names))
    return True


def _mask_path(st: Project, name: str) -> Path:
    return st.mask_path(name)


def _move(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    os.replace(src, dst)


def _convert_mask(src: Path, dst: Path) -> None:
    import cv2

    m = cv2.imread(str(src), cv2.IMREAD_GRAYSCALE)
    if m is not None:
        write_image(dst, m)


# ---- COLMAP workspace --------------------------------------------------------


def _from_colmap(spec: InputSpec, stage: Path, cfg: ProcessConfig, background: tuple[float, float, float] | None,
                 run: _Run) -> _Dataset:
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
    staged, bad = _stage_images([(spec.images_dir / n, n) for n in present], work, run, background=background,
                                orient=False, expect=sizes)
    if not staged:  # before the warnings: a failed run says one line
        raise SplatError(f"{spec.images_dir}: none of the model's images could be read ({bad[0]})")
    if missing:
        run.note(f"{len(missing)} image(s) of the model are missing from {spec.images_dir} and were skipped "
                 f"(first: {missing[0]})", "warning")
    for b in bad:
        run.note(f"skipped {b}", "warning")
    keep = [s.name for s in staged]
    model.keep_images(keep)
    has_masks = any(s.has_alpha for s in staged)
    undistorted = _finish_model(model, st, work, cfg, run, masks=has_masks)
    has_points = model.num_points > 0
    return _Dataset(registered=len(keep), total=len(names), undistorted=undistorted, masks=has_masks,
                    background=background, skipped=bad, missing=len(missing),
                    mean_reprojection_error=model.mean_reprojection_error() if has_points else None,
                    mean_track_length=model.mean_track_length() if has_points else None)


# ---- transforms.json ---------------------------------------------------------


def _from_transforms(spec: InputSpec, stage: Path, cfg: ProcessConfig,
                     background: tuple[float, float, float] | None, run: _Run) -> _Dataset:
    assert spec.transforms is not None
    work = stage / "work"
    st = Project(stage)
    scene = read_transforms(spec.transforms)
    frames = {f.name: f for f in scene.frames}
    staged, bad = _stage_images([(f.source, f.name) for f in scene.frames], work, run, background=background,
                                orient=False)
    if not staged:
        raise SplatError(f"{spec.transforms}: none of the listed images could be read ({bad[0]})")
    specs = []
    for s in staged:
        f = frames[s.name]
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
    has_masks = any(s.has_alpha for s in staged)
    undistorted = _finish_model(model, st, work, cfg, run, masks=has_masks)
    kept = {s.name for s in staged}
    test = sorted(f.name for f in scene.frames if f.split == "test" and f.name in kept) if scene.has_test_split else None
    bg = background
    if bg is None and has_masks:
        bg = (1.0, 1.0, 1.0)
    return _Dataset(registered=len(staged), total=len(scene.frames) + len(scene.missing), undistorted=undistorted,
                    masks=has_masks, test=test or None, background=bg, skipped=bad, missing=len(scene.missing))


def _read_ply_points(path: Path, run: _Run) -> tuple[np.ndarray | None, np.ndarray | None]:
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


# ---- publishing --------------------------------------------------------------


def _splits(names: list[str], test: list[str] | None) -> dict[str, list[str]]:
    names = sorted(names)
    if test:
        t = set(test)
        return {"train": [n for n in names if n not in t], "test": [n for n in names if n in t]}
    return {"train": [n for i, n in enumerate(names) if i % 8 != 0], "test": names[::8]}


def _scene_facts(cameras: list[Camera], points: np.ndarray, background: tuple[float, float, float]) -> dict[str, Any]:
    if len(points):
        lo, hi = points_bounds(points)
        init = "sfm"
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


def _publish(root: Path, stage: Path, spec: InputSpec, cfg: ProcessConfig, ds: _Dataset, run: _Run,
             t_start: float) -> ProcessResult:
    st = Project(stage)
    scene = read_scene(st.sparse_dir)  # also proves the model is readable and PINHOLE
    names = [c.name for c in scene.cameras]
    missing_files = [n for n in names if not (st.images_dir / n).is_file()]
    if missing_files:  # our own bug if it happens; never publish an inconsistent project
        raise RuntimeError(f"staged model lists images that were not written: {missing_files[:3]}")
    background = ds.background if ds.background is not None else ((1.0, 1.0, 1.0) if ds.masks else (0.0, 0.0, 0.0))
    splits = _splits(names, ds.test)
    facts = _scene_facts(scene.cameras, scene.points, background)
    facts["masks"] = ds.masks
    if facts["init"] == "random":
        run.note("no sparse points: training will initialise Gaussians randomly inside the camera frustums")

    source = {"path": str(spec.path.absolute()), "kind": spec.kind}
    proj = Project.create(root, source=source, overwrite=True)  # we checked the output before any work
    for d in (proj.images_dir, proj.masks_dir, proj.sfm_dir, proj.checkpoints_dir, proj.renders_dir,
              proj.exports_dir, proj.reports_dir):
        if d.exists():
            shutil.rmtree(d)
    for d in (st.images_dir, st.masks_dir, st.sfm_dir):
        if d.exists():
            os.replace(d, root / d.name)
    shutil.rmtree(stage, ignore_errors=True)

    seconds = dict(run.seconds)
    seconds["total"] = time.perf_counter() - t_start
    result = ProcessResult(
        project=root,
        input=spec.path,
        input_kind=spec.kind,
        registered=len(names),
        total=ds.total,
        points=int(len(scene.points)),
        mean_reprojection_error=ds.mean_reprojection_error,
        mean_track_length=ds.mean_track_length,
        seconds={k: round(v, 3) for k, v in seconds.items()},
        train=len(splits["train"]),
        test=len(splits["test"]),
        init=facts["init"],
        undistorted=ds.undistorted,
        masks=ds.masks,
        matcher=ds.matcher,
        pairs=ds.pairs,
        keypoints_median=ds.keypoints_median,
        model_sizes=ds.model_sizes,
        unregistered=ds.unregistered,
        skipped=ds.skipped,
        missing=ds.missing,
        dropped_blurry=ds.dropped_blurry,
        warnings=list(run.warnings),
    )
    config = asdict(cfg)
    config["background_rgb"] = list(background)

    proj.update_manifest(splits=splits, scene=facts)
    proj.record_step("process", config=config, summary=result.summary())  # marks the project processed
    # The report copy comes after the step record: batch Makefiles take it as
    # "process finished", so it must never exist for an unfinished project.
    atomic_write_json(proj.process_report_path, result.summary())
    return result

