"""Images to a COLMAP model: SIFT, pair selection, matching, incremental mapping.

Speed on a CPU comes from three choices (measured on fox: docs/benchmarks.md, "process"):
  * SIFT at the image's own resolution (`first_octave = 0`) instead of COLMAP's
    default upsampled octave: much faster extraction, still hundreds of
    well-localised features per image, which is what matching needs;
  * at most 4096 features per image, which bounds brute-force matching;
  * sequential pairs (each image with its next 5, plus exponentially spaced
    ones and its 5 most alike for loop closure) for video and numbered captures,
    and pairs by retrieval (sfm/retrieval.py) for larger unordered sets, instead of
    all N(N-1)/2 pairs; images that this leaves out are then matched with every image.
"""

from __future__ import annotations

import re
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..camera import Camera
from ..errors import SplatError
from ..events import EventSink, Note, Stages, emit
from . import colmap
from .check import Consistency, check_model
from .colmap import MapperOptions, MatchOptions, Model, SiftOptions
from .retrieval import nearest_pairs, similarity

MATCHERS = ("auto", "exhaustive", "sequential", "retrieval")


@dataclass(frozen=True)
class SfmOptions:
    matcher: str = "auto"  # auto | exhaustive | sequential | retrieval
    ordered: bool = False  # frames of a video: sequential when auto
    exhaustive_max_images: int = 40  # auto: below this, all pairs are cheap enough
    sequential_overlap: int = 5  # neighbours each image is matched with (plus 2^k further ones)
    retrieval_neighbours: int = 20  # retrieval: each image is matched with this many most alike (sfm/retrieval.py)
    loop_neighbours: int = 5  # sequential: each image also with this many most alike, to close loops (0: none)
    max_image_size: int = 1600  # pixels: SIFT sees images shrunk to this (keypoints in full-size pixels)
    max_features: int = 4096
    first_octave: int | None = None  # None: 0, or -1 when SIFT's image is under 400 px (too few features otherwise)
    seed: int = 0
    num_threads: int = -1  # features and matching (-1: all cores); the mapper: one, all from LARGE_CAPTURE images
    chunk: int = 8  # images per extraction call (progress granularity)
    camera_model: str = "SIMPLE_RADIAL"  # the COLMAP model each camera is fitted with


@dataclass
class Tried:
    """One mapping attempt, for the manifest: what, why, its cost (estimated and spent), what it gave."""

    attempt: str
    why: str
    seconds: float = 0.0
    estimate_s: float | None = None  # what it was expected to cost, where that decided whether it ran
    registered: int | None = None  # images in its largest model (None: it did not run to the end)
    kept: bool = False
    result: str = ""  # anything else it found

    def summary(self) -> dict[str, Any]:
        out = {"attempt": self.attempt, "why": self.why, "seconds": round(self.seconds, 1)}
        if self.estimate_s is not None:
            out["estimate_s"] = round(self.estimate_s, 1)
        out.update(registered=self.registered, kept=self.kept)
        if self.result:
            out["result"] = self.result
        return out


@dataclass
class SfmResult:
    model: Model
    names: list[str]  # every input image
    model_sizes: list[int]  # registered images per model, largest first
    unregistered: list[str]  # images the kept model lacks (those placed apart from it among them)
    matcher: str  # the pairing used in the end ("sequential+exhaustive" after a fallback)
    num_pairs: int
    keypoints_median: float
    seconds: dict[str, float] = field(default_factory=dict)
    left_out_models: dict[str, int | None] = field(default_factory=dict)  # unregistered -> model it fell into (2: the second largest), None: none
    tried: list[Tried] = field(default_factory=list)  # the mapping attempts made
    cameras: list[list[str]] = field(default_factory=list)  # the grouping of the kept model's database
    consistency: Consistency | None = None  # the kept model's check (sfm/check.py)
    placed_apart: list[str] = field(default_factory=list)  # registered, but where no model agreed with its pairs: left out
    features_changed: bool = False  # the database's features are not all what the options make (more features)


# Thresholds of the second attempts (COLMAP's defaults: 100 inliers, 16 degrees, 4 px;
# 30 inliers and a ratio of 0.25 for each further image, 3 trials).
RELAXED_INIT = {"init_min_num_inliers": 50, "init_min_tri_angle": 8.0, "init_max_error": 6.0}
RELAXED_REGISTRATION = {"abs_pose_min_num_inliers": 15, "abs_pose_min_inlier_ratio": 0.15, "max_reg_trials": 5}
# From this many images, bundle adjustment is most of mapping (250 video frames: two thirds of it in
# 41 global BAs, the model refined every time it grew by a tenth). Such a capture is mapped on every
# core, with a global BA each time the model grew by 40%, without the points that well-covered images
# see anyway, and one refinement of each local BA: 2x faster there, to poses within 0.12 degree.
# Smaller captures keep COLMAP's schedule on one thread, which repeats exactly (the demo).
LARGE_CAPTURE = 100
FAR_PAIRS = 4  # large ordered captures: sequential pairs at most this many overlaps apart (the rest: retrieval)
LARGE_MAPPER = {"num_threads": -1, "ba_global_frames_ratio": 1.4, "ba_global_points_ratio": 1.4,
                "ba_global_ignore_redundant": True, "ba_local_max_refinements": 1, "ba_threads_min_residuals": 10000}
# Images a mapping left out are matched again with every image when that is at most this many pairs,
# or as many as the first matching had (a bounded retry); beyond, with the images most like each.
EVERY_PAIR_MIN = 2000
# One camera each is kept over a shared one when the focal lengths it finds spread by more
# than this (90th over 10th percentile): far less on fox's photos from one camera, far more on
# the same photos cropped as four zooms.
FOCAL_SPREAD = 1.15
# Every image registered on a shared camera: the focal lengths found for each image alone (its pose
# with the focal length unknown, from its matches in that model) under this spread (90th over 10th
# percentile) mean one camera fits them, and no mapping with a camera each is tried. A shared camera
# bends the model towards itself, so photos from several cameras spread far less here than their true
# focal lengths do (docs/guide.md, "Cameras grouped as the photos were taken"): 1.11x for a quarter of the sample's views zoomed 1.5x.
ONE_CAMERA_SPREAD = 1.05
# SIFT goes again to the upsampled octave when its image's short side is under this and the
# mapping left over 10% of the images out (not for a few blurry frames of a video): upsampling
# larger images costs much and is rarely needed. It runs on the images left out and the
# images each matches best (`MATCHED_BEST`), at about `UPSAMPLED_COST` times the first extraction's
# time per image, and only where its estimate fits under the cap: `RETRY_SHARE` of what `process`
# has spent so far (at least `RETRY_MIN_S`).
UPSAMPLE_BELOW = 1000
UPSAMPLED = "SIFT again on the upsampled octave"
UPSAMPLED_COST = 4.0
MATCHED_BEST = 3
RETRY_SHARE = 1.0
RETRY_MIN_S = 60.0
GLOBAL_MAPPER = "the global mapper"  # the repair of a model that fails the check (its `Tried.attempt` starts so)


def natural_key(name: str) -> list:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def looks_ordered(names: list[str]) -> bool:
    """Numbered captures (IMG_0001.JPG..., frame_12.png...): one prefix, one
    suffix, a number between. Such names are usually in capture order."""
    if len(names) < 3:
        return False
    pats = set()
    for n in names:
        m = re.fullmatch(r"(.*?)(\d+)(\D*)", n)
        if m is None:
            return False
        pats.add((m.group(1), m.group(3).lower()))
    return len(pats) == 1


def exhaustive_pairs(names: list[str]) -> list[tuple[str, str]]:
    return [(a, b) for i, a in enumerate(names) for b in names[i + 1 :]]


def sequential_pairs(names: list[str], overlap: int) -> list[tuple[str, str]]:
    """Each image with the next `overlap` ones, plus those 2^k further on
    (k beyond the overlap), which closes loops of an orbit cheaply."""
    n = len(names)
    out = set()
    for i in range(n):
        for j in range(i + 1, min(n, i + overlap + 1)):
            out.add((i, j))
        step = 1
        while step <= overlap:
            step *= 2
        while i + step < n:
            out.add((i, i + step))
            step *= 2
    return [(names[i], names[j]) for i, j in sorted(out)]


def posed_pairs(cameras: list[Camera], neighbours: int, max_angle_deg: float = 60.0) -> list[tuple[str, str]]:
    """Pairs of posed cameras likely to see the same things: each camera with its
    `neighbours` nearest (camera centres) among those looking within `max_angle_deg`
    of its own direction. Known poses make exhaustive pairs unnecessary."""
    if len(cameras) < 2:
        return []
    centers = np.stack([c.center for c in cameras])  # [N, 3]
    dirs = np.stack([c.viewmat[2, :3] for c in cameras])  # [N, 3] optical axes in world
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    dist = np.linalg.norm(centers[:, None] - centers[None], axis=2)  # [N, N]
    facing = dirs @ dirs.T >= np.cos(np.radians(max_angle_deg))
    dist = np.where(facing, dist, np.inf)
    np.fill_diagonal(dist, np.inf)
    out = set()
    for i in range(len(cameras)):
        for j in np.argsort(dist[i], kind="stable")[:neighbours]:
            if np.isfinite(dist[i, j]):
                out.add((min(i, int(j)), max(i, int(j))))
    names = [c.name for c in cameras]
    return sorted((names[i], names[j]) for i, j in out)


def choose_matcher(opts: SfmOptions, names: list[str]) -> str:
    if opts.matcher != "auto":
        return opts.matcher
    if opts.ordered:
        return "sequential"
    if len(names) <= opts.exhaustive_max_images:
        return "exhaustive"
    return "sequential" if looks_ordered(names) else "retrieval"


def _focal_spread(focals: dict[str, float], cameras: list[list[str]], split: list[list[str]]) -> float:
    """The largest spread (90th over 10th percentile) of the focal lengths found for the
    images of one shared camera of `cameras` that `split` takes apart (within a camera: other
    cameras, and other sizes, differ anyway)."""
    kept = {tuple(g) for g in split}
    out = 1.0
    for g in cameras:
        f = [focals[n] for n in g if n in focals]
        if tuple(g) not in kept and len(f) >= 2:
            lo, hi = np.percentile(f, [10, 90])
            out = max(out, float(hi / lo) if lo > 0 else float("inf"))
    return out


@dataclass
class _Sfm:
    """What the mapping attempts share: the database, the images and the models so far.
    Each attempt (`ATTEMPTS`) takes it and returns better models, or None."""

    image_dir: Path
    where: Path  # the input, as error messages name it
    names: list[str]
    work: Path
    opts: SfmOptions
    cameras: list[list[str]]
    split_cameras: list[list[str]] | None
    min_side: int
    mask_dir: Path | None
    clock: Stages
    on_event: EventSink | None
    mapper: MapperOptions = field(init=False)
    models: list[Model] = field(default_factory=list)
    matcher: str = ""
    matched: set[tuple[str, str]] = field(default_factory=set)
    tried: list[Tried] = field(default_factory=list)
    weak_split: bool = False  # a camera each registered under 90% of what the shared camera did
    consistency: Consistency | None = None
    placed_apart: list[str] = field(default_factory=list)
    features_changed: bool = False  # the database's features are not those of the options (the upsampled retry)
    first_map_s: float = 0.0  # the first mapping's time, the measure of what mapping again costs
    started: float = field(default_factory=time.perf_counter)
    _sim: list[np.ndarray] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.mapper = MapperOptions(seed=self.opts.seed, min_model_size=min(10, max(2, len(self.names) // 4)),
                                    **(LARGE_MAPPER if self.large else {}))

    @property
    def db(self) -> Path:
        return self.work / "database.db"

    @property
    def large(self) -> bool:
        return len(self.names) >= LARGE_CAPTURE

    @property
    def registered(self) -> int:
        return self.models[0].num_registered if self.models else 0

    def note(self, message: str, level: str = "note") -> None:
        emit(self.on_event, Note(message, level))

    def spent(self, stage: str) -> float:
        return self.clock.seconds.get(stage, 0.0)

    def map(self, out: str, mapper: MapperOptions | None = None, db: Path | None = None,
            start: Model | None = None) -> list[Model]:
        """Every model mapping makes, largest first; `start`: a model to go on from."""
        n = len(self.names)
        with self.clock.stage("map", n) as st:
            return colmap.incremental_mapping(db or self.db, self.image_dir, self.work / out, mapper or self.mapper,
                                              start=start, on_registered=lambda k: st.progress(min(k, n), registered=k))

    def match(self, pairs: list[tuple[str, str]], db: Path | None = None) -> None:
        _match(db or self.db, pairs, self.work, MatchOptions(num_threads=self.opts.num_threads, seed=self.opts.seed),
               self.clock)

    def alike(self, k: int, of: set[str] | None = None) -> list[tuple[str, str]]:
        """Each image (of `of`) with the `k` most like it (retrieval), computed once when first asked for."""
        if not self._sim:
            with self.clock.stage("retrieve pairs", 1) as st:
                self._sim.append(similarity(colmap.read_descriptors(self.db, self.names), seed=self.opts.seed))
                st.progress(1)
        return nearest_pairs(self.names, self._sim[0], k, of)

    def attempt(self, attempt: str, why: str, models: list[Model] | None, t0: float, *, kept: bool = False,
                estimate_s: float | None = None, result: str = "") -> None:
        """Record an attempt started at `t0` (`models`: what it made, None: it stopped before the end)."""
        n = None if models is None else models[0].num_registered if models else 0
        self.tried.append(Tried(attempt, why, time.perf_counter() - t0, estimate_s, n, kept, result))

    def result(self, kp_median: float) -> SfmResult:
        if not self.models or self.registered < 2:
            lines = "; ".join(f"{t.attempt}: {t.registered or 0} registered" for t in self.tried)
            raise SplatError(f"{self.where}: structure from motion found no model (tried {lines}): "
                             f"{_diagnose(self.db, len(self.names))}")
        best = self.models[0]
        registered = set(best.registered_names())
        fell_into: dict[str, int] = {}
        for k, m in enumerate(self.models[1:], start=2):
            for n in m.registered_names():
                fell_into.setdefault(n, k)
        unregistered = [n for n in self.names if n not in registered]
        return SfmResult(model=best, names=self.names, model_sizes=[m.num_registered for m in self.models],
                         unregistered=unregistered, matcher=self.matcher, num_pairs=len(self.matched),
                         keypoints_median=kp_median, seconds=self.clock.seconds,
                         left_out_models={n: fell_into.get(n) for n in unregistered}, tried=self.tried,
                         cameras=self.cameras, consistency=self.consistency, placed_apart=self.placed_apart,
                         features_changed=self.features_changed)


def run_sfm(image_dir: Path, names: list[str], work_dir: Path, opts: SfmOptions, *,
            cameras: list[list[str]], min_side: int, where: Path, split_cameras: list[list[str]] | None = None,
            on_event: EventSink | None = None, mask_dir: Path | None = None, features_ready: bool = False,
            on_features: Callable[[], None] | None = None) -> SfmResult:
    """Extract, match and map `names` (files in `image_dir`); then the attempts of `ATTEMPTS`
    in turn, each taking the models so far and keeping what it makes where that is better.

    `cameras` groups the names into cameras (one camera per group: process/cameras.py);
    `split_cameras`, a finer grouping also mapped with, and kept when it registers more or
    finds different focal lengths (photos that share a camera only for want of EXIF may
    come from several);
    `min_side` is the smallest image side SIFT sees (chooses the octave); `mask_dir`
    holds a mask for every image, `<name>.png` (0: no features there); `where`
    names the input in error messages; `features_ready`: work_dir/database.db holds every image's
    features already (an earlier run's, with its matches: only new pairs are matched);
    `on_features`: called once the database holds every image's features. Raises SplatError
    (with the likely cause) when no model comes out."""
    work_dir.mkdir(parents=True, exist_ok=True)
    s = _Sfm(image_dir, where, sorted(names, key=natural_key), work_dir, opts, cameras, split_cameras, min_side, mask_dir,
             Stages(on_event), on_event)
    if features_ready:
        kp_median = _keypoint_median(s.db)
    else:
        kp_median = _extract(s.db, image_dir, s.names, opts, min_side, s.clock, mask_dir,
                             lambda: colmap.create_database(s.db, image_dir, cameras, camera_model=opts.camera_model))
    if on_features is not None:
        on_features()
    t0 = time.perf_counter()
    s.matcher = choose_matcher(opts, s.names)
    pairs = _first_pairs(s)
    s.match(pairs)
    s.matched = set(pairs)
    t_map = time.perf_counter()
    s.models = s.map("models")
    s.first_map_s = time.perf_counter() - t_map
    schedule = (f"; mapped on every core, a global bundle adjustment each time the model grew by "
                f"{LARGE_MAPPER['ba_global_frames_ratio'] - 1:.0%}" if s.large else "; mapped on one thread")
    s.attempt(f"{s.matcher} matching with COLMAP's thresholds{schedule}",
              f"{len(s.names)} images" + (f" (from {LARGE_CAPTURE}: every core)" if s.large
                                          else f" (below {LARGE_CAPTURE}: one thread, which repeats run to run)"),
              s.models, t0, kept=True)
    for attempt in ATTEMPTS:
        better = attempt(s)
        if better is not None:
            s.models = better
    return s.result(kp_median)


def _first_pairs(s: _Sfm) -> list[tuple[str, str]]:
    """The pairs the chosen matcher makes."""
    opts, names = s.opts, s.names
    if s.matcher == "sequential":
        pairs = sequential_pairs(names, opts.sequential_overlap)
        if opts.loop_neighbours and len(names) > 2 * opts.sequential_overlap:
            # A walk that comes back to where it started meets its own first frames far apart in
            # time: those pairs come from retrieval. In a long capture it also replaces the pairs
            # 2^k frames apart beyond 4x the overlap, which cost as much to match as any pair and
            # seldom match (250 frames of a walk around a monument: 21 of 526 such pairs verified).
            if s.large:
                at = {n: i for i, n in enumerate(names)}
                pairs = [q for q in pairs if at[q[1]] - at[q[0]] <= FAR_PAIRS * opts.sequential_overlap]
            known = set(pairs)
            pairs += [q for q in s.alike(opts.loop_neighbours) if q not in known]
        return pairs
    if s.matcher == "retrieval":
        return s.alike(opts.retrieval_neighbours)
    pairs = exhaustive_pairs(names)
    if len(names) > 200:
        s.note(f"matching all {len(pairs)} pairs of {len(names)} images will take long; "
               "--matcher sequential is much faster for captures taken in order")
    return pairs


def _match_left_out(s: _Sfm) -> list[Model] | None:
    """Images the first pairs left out of the model, matched again: with every image where that is
    bounded, else with the images most like each."""
    n = len(s.names)
    if s.matcher == "exhaustive" or s.opts.matcher != "auto" or s.registered >= n:
        return None
    out = set(s.names) - set(s.models[0].registered_names() if s.models else [])
    # Only pairs touching a left-out image: one bad frame in a long video must not cost N^2 pairs.
    # And no more of them than the first matching had: where many are left out, each is matched
    # with the images most like it (retrieval) instead of with every image.
    rest = [p for p in exhaustive_pairs(s.names) if p not in s.matched and (p[0] in out or p[1] in out)]
    first = s.matcher
    if len(rest) <= max(len(s.matched), EVERY_PAIR_MIN):
        s.note(f"{first} matching left {len(out)} image(s) out; matching them with every image")
        s.matcher = f"{first}+exhaustive"
    else:
        every, rest = len(rest), [p for p in s.alike(s.opts.retrieval_neighbours, out) if p not in s.matched]
        k = s.opts.retrieval_neighbours
        s.note(f"{first} matching left {len(out)} image(s) out; " + (
            f"matching each with the {k} images most like it ({len(rest):,} pairs, not the {every:,} with every "
            "image)" if rest else f"each was matched with the {k} images most like it already, and matching them "
            f"with every image would take {every:,} pairs: not tried (--matcher exhaustive does)"))
        if not rest:
            return None
        s.matcher = f"{first}+retrieval"
    t0 = time.perf_counter()
    s.match(rest)
    s.matched.update(rest)
    models = s.map("models2")
    s.attempt(f"{len(out)} image(s) left out matched again ({len(rest):,} pairs)", f"{first} matching left them out",
              models, t0, kept=True)
    return models


def _relaxed_start(s: _Sfm) -> list[Model] | None:
    """No model: a starting pair with fewer inliers and less parallax than COLMAP asks for."""
    if s.registered >= 2:
        return None
    s.note("no model with COLMAP's thresholds; mapping again with relaxed initial-pair thresholds")
    t0 = time.perf_counter()
    s.mapper = replace(s.mapper, **RELAXED_INIT)
    models = s.map("models_relaxed")
    s.attempt(f"relaxed initial-pair thresholds ({RELAXED_INIT['init_min_num_inliers']} inliers, "
              f"{RELAXED_INIT['init_min_tri_angle']:g} degrees)", "no model with COLMAP's thresholds", models, t0,
              kept=True)
    _said(s, "relaxed initial-pair thresholds")
    return models


def _camera_each(s: _Sfm) -> list[Model] | None:
    """Photos grouped by size alone may come from several cameras. One shared camera then
    registers badly, or (worse) registers them all with poses bent to fit one focal length. So
    they are mapped again with a camera each, kept when that registers more, or nearly as many
    with focal lengths that differ (several cameras)."""
    if s.split_cameras is None:
        return None
    n, n0, t0 = len(s.names), s.registered, time.perf_counter()
    if n0 == n:
        # Every image registered: each one's focal length found on its own (from its matches in
        # the model) tells at once whether one camera fits them: about the same for photos from one
        # camera, far apart for photos from several forced onto one (which register, with bent poses).
        spread = _focal_spread(s.models[0].estimated_focals(seed=s.opts.seed), s.cameras, s.split_cameras)
        if spread <= ONE_CAMERA_SPREAD:
            s.note(f"all {n} images registered, and the focal lengths found for each alone agree (spread "
                   f"{spread:.2f}x): one camera fits them; not mapping again with a camera each "
                   "(--per-image-cameras asks for that)")
            s.tried.append(Tried(f"no mapping with {len(s.split_cameras)} cameras", f"every image registered, and "
                                 f"the focal lengths found one image at a time spread {spread:.2f}x",
                                 time.perf_counter() - t0))
            return None
        s.note(f"the focal lengths found for each image alone spread {spread:.2f}x: the photos without EXIF "
               f"camera data may come from several cameras; mapping again with {len(s.split_cameras)}, one each")
        why = f"the focal lengths found one image at a time spread {spread:.2f}x"
    else:
        s.note(f"{n0} of {n} images registered with {len(s.cameras)} camera(s); mapping again with "
               f"{len(s.split_cameras)} (the photos without EXIF camera data one each)")
        why = f"{n0} of {n} images registered with {len(s.cameras)} camera(s)"
    split_db = s.work / "database_split.db"
    colmap.copy_database(s.db, split_db, s.image_dir, s.split_cameras, camera_model=s.opts.camera_model)
    split = s.map("models_split", db=split_db)
    s.weak_split = (split[0].num_registered if split else 0) < 0.9 * n0
    spread = _focal_spread(split[0].focal_lengths(), s.cameras, s.split_cameras) if split else 1.0
    keep = bool(split) and (split[0].num_registered > n0
                            or (split[0].num_registered >= 0.9 * n0 and spread > FOCAL_SPREAD))
    s.attempt(f"{len(s.split_cameras)} cameras instead of {len(s.cameras)} (the photos without EXIF apart)", why,
              split, t0, kept=keep, result=f"kept one camera each (their focal lengths spread {spread:.2f}x)"
              if keep else "")
    _said(s, f"{len(s.split_cameras)} cameras")
    if not keep:
        return None
    s.cameras = s.split_cameras
    split_db.replace(s.db)
    return split


def _second_pass(s: _Sfm) -> list[Model] | None:
    """The largest model goes on over the images left out, with relaxed pose thresholds (what
    COLMAP's defaults refused may fit it now)."""
    if not 2 <= s.registered < len(s.names):
        return None
    before, t0 = s.registered, time.perf_counter()
    more = s.map("models_more", replace(s.mapper, **RELAXED_REGISTRATION), start=s.models[0])
    keep = bool(more) and more[0].num_registered > before
    s.attempt("a second pass over the images left out, with relaxed registration thresholds",
              f"{len(s.names) - before} image(s) left out", more, t0, kept=keep)
    if not keep:
        return None
    s.note(f"a second pass registered {more[0].num_registered - before} more image(s)")
    return more


def _more_features(s: _Sfm) -> list[Model] | None:
    """Too few features, perhaps: SIFT again on COLMAP's upsampled octave, then mapping again. On
    the images left out and those each matches best; where a camera each registered fewer than
    the shared camera (it needs more features to calibrate), on every image, mapped a camera each.
    Only where its estimated cost fits under the cap, which also stops it."""
    n, n_best = len(s.names), s.registered
    if octave(s.opts, s.min_side) != 0 or s.min_side >= UPSAMPLE_BELOW or not (s.weak_split or n_best < 0.9 * n):
        return None
    out = set(s.names) - {x for m in s.models for x in m.registered_names()}  # in no model: too few features?
    if not (out or s.weak_split):
        s.tried.append(Tried(UPSAMPLED, f"{n - n_best} of {n} images left out", 0.0, None, None, False,
                             "not run: the images left out registered in models of their own (they have features "
                             "enough; nothing joins them to the largest)"))
        return None
    redo = set(s.names) if s.weak_split or not s.models else out | _matched_best(s.db, out, MATCHED_BEST)
    pairs = sorted(p for p in s.matched | set(s.alike(s.opts.retrieval_neighbours, out)) if set(p) & redo)
    per_image = s.spent("extract features") / max(n, 1)
    per_pair = s.spent("match") / max(len(s.matched), 1)
    estimate = UPSAMPLED_COST * per_image * len(redo) + per_pair * len(pairs) + s.first_map_s
    cap = max(RETRY_MIN_S, RETRY_SHARE * (time.perf_counter() - s.started))
    what = f"{UPSAMPLED}, on {len(redo)} of {n} images"
    why = f"{n_best} of {n} images registered" + (" (fewer with a camera each)" if s.weak_split else "")
    if estimate > cap:
        s.note(f"{why}; {UPSAMPLED[0].lower()}{UPSAMPLED[1:]} would take about {estimate:.0f} s, over the "
               f"{cap:.0f} s a retry may take now: not tried")
        s.tried.append(Tried(what, why, 0.0, estimate, None, False, f"not run: over the cap of {cap:.0f} s"))
        return None
    s.note(f"{why}; extracting more features (SIFT on the upsampled octave) on {len(redo)} image(s) and mapping "
           f"again (about {estimate:.0f} s, at most {cap:.0f} s)")
    cams = s.split_cameras if s.weak_split and s.split_cameras is not None else s.cameras
    t0, db = time.perf_counter(), s.work / "database_more.db"
    colmap.copy_database(s.db, db, s.image_dir, cams, camera_model=s.opts.camera_model, without=redo)
    try:
        with colmap.deadline(time.monotonic() + cap):
            _extract(db, s.image_dir, sorted(redo, key=natural_key), replace(s.opts, first_octave=-1), s.min_side,
                     s.clock, s.mask_dir, None)
            s.match(pairs, db)
            models = s.map("models_upsampled", db=db)
    except colmap.OverTime:
        s.attempt(what, why, None, t0, estimate_s=estimate, result=f"stopped at the cap of {cap:.0f} s")
        _said(s, "more features")
        return None
    got = models[0].num_registered if models else 0
    spread = _focal_spread(models[0].focal_lengths(), s.cameras, cams) if models and cams is not s.cameras else 1.0
    keep = got > n_best or (cams is not s.cameras and got >= 0.9 * n_best and spread > FOCAL_SPREAD)
    s.attempt(what, why, models, t0, estimate_s=estimate, kept=keep,
              result=f"kept one camera each (their focal lengths spread {spread:.2f}x)" if keep and cams is not s.cameras
              else "")
    _said(s, "more features")
    if not keep:
        return None
    db.replace(s.db)
    s.cameras, s.features_changed = cams, True
    s.matched.update(pairs)
    return models


def _matched_best(db: Path, names: set[str], k: int) -> set[str]:
    """The `k` images with the most verified matches to each of `names`."""
    best: dict[str, list[tuple[int, str]]] = {n: [] for n in names}
    pairs, _ = colmap.read_verified_pairs(db, keypoints=False)
    for p in pairs:
        for a, b in ((p.a, p.b), (p.b, p.a)):
            if a in best:
                best[a].append((len(p.matches), b))
    return {b for n in names for _, b in sorted(best[n], reverse=True)[:k]}


def _check(s: _Sfm) -> list[Model] | None:
    """The kept model against its pairs' own geometry (sfm/check.py)."""
    if not s.models or s.registered < 3:
        return None
    t0 = time.perf_counter()
    s.consistency = check_model(s.db, s.models[0])
    s.attempt("the consistency check", "every model is checked", s.models, t0, kept=True,
              result=s.consistency.line())
    if not s.consistency.consistent:
        s.note(f"the model fails the consistency check: {s.consistency.line()}", "warning")
    return None


def _global_repair(s: _Sfm) -> list[Model] | None:
    """A model that fails the check is mapped again with the global mapper, which places every
    camera at once from all the pairs (an incremental mapper can join an arc of cameras to the
    rest by a few false pairs); kept when it passes the check."""
    if s.consistency is None or s.consistency.consistent:
        return None
    estimate = 2.0 * s.first_map_s
    cap = max(2 * RETRY_MIN_S, time.perf_counter() - s.started)
    s.note(f"mapping again with the global mapper, which places every camera at once (about {estimate:.0f} s, "
           f"at most {cap:.0f} s)")
    t0 = time.perf_counter()
    try:
        with s.clock.stage("map (global)", None), colmap.deadline(time.monotonic() + cap):
            models = colmap.global_mapping(s.db, s.image_dir, s.work / "models_global", seed=s.opts.seed,
                                           num_threads=s.mapper.num_threads)
    except colmap.OverTime:
        s.attempt(GLOBAL_MAPPER, "the model failed the consistency check", None, t0, estimate_s=estimate,
                  result=f"stopped at the cap of {cap:.0f} s")
        return None
    check = check_model(s.db, models[0]) if models and models[0].num_registered >= 3 else None
    keep = check is not None and check.consistent and models[0].num_registered >= len(s.consistency.parts[0])
    s.attempt(GLOBAL_MAPPER, "the model failed the consistency check", models, t0, estimate_s=estimate, kept=keep,
              result=check.line() if check is not None else "no model")
    if keep:
        s.note(f"the global mapper's model passes the check: {check.line()}; keeping it")
        s.consistency = check
        return models
    if check is not None and len(check.parts[0]) > len(s.consistency.parts[0]):
        s.consistency = check  # its consistent part is the larger: the split below takes it
        return models
    return None


def _keep_consistent_part(s: _Sfm) -> list[Model] | None:
    """Where no model passes the check: the largest part whose pairs agree is kept, and the
    images placed apart from it are left out (named in a warning and the manifest)."""
    if s.consistency is None or s.consistency.consistent:
        return None
    part = s.consistency.parts[0]
    s.placed_apart = s.consistency.named()
    model = s.models[0]
    model.keep_images(part)
    s.note(f"no model passed the consistency check: keeping the {len(part)} images whose pairs agree and leaving "
           f"out {len(s.placed_apart)} placed apart from them ({', '.join(s.placed_apart[:12])}"
           f"{', ...' if len(s.placed_apart) > 12 else ''})", "warning")
    s.tried.append(Tried("the largest consistent part kept", "no model passed the consistency check", 0.0, None,
                         model.num_registered, True, f"{len(s.placed_apart)} image(s) left out"))
    return [model] + s.models[1:]


def _said(s: _Sfm, label: str) -> None:
    """The last attempt's outcome, as one line of output."""
    t = s.tried[-1]
    s.note(f"{label}: {t.registered or 0} registered in {t.seconds:.0f} s" + (f" ({t.result})" if t.result else ""))


# The attempts after the first mapping, in order; each takes the models so far and returns better
# ones, or None.
ATTEMPTS: tuple[Callable[[_Sfm], list[Model] | None], ...] = (
    _match_left_out, _relaxed_start, _camera_each, _second_pass, _more_features, _check, _global_repair,
    _keep_consistent_part,
)


@dataclass
class TriangulationResult:
    model: Model  # the posed model with the triangulated points
    num_pairs: int
    keypoints_median: float
    seconds: dict[str, float] = field(default_factory=dict)


def triangulate_posed(image_dir: Path, model: Model, work_dir: Path, opts: SfmOptions, *, neighbours: int,
                      min_side: int, on_event: EventSink | None = None,
                      mask_dir: Path | None = None) -> TriangulationResult:
    """Points for a capture whose poses are known (transforms.json, LLFF): SIFT as for
    photos, matching of the pairs the poses say overlap (`posed_pairs`), then
    triangulation with every pose and intrinsic held fixed; no mapping. `model` holds
    the posed images (in `image_dir`), with their distortion."""
    clock = Stages(on_event)
    work_dir.mkdir(parents=True, exist_ok=True)
    db = work_dir / "database.db"
    names = model.registered_names()
    kp_median = _extract(db, image_dir, names, opts, min_side, clock, mask_dir,
                         lambda: colmap.create_posed_database(db, model))
    pairs = posed_pairs(model.cameras(), neighbours)
    _match(db, pairs, work_dir, MatchOptions(num_threads=opts.num_threads, seed=opts.seed), clock)
    with clock.stage("triangulate", 1) as st:
        mapper = MapperOptions(seed=opts.seed)
        out = colmap.triangulate(model, db, image_dir, work_dir / "triangulated", mapper)
        st.progress(1)
    return TriangulationResult(model=out, num_pairs=len(pairs), keypoints_median=kp_median,
                               seconds=clock.seconds)


def _extract(db: Path, image_dir: Path, names: list[str], opts: SfmOptions, min_side: int, clock: Stages,
             mask_dir: Path | None, create: Callable[[], None] | None) -> float:
    """SIFT on `names` (files in `image_dir`) into the database `create` makes (None: the database
    holds the images already, without features), within the
    "extract features" stage; the median keypoint count per image. `min_side`, the smallest
    image side SIFT sees, chooses the octave when `opts` leaves it open."""
    sift = SiftOptions(max_image_size=opts.max_image_size, max_num_features=opts.max_features,
                       first_octave=octave(opts, min_side), num_threads=opts.num_threads)
    with clock.stage("extract features", len(names)) as st:
        if create is not None:
            create()
        for i in range(0, len(names), opts.chunk):
            colmap.extract_features(db, image_dir, names[i : i + opts.chunk], sift, mask_dir=mask_dir)
            st.progress(min(i + opts.chunk, len(names)))
    return _keypoint_median(db)


def _match(db: Path, pairs: list[tuple[str, str]], work_dir: Path, mopts: MatchOptions, clock: Stages) -> None:
    if not pairs:
        return
    with clock.stage("match", len(pairs)) as st:
        colmap.match_pairs(db, pairs, work_dir, mopts, on_progress=st.progress)


def _keypoint_median(db: Path) -> float:
    """The median keypoint count per image in the database."""
    counts = colmap.keypoint_counts(db)  # (not database_stats: the two-view geometries are not needed here)
    return float(statistics.median(counts.values())) if counts else 0.0


def octave(opts: SfmOptions, min_side: int) -> int:
    """SIFT's first octave: the options', else -1 (upsampled) when SIFT's image is under 400 px."""
    if opts.first_octave is not None:
        return opts.first_octave
    return -1 if min_side < 400 else 0


def _diagnose(db: Path, n: int) -> str:
    """The likely reason mapping failed, from what the database holds."""
    stats = colmap.database_stats(db)
    kp = sorted(stats.keypoints.values())
    med = kp[len(kp) // 2] if kp else 0
    if med < 100:
        return (f"too few features (median {med} per image): the images are too small, blurry or "
                "textureless; try a larger --max-size or sharper photos")
    if stats.verified_pairs == 0:
        return "no two images share enough matching features: too little overlap between the photos"
    if stats.verified_pairs < n - 1:
        return (f"only {stats.verified_pairs} image pairs match well: too little overlap between the photos "
                "(take them closer together)")
    return ("no image pair gives a good starting reconstruction: too little camera motion (parallax) "
            "or too little overlap")
