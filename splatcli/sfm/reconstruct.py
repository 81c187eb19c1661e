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

import numpy as np

from ..camera import Camera
from ..errors import SplatError
from ..events import EventSink, Note, Stages, emit
from . import colmap
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
class SfmResult:
    model: Model
    names: list[str]  # every input image
    model_sizes: list[int]  # registered images per model, largest first
    unregistered: list[str]
    matcher: str  # the pairing used in the end ("sequential+exhaustive" after a fallback)
    num_pairs: int
    keypoints_median: float
    seconds: dict[str, float] = field(default_factory=dict)
    left_out_models: dict[str, int | None] = field(default_factory=dict)  # unregistered -> model it fell into (2: the second largest), None: none
    tried: list[str] = field(default_factory=list)  # the mapping attempts made
    cameras: list[list[str]] = field(default_factory=list)  # the grouping of the kept model's database


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


# Images a mapping left out are matched again with every image when that is at most this many pairs,
# or as many as the first matching had (a bounded retry); beyond, with the images most like each.
EVERY_PAIR_MIN = 2000
# One camera each is kept over a shared one when the focal lengths it finds spread by more
# than this (90th over 10th percentile): far less on fox's photos from one camera, far more on
# the same photos cropped as four zooms (docs/benchmarks.md, "process").
FOCAL_SPREAD = 1.15
# Every image registered on a shared camera: the focal lengths found for each image alone (its pose
# with the focal length unknown, from its matches in that model) under this spread (90th over 10th
# percentile) mean one camera fits them, and no mapping with a camera each is tried. A shared camera
# bends the model towards itself, so photos from several cameras spread far less here than their true
# focal lengths do (docs/guide.md, "Cameras grouped as the photos were taken"): 1.11x for a quarter of the sample's views zoomed 1.5x.
ONE_CAMERA_SPREAD = 1.05
# SIFT goes again to the upsampled octave when its image's short side is under this and the
# mapping left over 10% of the images out (not for a few blurry frames of a video): upsampling
# larger images costs much and is rarely needed.
UPSAMPLE_BELOW = 1000
UPSAMPLED = "SIFT again on the upsampled octave"  # its line in `tried` starts so (what it gave, "not kept" after)


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


def run_sfm(image_dir: Path, names: list[str], work_dir: Path, opts: SfmOptions, *,
            cameras: list[list[str]], min_side: int, where: Path, split_cameras: list[list[str]] | None = None,
            on_event: EventSink | None = None, mask_dir: Path | None = None, features_ready: bool = False,
            on_features: Callable[[], None] | None = None) -> SfmResult:
    """Extract, match and map `names` (files in `image_dir`).

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
    clock = Stages(on_event)
    names = sorted(names, key=natural_key)
    work_dir.mkdir(parents=True, exist_ok=True)
    db = work_dir / "database.db"
    cameras0 = cameras

    # -- features
    if features_ready:
        kp_median = _keypoint_median(db)
    else:
        kp_median = _extract(db, image_dir, names, opts, min_side, clock, mask_dir,
                             lambda: colmap.create_database(db, image_dir, cameras, camera_model=opts.camera_model))
    if on_features is not None:
        on_features()

    # -- matching
    matcher = choose_matcher(opts, names)
    mopts = MatchOptions(num_threads=opts.num_threads, seed=opts.seed)
    sim: list[np.ndarray] = []  # the images' likeness (retrieval), computed once when first asked for

    def alike(k: int, of: set[str] | None = None) -> list[tuple[str, str]]:
        if not sim:
            with clock.stage("retrieve pairs", 1) as st:
                sim.append(similarity(colmap.read_descriptors(db, names), seed=opts.seed))
                st.progress(1)
        return nearest_pairs(names, sim[0], k, of)

    large = len(names) >= LARGE_CAPTURE
    if matcher == "sequential":
        pairs = sequential_pairs(names, opts.sequential_overlap)
        if opts.loop_neighbours and len(names) > 2 * opts.sequential_overlap:
            # A walk that comes back to where it started meets its own first frames far apart in
            # time: those pairs come from retrieval. In a long capture it also replaces the pairs
            # 2^k frames apart beyond 4x the overlap, which cost as much to match as any pair and
            # seldom match (250 frames of a walk around a monument: 21 of 526 such pairs verified).
            if large:
                at = {n: i for i, n in enumerate(names)}
                pairs = [q for q in pairs if at[q[1]] - at[q[0]] <= FAR_PAIRS * opts.sequential_overlap]
            known = set(pairs)
            pairs += [q for q in alike(opts.loop_neighbours) if q not in known]
    elif matcher == "retrieval":
        pairs = alike(opts.retrieval_neighbours)
    else:
        pairs = exhaustive_pairs(names)
        if len(names) > 200:
            emit(on_event, Note(f"matching all {len(pairs)} pairs of {len(names)} images will take long; "
                                "--matcher sequential is much faster for captures taken in order"))
    _match(db, pairs, work_dir, mopts, clock)
    matched = set(pairs)

    # -- mapping
    mapper = MapperOptions(seed=opts.seed, min_model_size=min(10, max(2, len(names) // 4)),
                           **(LARGE_MAPPER if large else {}))
    models = _map(db, image_dir, work_dir / "models", mapper, len(names), clock)
    used = matcher
    if matcher != "exhaustive" and opts.matcher == "auto" and (not models or models[0].num_registered < len(names)):
        out = set(names) - set(models[0].registered_names() if models else [])
        # Only pairs touching a left-out image: one bad frame in a long video must not cost N^2 pairs.
        # And no more of them than the first matching had: where many are left out, each is matched
        # with the images most like it (retrieval) instead of with every image.
        rest = [p for p in exhaustive_pairs(names) if p not in matched and (p[0] in out or p[1] in out)]
        if len(rest) <= max(len(matched), EVERY_PAIR_MIN):
            emit(on_event, Note(f"{matcher} matching left {len(out)} image(s) out; matching them with every image"))
            used = f"{matcher}+exhaustive"
        else:
            every, rest = len(rest), [p for p in alike(opts.retrieval_neighbours, out) if p not in matched]
            k = opts.retrieval_neighbours
            emit(on_event, Note(f"{matcher} matching left {len(out)} image(s) out; " + (
                f"matching each with the {k} images most like it ({len(rest):,} pairs, not the {every:,} with every "
                "image)" if rest else f"each was matched with the {k} images most like it already, and matching them "
                f"with every image would take {every:,} pairs: not tried (--matcher exhaustive does)")))
            used = f"{matcher}+retrieval" if rest else matcher
        if rest:
            _match(db, rest, work_dir, mopts, clock)
            matched.update(rest)
            models = _map(db, image_dir, work_dir / "models2", mapper, len(names), clock)
    tried = [f"{used} matching with COLMAP's thresholds"]
    if large:
        tried.append(f"mapped on every core, a global bundle adjustment each time the model grew by "
                     f"{LARGE_MAPPER['ba_global_frames_ratio'] - 1:.0%} ({len(names)} images; below {LARGE_CAPTURE}: "
                     "one thread, which repeats run to run)")
    if not models or models[0].num_registered < 2:
        # Try harder: a starting pair with fewer inliers and less parallax than COLMAP asks for.
        mapper = replace(mapper, **RELAXED_INIT)
        emit(on_event, Note("no model with COLMAP's thresholds; mapping again with relaxed initial-pair thresholds"))
        t0 = time.perf_counter()
        models = _map(db, image_dir, work_dir / "models_relaxed", mapper, len(names), clock)
        tried.append(f"relaxed initial-pair thresholds ({RELAXED_INIT['init_min_num_inliers']} inliers, "
                     f"{RELAXED_INIT['init_min_tri_angle']:g} degrees){_outcome(models, t0, on_event, 'relaxed initial-pair thresholds')}")
    weak_split = False
    if split_cameras is not None and models and models[0].num_registered == len(names):
        # Every image registered: a second mapping with a camera each pays only where one shared
        # camera does not fit them. Each image's focal length found on its own (from its matches in
        # the model) tells that at once: about the same for photos from one camera, far apart for
        # photos from several forced onto one (which register, with bent poses).
        t0 = time.perf_counter()
        spread = _focal_spread(models[0].estimated_focals(), cameras, split_cameras)
        if spread <= ONE_CAMERA_SPREAD:
            emit(on_event, Note(f"all {len(names)} images registered, and the focal lengths found for each alone "
                                f"agree (spread {spread:.2f}x): one camera fits them; not mapping again with a "
                                "camera each (--per-image-cameras asks for that)"))
            tried.append(f"no mapping with {len(split_cameras)} cameras: every image registered, and the focal "
                         f"lengths found one image at a time spread {spread:.2f}x ({time.perf_counter() - t0:.1f} s)")
            split_cameras = None
    if split_cameras is not None:
        # Photos grouped by size alone may come from several cameras. One shared camera then
        # registers badly, or (worse) registers them all with poses bent to fit one focal
        # length. So they are also mapped with one camera each, and that model is kept when it
        # registers more, or nearly as many with focal lengths that differ (several cameras).
        n0 = models[0].num_registered if models else 0
        if n0 < len(names):
            emit(on_event, Note(f"{n0} of {len(names)} images registered with {len(cameras)} camera(s); mapping again "
                                f"with {len(split_cameras)} (the photos without EXIF camera data one each)"))
        else:
            emit(on_event, Note(f"the focal lengths found for each image alone spread {spread:.2f}x: the photos "
                                f"without EXIF camera data may come from several cameras; mapping again with "
                                f"{len(split_cameras)}, one each"))
        t0 = time.perf_counter()
        split_db = work_dir / "database_split.db"
        colmap.regroup_database(db, split_db, image_dir, split_cameras, camera_model=opts.camera_model)
        split = _map(split_db, image_dir, work_dir / "models_split", mapper, len(names), clock)
        tried.append(f"{len(split_cameras)} cameras instead of {len(cameras)} (the photos without EXIF apart)"
                     f"{_outcome(split, t0, on_event, f'{len(split_cameras)} cameras')}")
        weak_split = (split[0].num_registered if split else 0) < 0.9 * n0
        spread = _focal_spread(split[0].focal_lengths(), cameras, split_cameras) if split else 1.0
        if split and (split[0].num_registered > n0
                      or (split[0].num_registered >= 0.9 * n0 and spread > FOCAL_SPREAD)):
            models, cameras = split, split_cameras
            split_db.replace(db)
            tried.append(f"kept one camera each (their focal lengths spread {spread:.2f}x)")
    if models and 2 <= models[0].num_registered < len(names):
        # A second pass over the images left out: the largest model goes on, registering
        # with relaxed pose thresholds (what COLMAP's defaults refused may fit it now).
        before, t0 = models[0].num_registered, time.perf_counter()
        more = _map(db, image_dir, work_dir / "models_more", replace(mapper, **RELAXED_REGISTRATION), len(names),
                    clock, start=models[0])
        tried.append("a second pass over the images left out, with relaxed registration thresholds"
                     f"{_outcome(more, t0, None)}")
        if more and more[0].num_registered > before:
            emit(on_event, Note(f"a second pass registered {more[0].num_registered - before} more image(s)"))
            models = more
    n_best = models[0].num_registered if models else 0
    if octave(opts, min_side) == 0 and min_side < UPSAMPLE_BELOW and (weak_split or n_best < 0.9 * len(names)):
        # Too few features, perhaps: a camera each needs more to calibrate than a shared one
        # (on small real photos from different cameras it registered fewer than the shared camera,
        # which bent all to one focal length). SIFT again on COLMAP's upsampled octave.
        emit(on_event, Note(f"{n_best} of {len(names)} images registered"
                            + (" (fewer with a camera each)" if weak_split else "")
                            + "; extracting more features (SIFT on the upsampled octave) and mapping again"))
        t0 = time.perf_counter()
        try:
            again = run_sfm(image_dir, names, work_dir / "upsampled", replace(opts, first_octave=-1),
                            cameras=cameras0, min_side=min_side, where=where, split_cameras=split_cameras,
                            on_event=on_event, mask_dir=mask_dir)
        except SplatError:
            again = None
        tried.append(UPSAMPLED + _outcome([again.model] if again else [], t0, on_event, 'more features'))
        if again is not None and again.model.num_registered >= n_best:
            (work_dir / "upsampled" / "database.db").replace(db)
            again.tried[:0] = tried
            again.seconds = {k: clock.seconds.get(k, 0.0) + again.seconds.get(k, 0.0)
                             for k in {*clock.seconds, *again.seconds}}
            return again
        tried[-1] += f" (it registered {again.model.num_registered if again else 0}: not kept)"
    if not models or models[0].num_registered < 2:
        raise SplatError(f"{where}: structure from motion found no model (tried {'; '.join(tried)}): "
                         f"{_diagnose(db, len(names))}")
    best = models[0]
    registered = set(best.registered_names())
    fell_into = {}
    for k, m in enumerate(models[1:], start=2):
        for n in m.registered_names():
            fell_into.setdefault(n, k)
    unregistered = [n for n in names if n not in registered]
    return SfmResult(
        model=best,
        names=names,
        model_sizes=[m.num_registered for m in models],
        unregistered=unregistered,
        matcher=used,
        num_pairs=len(matched),
        keypoints_median=kp_median,
        seconds=clock.seconds,
        left_out_models={n: fell_into.get(n) for n in unregistered},
        tried=tried,
        cameras=cameras,
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
             mask_dir: Path | None, create: Callable[[], None]) -> float:
    """SIFT on `names` (files in `image_dir`) into the database `create` makes, within the
    "extract features" stage; the median keypoint count per image. `min_side`, the smallest
    image side SIFT sees, chooses the octave when `opts` leaves it open."""
    sift = SiftOptions(max_image_size=opts.max_image_size, max_num_features=opts.max_features,
                       first_octave=octave(opts, min_side), num_threads=opts.num_threads)
    with clock.stage("extract features", len(names)) as st:
        create()
        for i in range(0, len(names), opts.chunk):
            colmap.extract_features(db, image_dir, names[i : i + opts.chunk], sift, mask_dir=mask_dir)
            st.progress(min(i + opts.chunk, len(names)))
    return _keypoint_median(db)


def _keypoint_median(db: Path) -> float:
    """The median keypoint count per image in the database."""
    stats = colmap.database_stats(db)
    return float(statistics.median(stats.keypoints.values())) if stats.keypoints else 0.0


def octave(opts: SfmOptions, min_side: int) -> int:
    """SIFT's first octave: the options', else -1 (upsampled) when SIFT's image is under 400 px."""
    if opts.first_octave is not None:
        return opts.first_octave
    return -1 if min_side < 400 else 0


def _match(db: Path, pairs: list[tuple[str, str]], work_dir: Path, mopts: MatchOptions, clock: Stages) -> None:
    if not pairs:
        return
    with clock.stage("match", len(pairs)) as st:
        # Each call reloads descriptors and restarts threads, so calls carry
        # at least 100 pairs: ~10 progress updates at a small overhead.
        step = max(100, -(-len(pairs) // 10))
        for i in range(0, len(pairs), step):
            colmap.match_pairs(db, pairs[i : i + step], work_dir / "pairs.txt", mopts)
            st.progress(min(i + step, len(pairs)))


def _outcome(models: list[Model], t0: float, on_event: EventSink | None, label: str = "") -> str:
    """What an attempt gave, for its line in `tried`; also one line of output, `label` first,
    when `on_event`."""
    n = models[0].num_registered if models else 0
    out = f": {n} registered in {time.perf_counter() - t0:.0f} s"
    emit(on_event, Note(f"{label}{out}"))
    return out


def _map(db: Path, image_dir: Path, out: Path, mapper: MapperOptions, n: int, clock: Stages,
         start: Model | None = None) -> list[Model]:
    """Every model mapping makes, largest first; `start`: a model to go on from."""
    with clock.stage("map", n) as st:
        return colmap.incremental_mapping(db, image_dir, out, mapper, start=start,
                                          on_registered=lambda k: st.progress(min(k, n), registered=k))


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
