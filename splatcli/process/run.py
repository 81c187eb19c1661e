"""`process`: from what the user has to a posed dataset `train` can use.

Inputs (see process/detect.py): a folder of photos or a video (structure
from motion with pycolmap), a COLMAP workspace, or a transforms.json or an LLFF
poses_bounds.npy (poses imported as they are, points triangulated from the photos
with them: posed.py). Every path ends the same way:

    PROJECT/images/<name>           RGB images, exactly those of the model
    PROJECT/masks/<name>.png        masks (255 = keep): the input's alpha or its mask files (masks.py)
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
import os
import shutil
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from ..errors import Interrupted, ProjectBusy, SplatError
from ..events import EventSink, Stages
from ..project import LOCK_NAME, Project, is_project, writer_lock
from ..sfm import colmap
from . import features
from .capture import from_capture
from .config import ProcessConfig, ProcessResult, check_config
from .detect import InputSpec, detect_input
from .features import CACHE_DIR
from .llff import from_llff
from .publish import publish
from .transforms import from_transforms
from .workspace import from_colmap

STAGE_DIR = ".process-tmp"


def _check_output(root: Path, spec: InputSpec, overwrite: bool) -> None:
    """Refuse outputs that would clobber something, before doing any work."""
    if root.exists() and not root.is_dir():
        raise SplatError(f"{root}: exists and is not a directory")
    r = Path(os.path.abspath(root))
    for p in {spec.path, spec.root, spec.images_dir or spec.path}:
        q = Path(os.path.abspath(p))
        if q == r or r in q.parents:
            raise SplatError(f"{root}: the output folder holds the input ({p}); choose another -o")
    if not root.is_dir() or not any(p.name not in (STAGE_DIR, LOCK_NAME, CACHE_DIR) for p in root.iterdir()):
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


def process(input: str | Path, project_dir: str | Path, cfg: ProcessConfig = ProcessConfig(),
            on_event: EventSink | None = None) -> ProcessResult:
    """Turn `input` into a posed dataset in `project_dir`. Raises SplatError
    (one line naming the file and problem) for anything wrong with the input."""
    t_start = time.perf_counter()
    input = Path(input)
    root = Path(project_dir)
    check_config(cfg)
    background = cfg.background
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

    colmap.load()  # imported on this (the main) thread: only there does the import keep glog off SIGTERM
    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _process(spec: InputSpec, root: Path, cfg: ProcessConfig, background: tuple[float, float, float] | None,
             on_event: EventSink | None, t_start: float) -> ProcessResult:
    run = Stages(on_event)
    created = not root.exists()
    stage = root / STAGE_DIR
    root.mkdir(parents=True, exist_ok=True)
    try:
        with writer_lock(root, "process"):
            return _stage_and_publish(spec, root, stage, cfg, background, run, t_start)
    except ProjectBusy:  # another process is writing there: its folder is not ours to remove
        raise
    except BaseException:
        if created and not (root / CACHE_DIR).is_dir():  # (features kept for the next run stay)
            shutil.rmtree(root, ignore_errors=True)
        raise


def _stage_and_publish(spec: InputSpec, root: Path, stage: Path, cfg: ProcessConfig,
                       background: tuple[float, float, float] | None, run: Stages, t_start: float) -> ProcessResult:
    try:
        if stage.exists():
            shutil.rmtree(stage)  # left by an interrupted run: never reuse its database
        stage.mkdir()
        if spec.kind in ("images", "video"):
            ds = from_capture(spec, stage, cfg, background, run)
        elif spec.kind == "colmap":
            ds = from_colmap(spec, stage, cfg, background, run)
        elif spec.kind == "llff":
            ds = from_llff(spec, stage, cfg, background, run)
        else:
            ds = from_transforms(spec, stage, cfg, background, run)
        result = publish(root, stage, spec, cfg, ds, run, t_start)
    except BaseException as exc:
        if isinstance(exc, (Interrupted, KeyboardInterrupt)) and features.keep(root, stage / "work"):
            run.note(f"features and matches kept in {root / CACHE_DIR}: the next process of these photos "
                     "starts from them")
        shutil.rmtree(stage, ignore_errors=True)
        if isinstance(exc, OSError):  # disk full, permissions: the user's to fix, not a bug
            raise SplatError(f"{exc.filename or root}: {exc.strerror or exc}") from exc
        raise
    return result
