"""Every pycolmap call splatcli makes lives here, because pycolmap's API moves
between versions (frames/rigs in 3.12, option objects renamed in 4.0).

Long calls run in a worker thread with a `CancellationToken`, so Ctrl-C stops
them cleanly and the main thread can report progress meanwhile. pycolmap
releases the GIL inside its C++ code.

Never read the SfM database with Python's own `sqlite3` while pycolmap writes
it: the two SQLite copies in one process corrupt each other's locks (SIGBUS).
"""

from __future__ import annotations

import contextlib
import hashlib
import math
import os
import shutil
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..camera import Camera, SceneData
from ..errors import SplatError
from ..project import Project
from .colmap_files import MODEL_FILES, check_model, model_format

_VERBOSE = False


def set_verbose(verbose: bool) -> None:
    """Let COLMAP's own log through (for --debug)."""
    global _VERBOSE
    _VERBOSE = verbose


def _pc() -> Any:
    pycolmap = _import()
    # glog: 0 INFO, 1 WARNING, 2 ERROR, 3 FATAL. COLMAP is chatty; we report ourselves.
    pycolmap.logging.minloglevel = 0 if _VERBOSE else 3
    return pycolmap


def _import() -> Any:
    """pycolmap, with SIGTERM as it was before the import. Its glog installs C-level handlers for
    crash signals and SIGTERM on import, and that one prints a stack trace of 30 lines: a `train
    --nproc` worker that the launcher stops while another reports a one-line error would print it.
    On the main thread the import runs with SIGTERM held back, and the handler in place before it
    is put back (a SIGTERM that came meanwhile is then taken by that one)."""
    if "pycolmap" in sys.modules or threading.current_thread() is not threading.main_thread():
        import pycolmap

        return pycolmap
    before = signal.getsignal(signal.SIGTERM)
    held = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})
    try:
        import pycolmap
    finally:
        if before is not None:  # (None: a handler not set from Python, which cannot be put back)
            signal.signal(signal.SIGTERM, before)
        signal.pthread_sigmask(signal.SIG_SETMASK, held)
    return pycolmap


def load() -> None:
    """Import pycolmap now (with SIGTERM kept as it was: `_import`)."""
    _pc()


class OverTime(Exception):
    """A call stopped at its time cap (`deadline`)."""


_DEADLINES: list[float] = []  # time.monotonic() values


@contextlib.contextmanager
def deadline(when: float) -> Iterator[None]:
    """Calls through `run_cancellable` (and `global_mapping`) within stop, cancelled, with OverTime
    raised, once `time.monotonic()` passes `when`."""
    _DEADLINES.append(when)
    try:
        yield
    finally:
        _DEADLINES.remove(when)


def _check_deadline() -> None:
    if _DEADLINES and time.monotonic() > min(_DEADLINES):
        raise OverTime


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())[:300]


def run_cancellable(fn: Callable[..., Any], *args: Any, poll: Callable[[], None] | None = None,
                    **kwargs: Any) -> Any:
    """Call `fn(*args, cancellation_token=token, **kwargs)` in a worker thread.

    `poll` runs every 0.1 s on the calling thread (progress). An exception on
    the calling thread (Ctrl-C) cancels the token and waits for pycolmap to
    unwind before re-raising: a thread still inside pycolmap when Python exits
    aborts the process. The wait uses an Event, not Thread.join, because an
    interrupted join marks a running thread as finished (CPython bpo-45274)."""
    pycolmap = _pc()
    token = pycolmap.CancellationToken()
    box: dict[str, Any] = {}
    done = threading.Event()

    def work() -> None:
        try:
            box["value"] = fn(*args, cancellation_token=token, **kwargs)
        except BaseException as exc:  # re-raised on the caller's thread
            box["error"] = exc
        finally:
            done.set()

    th = threading.Thread(target=work, name=f"pycolmap-{getattr(fn, '__name__', 'call')}", daemon=True)
    th.start()
    try:
        while not done.wait(0.1):
            _check_deadline()
            if poll is not None:
                poll()
    except BaseException:
        token.cancel()
        while True:
            try:
                done.wait()
                break
            except BaseException:  # a second Ctrl-C: still wait, exiting now would abort
                continue
        raise
    if poll is not None:
        poll()
    if "error" in box:
        raise box["error"]
    return box.get("value")


# ---- database ---------------------------------------------------------------


def create_database(path: Path, image_dir: Path, cameras: list[list[str]], *,
                    camera_model: str = "SIMPLE_RADIAL") -> None:
    """A fresh database with one camera per group of image names in `cameras`,
    and no features yet. COLMAP reads each camera's focal length prior from the
    EXIF of its group's first image (else 1.2 x the longest side, no prior)."""
    pycolmap = _pc()
    path = Path(path)
    if path.exists():
        path.unlink()  # never extend a stale database from an interrupted run
    pycolmap.Database.open(str(path)).close()
    opts = pycolmap.ImageReaderOptions()
    opts.camera_model = camera_model
    singles = [g[0] for g in cameras if len(g) == 1]
    calls = [(pycolmap.CameraMode.SINGLE, g) for g in cameras if len(g) > 1]
    if singles:
        calls.append((pycolmap.CameraMode.PER_IMAGE, singles))
    try:
        for mode, names in calls:  # each SINGLE call makes one new camera
            pycolmap.import_images(str(path), str(image_dir), camera_mode=mode, image_names=list(names),
                                   options=opts)
    except (RuntimeError, ValueError) as exc:
        raise SplatError(f"{image_dir}: COLMAP could not read the images ({_one_line(exc)})") from None


def copy_database(src: Path, dst: Path, image_dir: Path, cameras: list[list[str]], *,
                  camera_model: str = "SIMPLE_RADIAL", without: Iterable[str] = ()) -> None:
    """A new database `dst` whose images are grouped into `cameras` afresh, with `src`'s features,
    matches and verified geometries copied (the geometries do not depend on the grouping), except
    the features of the images in `without` and every match of theirs: extraction and matching
    then redo those alone."""
    pycolmap = _pc()
    drop = set(without)
    create_database(dst, image_dir, cameras, camera_model=camera_model)
    with pycolmap.Database.open(str(src)) as a, pycolmap.Database.open(str(dst)) as b:
        old = {im.image_id: im.name for im in a.read_all_images()}
        new = {im.name: im.image_id for im in b.read_all_images()}
        ids = {i: new[n] for i, n in old.items()}
        for i, n in old.items():
            if n in drop:
                continue
            if a.exists_keypoints(i):
                b.write_keypoints(ids[i], a.read_keypoints(i))
            if a.exists_descriptors(i):
                b.write_descriptors(ids[i], a.read_descriptors(i))
        for pair, matches in zip(*a.read_all_matches()):
            i, j = pycolmap.pair_id_to_image_pair(pair)
            if old[i] not in drop and old[j] not in drop:
                b.write_matches(ids[i], ids[j], matches)  # the database orders each pair itself
        for pair, geom in zip(*a.read_two_view_geometries()):
            i, j = pycolmap.pair_id_to_image_pair(pair)
            if old[i] not in drop and old[j] not in drop:
                b.write_two_view_geometry(ids[i], ids[j], geom)


@dataclass(frozen=True)
class SiftOptions:
    max_image_size: int = 1600  # pixels, longest side SIFT sees; keypoints are scaled back to full size
    max_num_features: int = 4096
    first_octave: int = 0  # -1 upsamples the image twice: much slower, finds small features
    peak_threshold: float = 0.02 / 3  # COLMAP's default
    num_threads: int = -1


def extract_features(db: Path, image_dir: Path, names: list[str], opts: SiftOptions, *,
                     mask_dir: Path | None = None) -> None:
    """SIFT for `names` (already in the database, with their cameras); call in chunks for progress.
    `mask_dir`: COLMAP's mask folder, `<name>.png` per image; none are kept where it is 0."""
    pycolmap = _pc()
    ro = pycolmap.ImageReaderOptions()
    if mask_dir is not None:
        ro.mask_path = str(mask_dir)
    eo = pycolmap.FeatureExtractionOptions()
    eo.num_threads = opts.num_threads
    eo.max_image_size = opts.max_image_size
    eo.sift.max_num_features = opts.max_num_features
    eo.sift.first_octave = opts.first_octave
    eo.sift.peak_threshold = opts.peak_threshold
    mode = pycolmap.CameraMode.PER_IMAGE  # the images are in the database: no camera is made here
    run_cancellable(
        pycolmap.extract_features, str(db), str(image_dir), image_names=list(names), camera_mode=mode,
        reader_options=ro, extraction_options=eo, device=pycolmap.Device.cpu,
    )


@dataclass(frozen=True)
class MatchOptions:
    num_threads: int = -1
    max_ratio: float = 0.8
    min_num_inliers: int = 15
    seed: int = 0


# A child process costs about 0.5 s (start, pycolmap, a copy of the database): one is started only for at least
# MIN_WORKER_S of matching, estimated from the pairs' keypoints (brute-force matching costs the product of the two
# counts). PAIR_S: one pair of PAIR_KEYPOINTS keypoints each on one thread, matched and verified (fox's photos,
# about 3,100 keypoints each: 343 pairs in 19.9 s on a Zen 4).
MIN_WORKER_S = 2.0
PAIR_S, PAIR_KEYPOINTS = 0.058, 3100


def _workers(db: Path, pairs: list[tuple[str, str]], threads: int) -> int:
    """How many processes match `pairs`: one per core, but none with under MIN_WORKER_S of work."""
    kp = keypoint_counts(db)
    work_s = PAIR_S * sum(kp.get(a, 0) * kp.get(b, 0) for a, b in pairs) / PAIR_KEYPOINTS**2
    return max(1, min(threads, len(pairs), int(work_s // MIN_WORKER_S) if MIN_WORKER_S > 0 else threads))


def match_pairs(db: Path, pairs: list[tuple[str, str]], work_dir: Path, opts: MatchOptions,
                on_progress: Callable[[int], None] | None = None) -> None:
    """Match and geometrically verify the given image pairs (names), repeatably: on one thread per
    process (worker.py says why), the pairs split into contiguous shares among child processes, one
    per core (`opts.num_threads`), each into a copy of the database, merged back in pair order.
    `on_progress(k)`: pairs done so far."""
    from . import worker

    pycolmap = _pc()
    k = _workers(db, pairs, _threads(opts.num_threads))
    settings = {"num_threads": 1, "max_ratio": opts.max_ratio, "min_inliers": opts.min_num_inliers,
                "seed": opts.seed}
    done = [0] * k

    def progress(w: int, line: str) -> None:
        done[w] += int(line)
        if on_progress is not None:
            on_progress(sum(done))

    if k == 1:
        step = max(worker.PAIRS_PER_CALL, -(-len(pairs) // (2 * worker.CALLS)))
        for i in range(0, len(pairs), step):
            chunk = [list(p) for p in pairs[i : i + step]]
            run_cancellable(worker.match_chunk, pycolmap, str(db), chunk, str(work_dir / "pairs.txt"), settings)
            progress(0, str(len(chunk)))
        return
    shares = [pairs[w * len(pairs) // k : (w + 1) * len(pairs) // k] for w in range(k)]
    copies = [work_dir / f"{db.stem}.match{w}.db" for w in range(k)]
    try:
        for c in copies:
            shutil.copyfile(db, c)
        run_workers([{"kind": "match", "db": str(c), "pairs": [list(p) for p in share],
                      "list_file": str(work_dir / f"pairs{w}.txt"), "opts": settings,
                      "per_call": max(worker.PAIRS_PER_CALL, -(-len(share) // worker.CALLS))}
                     for w, (c, share) in enumerate(zip(copies, shares))], on_line=progress)
        _merge_matches(db, list(zip(copies, shares)))
    finally:
        for c in copies:
            c.unlink(missing_ok=True)


def _merge_matches(db: Path, parts: list[tuple[Path, list[tuple[str, str]]]]) -> None:
    """Each part's pairs' matches and verified geometries (from its database) into `db`, in order;
    pairs `db` holds already are left as they are."""
    pycolmap = _pc()
    with pycolmap.Database.open(str(db)) as d:
        ids = {im.name: im.image_id for im in d.read_all_images()}
        for path, pairs in parts:
            with pycolmap.Database.open(str(path)) as src:
                for a, b in pairs:
                    i, j = ids[a], ids[b]
                    if d.exists_matches(i, j) or not src.exists_matches(i, j):
                        continue
                    d.write_matches(i, j, src.read_matches(i, j))
                    if src.exists_two_view_geometry(i, j):
                        d.write_two_view_geometry(i, j, src.read_two_view_geometry(i, j))


def _threads(n: int) -> int:
    return (os.cpu_count() or 1) if n < 1 else n


def run_workers(jobs: list[dict[str, Any]], on_line: Callable[[int, str], None] | None = None) -> None:
    """Each job in a child process (worker.py), all at once; `on_line(k, line)` for each line job k
    prints. Ctrl-C, a `deadline` passing (OverTime) or one child failing stops them all."""
    import json
    import subprocess

    procs = [subprocess.Popen([sys.executable, "-m", "splatcli.sfm.worker", json.dumps({**job, "verbose": _VERBOSE})],
                              stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for job in jobs]
    lines: list[tuple[int, str]] = []
    lock = threading.Lock()

    def read(k: int, p: subprocess.Popen) -> None:
        for line in p.stdout:  # type: ignore[union-attr]
            with lock:
                lines.append((k, line.strip()))

    readers = [threading.Thread(target=read, args=(k, p), daemon=True) for k, p in enumerate(procs)]
    for r in readers:
        r.start()

    def drain() -> None:
        with lock:
            got, lines[:] = list(lines), []
        for k, line in got:
            if on_line is not None and line:
                on_line(k, line)

    def stop() -> None:
        for p in procs:
            if p.poll() is None:
                p.kill()
        for p in procs:
            p.wait()

    failed = None
    try:
        while failed is None and any(p.poll() is None for p in procs):
            _check_deadline()
            drain()
            failed = next((p for p in procs if p.poll()), None)
            time.sleep(0.1)
    except BaseException:
        stop()
        raise
    failed = failed or next((p for p in procs if p.poll()), None)
    if failed is not None:
        stop()
        err = failed.stderr.read().strip().splitlines() if failed.stderr else []
        raise SplatError(f"COLMAP failed in a worker process ({_one_line(RuntimeError(err[-1] if err else f'exit {failed.returncode}'))})")
    for r in readers:
        r.join()
    drain()


@dataclass(frozen=True)
class DatabaseStats:
    keypoints: dict[str, int]  # image name -> keypoints
    verified_pairs: int  # pairs with a two-view geometry of enough inliers


def keypoint_counts(db: Path) -> dict[str, int]:
    """Image name -> its keypoints in the database."""
    pycolmap = _pc()
    with pycolmap.Database.open(str(db)) as d:
        return {im.name: int(d.num_keypoints_for_image(im.image_id)) for im in d.read_all_images()}


def database_stats(db: Path, min_inliers: int = 15) -> DatabaseStats:
    kp = keypoint_counts(db)
    pycolmap = _pc()
    with pycolmap.Database.open(str(db)) as d:
        _, geoms = d.read_two_view_geometries()
        verified = sum(1 for g in geoms if len(g.inlier_matches) >= min_inliers)
    return DatabaseStats(keypoints=kp, verified_pairs=verified)


def read_descriptors(db: Path, names: list[str]) -> list[np.ndarray]:
    """Each named image's SIFT descriptors, [n_i, 128] uint8 (empty where it has none)."""
    pycolmap = _pc()
    with pycolmap.Database.open(str(db)) as d:
        ids = {im.name: im.image_id for im in d.read_all_images()}
        out = []
        for n in names:
            a = np.asarray(d.read_descriptors(ids[n]).data, dtype=np.uint8) if n in ids else None
            out.append(a.reshape(-1, 128) if a is not None and a.size else np.zeros((0, 128), np.uint8))
    return out


@dataclass(frozen=True)
class VerifiedPair:
    """A verified image pair of the database: its inlier matches and its own two-view geometry."""

    a: str
    b: str
    matches: np.ndarray  # [M, 2] uint32: keypoint indices in a and in b
    kind: str  # "E" (calibrated), "F" (uncalibrated), or "H" (planar or a pure rotation: no relative pose)
    matrix: np.ndarray | None  # [3, 3]: the E or F the pair's own RANSAC found (x_b^T M x_a = 0), None for "H"


_POSED_KINDS = {2: "E", 3: "F"}  # TwoViewGeometryConfiguration: CALIBRATED, UNCALIBRATED


def read_verified_pairs(db: Path, min_inliers: int = 15, *,
                        keypoints: bool = True) -> tuple[list[VerifiedPair], dict[str, np.ndarray]]:
    """Every verified pair with at least `min_inliers` inlier matches, and (`keypoints`) each image's
    keypoints ([n, 2] float64, COLMAP's pixel coordinates) for the images of those pairs."""
    pycolmap = _pc()
    out: list[VerifiedPair] = []
    with pycolmap.Database.open(str(db)) as d:
        names = {im.image_id: im.name for im in d.read_all_images()}
        ids, geoms = d.read_two_view_geometries()
        used: set[int] = set()
        for pair, g in zip(ids, geoms):
            m = np.asarray(g.inlier_matches)
            if len(m) < min_inliers:
                continue
            i, j = pycolmap.pair_id_to_image_pair(pair)
            kind = _POSED_KINDS.get(int(g.config), "H")
            mat = None if kind == "H" else np.asarray(g.E if kind == "E" else g.F, np.float64)
            out.append(VerifiedPair(names[i], names[j], m.reshape(-1, 2), kind, mat))
            used.update((i, j))
        points = {names[i]: np.asarray(d.read_keypoints(i), np.float64).reshape(-1, 6)[:, :2]
                  for i in sorted(used)} if keypoints else {}
    return out, points


# ---- mapping ----------------------------------------------------------------


@dataclass(frozen=True)
class MapperOptions:
    seed: int = 0
    # One thread: COLMAP's mapper with several is not repeatable (one seed under load gave different point counts),
    # with one it is, and on 2 cores it is no slower (docs/guide.md, "Threads")
    num_threads: int = 1
    min_model_size: int = 3
    ba_local_max_num_iterations: int = 25  # COLMAP's default is 25 (via -1 = Ceres default)
    ba_global_max_num_iterations: int = 50
    ba_global_frames_ratio: float = 1.1  # global BA when the model grew by this factor
    ba_global_points_ratio: float = 1.1
    ba_global_ignore_redundant: bool = False  # global BA leaves out points that well-covered images see anyway
    ba_local_max_refinements: int = 2  # COLMAP's default
    ba_threads_min_residuals: int = 50000  # a BA smaller than this runs on one thread (COLMAP's default)
    init_min_num_inliers: int = 100
    init_min_tri_angle: float = 16.0  # degrees
    init_max_error: float = 4.0  # pixels
    abs_pose_min_num_inliers: int = 30
    abs_pose_min_inlier_ratio: float = 0.25
    max_reg_trials: int = 3


class Model:
    """A COLMAP reconstruction (opaque outside this module)."""

    def __init__(self, rec: Any) -> None:
        self._rec = rec

    # --- facts
    @property
    def num_registered(self) -> int:
        return int(self._rec.num_reg_images())

    @property
    def num_points(self) -> int:
        return int(self._rec.num_points3D())

    def registered_names(self) -> list[str]:
        return sorted(im.name for im in self._rec.images.values() if im.has_pose)

    def mean_reprojection_error(self) -> float:
        return float(self._rec.compute_mean_reprojection_error()) if self.num_points else 0.0

    def mean_track_length(self) -> float:
        return float(self._rec.compute_mean_track_length()) if self.num_points else 0.0

    def focal_lengths(self) -> dict[str, float]:
        """Registered image name -> the mean focal length (px) of its camera."""
        return {im.name: float(self._rec.cameras[im.camera_id].mean_focal_length())
                for im in self._rec.images.values() if im.has_pose}

    def estimated_focals(self, min_points: int = 50, most: int = 64, seed: int = 0) -> dict[str, float]:
        """Registered image name -> a focal length (px) found for that image alone: its absolute pose
        with the focal length unknown, from its 2D-3D matches in this model (images with fewer than
        `min_points`, or where no pose is found, are left out). Photos that fit one shared camera give
        about the same value each; photos from several cameras forced onto one do not. At most `most`
        images, evenly spaced in name order (250 video frames took 7.4 s, for a spread that 64 tell)."""
        pycolmap = _pc()
        est = pycolmap.AbsolutePoseEstimationOptions(estimate_focal_length=True)
        est.mergedict({"ransac": {"max_error": 4.0, "random_seed": seed}})  # (COLMAP's other RANSAC defaults kept)
        ref = pycolmap.AbsolutePoseRefinementOptions(refine_focal_length=True)
        out = {}
        posed = sorted((im for im in self._rec.images.values() if im.has_pose), key=lambda im: im.name)
        for im in posed[:: max(1, math.ceil(len(posed) / most))]:
            obs = [(p.xy, self._rec.points3D[p.point3D_id].xyz) for p in im.points2D if p.has_point3D()]
            if len(obs) < min_points:
                continue
            cam = self._rec.cameras[im.camera_id]
            guess = pycolmap.Camera(model="SIMPLE_PINHOLE", width=cam.width, height=cam.height,
                                    params=[cam.mean_focal_length(), cam.width / 2, cam.height / 2])
            found = pycolmap.estimate_and_refine_absolute_pose(np.array([o[0] for o in obs], np.float64),
                                                               np.array([o[1] for o in obs], np.float64), guess, est, ref)
            if found is not None:
                out[im.name] = float(guess.mean_focal_length())
        return out

    def camera_models(self) -> set[str]:
        return {_model_name(c) for c in self._rec.cameras.values()}

    def is_pinhole(self) -> bool:
        return self.camera_models() <= {"PINHOLE", "SIMPLE_PINHOLE"}

    def camera_sizes(self) -> dict[str, tuple[int, int]]:
        """Registered image name -> (width, height) of its camera."""
        out = {}
        for im in self._rec.images.values():
            if im.has_pose:
                cam = self._rec.cameras[im.camera_id]
                out[im.name] = (int(cam.width), int(cam.height))
        return out

    def points(self) -> tuple[np.ndarray, np.ndarray]:  # [P, 3] float64, [P, 3] uint8
        pts = self._rec.points3D
        if not len(pts):
            return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
        return (np.stack([p.xyz for p in pts.values()]).astype(np.float64),
                np.stack([p.color for p in pts.values()]).astype(np.uint8))

    def observations(self) -> dict[str, np.ndarray]:  # name -> [M] int64 rows of points()
        """Registered image name -> the rows of `points()` that image observed (its track entries)."""
        row = {pid: i for i, pid in enumerate(self._rec.points3D)}
        out = {}
        for im in self._rec.images.values():
            if im.has_pose:
                out[im.name] = np.fromiter((row[p.point3D_id] for p in im.points2D if p.has_point3D()), np.int64)
        return out

    def views(self) -> dict[str, View]:
        """Registered image name -> its pose and camera (for checking the model against pair geometry)."""
        out = {}
        for im in self._rec.images.values():
            if im.has_pose:
                pose = im.cam_from_world
                pose = pose() if callable(pose) else pose
                out[im.name] = View(np.asarray(pose.matrix(), np.float64), self._rec.cameras[im.camera_id])
        return out

    # --- edits
    def keep_images(self, names: Iterable[str]) -> None:
        """Deregister every image not in `names` (with its observations)."""
        keep = set(names)
        for im in list(self._rec.images.values()):
            if im.has_pose and im.name not in keep:
                self._rec.deregister_frame(im.frame_id)

    def to_pinhole(self) -> None:
        """SIMPLE_PINHOLE -> PINHOLE (same geometry) so every project model looks alike."""
        pycolmap = _pc()
        for cid, cam in list(self._rec.cameras.items()):
            if _model_name(cam) == "SIMPLE_PINHOLE":
                f, cx, cy = [float(v) for v in cam.params]
                new = pycolmap.Camera(model="PINHOLE", width=cam.width, height=cam.height,
                                      params=[f, f, cx, cy], camera_id=cid)
                self._rec.cameras[cid] = new  # replaces in place; images keep their camera_id

    def cameras(self) -> list[Camera]:
        """Registered cameras as `Camera`, sorted by name (K ignores distortion)."""
        out = []
        for im in self._rec.images.values():
            if not im.has_pose:
                continue
            cam = self._rec.cameras[im.camera_id]
            view = np.eye(4)
            pose = im.cam_from_world
            pose = pose() if callable(pose) else pose
            view[:3, :4] = np.asarray(pose.matrix(), np.float64)
            out.append(Camera(im.name, int(cam.width), int(cam.height),
                              np.asarray(cam.calibration_matrix(), np.float64), view))
        return sorted(out, key=lambda c: c.name)

    def write(self, out_dir: Path, *, text: bool = False) -> None:
        """COLMAP binary files (or .txt) in `out_dir`."""
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        if text:
            self._rec.write_text(str(out_dir))
        else:
            self._rec.write(str(out_dir))


class View:
    """A registered image's pose ([3, 4] cam_from_world) and camera."""

    def __init__(self, pose: np.ndarray, camera: Any) -> None:
        self.pose = pose
        self._cam = camera
        self.K = np.asarray(camera.calibration_matrix(), np.float64)  # [3, 3] (distortion left out)
        self.focal = float(camera.mean_focal_length())

    def normalised(self, xy: np.ndarray) -> np.ndarray:  # [n, 2] pixels -> [n, 2] on the z = 1 plane
        """Keypoints through the camera's model, distortion included."""
        return np.asarray(self._cam.cam_from_img(np.asarray(xy, np.float64)), np.float64).reshape(-1, 2)


def _model_name(cam: Any) -> str:
    return str(getattr(cam, "model_name", None) or cam.model).split(".")[-1]


def incremental_mapping(db: Path, image_dir: Path, out_dir: Path, opts: MapperOptions,
                        on_registered: Callable[[int], None] | None = None, start: Model | None = None) -> list[Model]:
    """COLMAP's incremental mapper. Returns every model, largest first.

    `start`: a model to go on from (its images stay registered; more may join).
    `on_registered(n)` is called from the calling thread with the number of
    images registered so far in the current model."""
    pycolmap = _pc()
    pycolmap.set_random_seed(opts.seed)
    o = pycolmap.IncrementalPipelineOptions()
    o.random_seed = opts.seed
    o.num_threads = opts.num_threads
    o.min_model_size = opts.min_model_size
    o.ba_local_max_num_iterations = opts.ba_local_max_num_iterations
    o.ba_global_max_num_iterations = opts.ba_global_max_num_iterations
    o.ba_global_frames_ratio = opts.ba_global_frames_ratio
    o.ba_global_points_ratio = opts.ba_global_points_ratio
    o.ba_local_max_refinements = opts.ba_local_max_refinements
    o.ba_min_num_residuals_for_cpu_multi_threading = opts.ba_threads_min_residuals
    o.mapper.ba_global_ignore_redundant_points3D = opts.ba_global_ignore_redundant
    o.mapper.init_min_num_inliers = opts.init_min_num_inliers
    o.mapper.init_min_tri_angle = opts.init_min_tri_angle
    o.mapper.init_max_error = opts.init_max_error
    o.mapper.abs_pose_min_num_inliers = opts.abs_pose_min_num_inliers
    o.mapper.abs_pose_min_inlier_ratio = opts.abs_pose_min_inlier_ratio
    o.mapper.max_reg_trials = opts.max_reg_trials
    o.mapper.random_seed = opts.seed
    o.triangulation.random_seed = opts.seed
    counter = {"n": start.num_registered if start is not None else 0, "shown": -1}

    def on_init() -> None:
        counter["n"] = 2

    def on_next() -> None:
        counter["n"] += 1

    def poll() -> None:
        if on_registered is not None and counter["n"] != counter["shown"]:
            counter["shown"] = counter["n"]
            on_registered(counter["n"])

    out_dir.mkdir(parents=True, exist_ok=True)
    extra = {}
    if start is not None:
        start.write(out_dir / "_start")
        extra["input_path"] = str(out_dir / "_start")
    try:
        recs = run_cancellable(
            pycolmap.incremental_mapping, str(db), str(image_dir), str(out_dir), options=o,
            initial_image_pair_callback=on_init, next_image_callback=on_next, poll=poll, **extra,
        )
    except (RuntimeError, ValueError) as exc:
        raise SplatError(f"{db}: COLMAP's mapper failed ({_one_line(exc)})") from None
    models = [Model(r) for r in (recs or {}).values()]
    models.sort(key=lambda m: (-m.num_registered, -m.num_points))
    return models


def global_mapping(db: Path, image_dir: Path, out_dir: Path, *, seed: int, num_threads: int) -> list[Model]:
    """COLMAP's global mapper (GLOMAP: every rotation, then every position, at once), largest
    model first. pycolmap cannot cancel it, so it runs in a child process (worker.py), which Ctrl-C
    or a `deadline` passing (OverTime) stops at once."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    run_workers([{"kind": "global", "db": str(db), "images": str(image_dir), "out": str(out_dir), "seed": seed,
                  "threads": num_threads}])
    pycolmap = _pc()
    models = [Model(pycolmap.Reconstruction(str(d))) for d in sorted(out_dir.iterdir()) if (d / "images.bin").is_file()]
    models.sort(key=lambda m: (-m.num_registered, -m.num_points))
    return models


# ---- reading, building and undistorting models -----------------------------


def read_model(model_dir: Path) -> Model:
    """Read a model whose files were checked by `colmap_files.check_model`."""
    pycolmap = _pc()
    try:
        return Model(pycolmap.Reconstruction(str(model_dir)))
    except Exception as exc:  # pycolmap raises plain RuntimeError/ValueError on bad files
        raise SplatError(f"{model_dir}: cannot read the COLMAP model ({_one_line(exc)})") from None


@dataclass(frozen=True)
class CameraSpec:
    """A posed image to put into a new model."""

    name: str
    width: int
    height: int
    model: str  # COLMAP model name, e.g. "PINHOLE", "OPENCV"
    params: list[float]
    viewmat: np.ndarray  # [4, 4] world-to-camera, OpenCV axes


def build_model(specs: list[CameraSpec], points: np.ndarray | None = None,
                colors: np.ndarray | None = None) -> Model:
    """A model from known poses; cameras with identical intrinsics are shared.

    points: [P, 3] float64 or None; colors: [P, 3] uint8. Points get no tracks
    (there are no keypoints), which COLMAP reads and writes fine."""
    pycolmap = _pc()
    rec = pycolmap.Reconstruction()
    cam_ids: dict[tuple, int] = {}
    for i, s in enumerate(specs, start=1):
        key = (s.model, s.width, s.height, tuple(round(p, 9) for p in s.params))
        if key not in cam_ids:
            cid = len(cam_ids) + 1
            cam = pycolmap.Camera(model=s.model, width=int(s.width), height=int(s.height),
                                  params=[float(p) for p in s.params], camera_id=cid)
            rec.add_camera_with_trivial_rig(cam)
            cam_ids[key] = cid
        im = pycolmap.Image(name=s.name, camera_id=cam_ids[key], image_id=i)
        pose = pycolmap.Rigid3d(np.ascontiguousarray(s.viewmat[:3, :4], dtype=np.float64))
        rec.add_image_with_trivial_frame(im, pose)
    if points is not None and len(points):
        cols = colors if colors is not None else np.full((len(points), 3), 128, np.uint8)
        for xyz, rgb in zip(np.asarray(points, np.float64), np.asarray(cols, np.uint8)):
            rec.add_point3D(xyz, pycolmap.Track(), rgb)
    return Model(rec)


def create_posed_database(path: Path, model: Model) -> None:
    """A fresh database holding `model`'s cameras, rigs, frames and images under
    their own ids, and no features yet: point triangulation pairs the database's
    matches with the model's poses by image id. The cameras are marked as knowing
    their focal length, so two-view verification uses it."""
    pycolmap = _pc()
    path = Path(path)
    if path.exists():
        path.unlink()
    rec = model._rec
    with pycolmap.Database.open(str(path)) as db:
        for cam in rec.cameras.values():
            cam.has_prior_focal_length = True
            db.write_camera(cam, use_camera_id=True)
        for rig in rec.rigs.values():
            db.write_rig(rig, use_rig_id=True)
        for frame in rec.frames.values():
            db.write_frame(frame, use_frame_id=True)
        for im in rec.images.values():
            db.write_image(im, use_image_id=True)


def triangulate(model: Model, db: Path, image_dir: Path, out_dir: Path, opts: MapperOptions) -> Model:
    """Points triangulated from the database's matches with `model`'s poses and
    intrinsics held fixed (COLMAP's point triangulator: no mapping; the points alone
    are refined by bundle adjustment). Returns a new model; `model` is unchanged."""
    pycolmap = _pc()
    pycolmap.set_random_seed(opts.seed)
    o = pycolmap.IncrementalPipelineOptions()
    o.random_seed = opts.seed
    o.num_threads = opts.num_threads
    o.mapper.random_seed = opts.seed
    o.triangulation.random_seed = opts.seed
    o.ba_global_max_num_iterations = opts.ba_global_max_num_iterations
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rec = pycolmap.Reconstruction(model._rec)  # a copy: the caller keeps the pose-only model
    try:
        out = run_cancellable(pycolmap.triangulate_points, rec, str(db), str(image_dir), str(out_dir),
                              clear_points=True, options=o, refine_intrinsics=False)
    except (RuntimeError, ValueError) as exc:
        raise SplatError(f"{db}: COLMAP's point triangulation failed ({_one_line(exc)})") from None
    return Model(out if out is not None else rec)


def undistort(model: Model, image_dir: Path, out_dir: Path, *, jpeg_quality: int = 95,
              num_threads: int = -1, on_progress: Callable[[int], None] | None = None) -> Path:
    """Undistort the model's registered images to PINHOLE.

    Writes `out_dir/images/<name>` and the model in `out_dir/sparse`; returns
    the model folder. Images are cropped to the region valid in every direction
    (no black borders to learn). COLMAP's undistorter writes the model (cameras and 2D points)
    and one image; the images are resampled here, with one pixel map per camera, where COLMAP
    undistorts every pixel of every image again (250 video frames: 13.6 s against 2.8 s, the
    same pictures to 70 dB after JPEG). `on_progress(n)`: images done so far."""
    pycolmap = _pc()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    model_in = out_dir / "_in"
    model.write(model_in)
    uo = pycolmap.UndistortCameraOptions()
    uo.blank_pixels = 0.0
    names = model.registered_names()
    if not names:
        raise SplatError(f"{image_dir}: no registered image to undistort")
    try:
        run_cancellable(
            pycolmap.undistort_images, str(out_dir), str(model_in), str(image_dir), image_names=names[:1],
            output_type="COLMAP", undistort_options=uo, jpeg_quality=jpeg_quality, num_threads=num_threads,
        )
    except (RuntimeError, ValueError) as exc:
        raise SplatError(f"{image_dir}: undistortion failed ({_one_line(exc)})") from None
    pinhole = pycolmap.Reconstruction(str(out_dir / "sparse"))
    maps = {cid: _pixel_map(model._rec.cameras[cid], cam) for cid, cam in pinhole.cameras.items()}
    cam_of = {im.name: im.camera_id for im in pinhole.images.values()}
    _resample(names, image_dir, out_dir / "images", lambda n: maps[cam_of[n]], jpeg_quality, num_threads, on_progress)
    return out_dir / "sparse"


def _pixel_map(distorted, pinhole) -> tuple[np.ndarray, np.ndarray]:  # pycolmap Cameras -> 2 x [H, W] float32
    """Where each pixel of the undistorted image lies in the distorted one, in OpenCV's pixel
    coordinates (COLMAP's pixel centres are at +0.5)."""
    W, H = int(pinhole.width), int(pinhole.height)
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    ray = pinhole.cam_from_img(np.stack([u.ravel(), v.ravel()], 1))
    src = distorted.img_from_cam(np.concatenate([ray, np.ones((len(ray), 1))], 1)) - 0.5
    return src[:, 0].reshape(H, W).astype(np.float32), src[:, 1].reshape(H, W).astype(np.float32)


def _resample(names: list[str], image_dir: Path, out_dir: Path, pixel_map: Callable, jpeg_quality: int,
              num_threads: int, on_progress: Callable[[int], None] | None) -> None:
    """Each image resampled bilinearly through its camera's pixel map, written under its name in
    `out_dir` (the format its extension says), on `num_threads` threads (-1: every core). Read as
    COLMAP reads them: 8-bit colour, EXIF orientation ignored, whatever the name says (masks are
    PNGs under their images' names, which `inputs.images.read_image` would refuse)."""
    import cv2

    from ..inputs.images import ImageError, write_image

    def one(name: str) -> None:
        src = np.fromfile(image_dir / name, np.uint8)
        img = cv2.imdecode(src, cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION) if src.size else None
        if img is None:
            raise SplatError(f"{image_dir / name}: cannot be read for undistortion")
        mx, my = pixel_map(name)
        try:
            write_image(out_dir / name, cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE),
                        jpeg_quality)
        except ImageError as exc:
            raise SplatError(f"{name}: {exc} after undistortion") from None

    threads = (os.cpu_count() or 1) if num_threads < 1 else num_threads
    with ThreadPoolExecutor(max(1, threads)) as ex:
        for i, _ in enumerate(ex.map(one, names)):
            if on_progress is not None:
                on_progress(i + 1)


def undistort_masks(model: Model, mask_dir: Path, out_dir: Path, *, num_threads: int = -1) -> Path:
    """Warp masks (stored under the images' names) exactly like their images;
    returns the folder holding the results under the same names."""
    undistort(model, mask_dir, out_dir, jpeg_quality=100, num_threads=num_threads)
    return out_dir / "images"


# ---- the project's own model ---------------------------------------------------


def model_digest(sparse_dir: Path) -> str:
    """SHA-256 of a model's cameras, images and points3D files (either format)."""
    h = hashlib.sha256()
    fmt = model_format(sparse_dir) or "bin"
    for stem in MODEL_FILES:
        p = sparse_dir / f"{stem}.{fmt}"
        h.update(p.read_bytes() if p.is_file() else b"")
    return h.hexdigest()


def read_project_scene(project: Project) -> SceneData:
    """The project's own model (sfm/sparse/0). When it is the model `process` wrote
    (its digest is the one recorded in the manifest) the file walk is skipped."""
    project.require_processed()
    recorded = (project.manifest().get("scene") or {}).get("model_sha256")
    return read_scene(project.sparse_dir, digest=recorded if isinstance(recorded, str) else None)


def read_scene(sparse_dir: str | Path, *, pinhole_only: bool = True, digest: str | None = None) -> SceneData:
    """Cameras sorted by image name, plus the SfM points and colours.

    Only PINHOLE / SIMPLE_PINHOLE cameras are accepted: `process` undistorts
    everything else before writing the model. `pinhole_only=False` reads any
    model (K then ignores the distortion), for comparing raw SfM output.
    pycolmap trusts the counts in .bin files, so a damaged file can abort the
    interpreter: the files are walked first (colmap_files.check_model, about half
    pycolmap's own read time), unless their SHA-256 is `digest`, a model we wrote.
    """
    sparse_dir = Path(sparse_dir)
    if digest is None or model_digest(sparse_dir) != digest:
        check_model(sparse_dir)
    model = read_model(sparse_dir)
    if pinhole_only:
        for cid, cam in model._rec.cameras.items():
            if _model_name(cam) not in ("PINHOLE", "SIMPLE_PINHOLE"):
                raise SplatError(f"{sparse_dir}: camera {cid} is {_model_name(cam)}, expected PINHOLE (undistorted)")
    points, colors = model.points()
    return SceneData(cameras=model.cameras(), points=points, colors=colors, views_per_point=model.mean_track_length(),
                     observed=model.observations())
