"""What `splatcli process` is asked to do, and what it reports back."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from ..errors import SplatError
from ..sfm.reconstruct import MATCHERS
from .cameras import CAMERA_MODELS, CAMERA_MODES

MIN_IMAGES = 2
SFM_MAX_SIZE = 1600  # --max-size's default for structure from motion
POSED_MAX_SIZE = 1000  # and for the points of posed captures (transforms.json, LLFF)


@dataclass(frozen=True)
class ProcessConfig:
    input_type: str = "auto"  # auto | images | video | colmap | transforms | llff
    max_size: int | None = None  # longest side, pixels, of the image SIFT sees (the dataset keeps full resolution);
    # None: SFM_MAX_SIZE for photos and video, POSED_MAX_SIZE for posed captures
    matcher: str = "auto"  # auto | exhaustive | sequential | retrieval
    fps: float | None = None  # video: frames per second of video to extract
    num_frames: int = 100  # video: frames to extract when fps is not given
    background: tuple[float, float, float] | None = None  # RGB in [0, 1]; None: white for RGBA inputs, else black
    overwrite: bool = False
    seed: int = 0
    max_features: int = 4096  # SIFT features per image
    first_octave: int | None = None  # SIFT: None picks 0, or -1 (upsampled) for images under 400 px
    sequential_overlap: int = 5  # neighbours each image is matched with (plus 2^k further ones)
    blur_ratio: float = 0.6  # video: drop frames less sharp than this x their neighbours' median
    num_threads: int = -1  # SIFT and matching (-1: all cores); the mapper runs on one, to be repeatable
    strict: bool = False  # an unreadable image or video frame is an error instead of a skipped input
    invert_masks: bool = False  # mask files given with white = masked out (flipped to the project's 255 = keep)
    triangulate: bool = True  # posed captures: points triangulated from the photos with the poses fixed
    cameras: str = "auto"  # SfM: auto (video; EXIF make, model, focal length, size) | single | per-image (process/cameras.py)
    camera_model: str = "SIMPLE_RADIAL"  # SfM: the COLMAP camera model fitted (undistorted to PINHOLE after)


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
    mask_source: str | None = None  # "alpha" or "files"; None without masks
    matcher: str | None = None  # the image pairs matched (SfM only)
    pairs: int = 0
    keypoints_median: float | None = None  # SIFT features per image (SfM only)
    model_sizes: list[int] = field(default_factory=list)  # images per SfM model, largest first
    unregistered: list[str] = field(default_factory=list)
    left_out_models: dict[str, int | None] = field(default_factory=dict)  # unregistered image -> the model (numbered
    # by size: 1 is the kept one) it registered in instead, None for none
    sfm_tried: list[dict[str, Any]] = field(default_factory=list)  # the mapping attempts made: what, why, cost, result
    consistency: dict[str, Any] | None = None  # SfM: the model's poses against its image pairs' own geometry
    placed_apart: list[str] = field(default_factory=list)  # SfM: images left out because no model placed them
    # where their pairs say (among `unregistered` too)
    skipped: list[str] = field(default_factory=list)  # "name: reason"
    missing: int = 0  # files listed by the input but absent
    dropped_blurry: int = 0
    triangulated: int | None = None  # posed captures: points triangulated with the poses fixed (kept or not)
    camera_grouping: str | None = None  # SfM: how images were grouped into cameras (process/cameras.py)
    cameras: list[dict[str, Any]] = field(default_factory=list)  # SfM: each camera's images and EXIF facts
    warnings: list[str] = field(default_factory=list)
    repeatable: bool = True  # the same input, options and --seed give the same model on one machine (False for SfM
    # from 100 photos, mapped on every core, which COLMAP does not promise to repeat)

    def summary(self) -> dict[str, Any]:
        d = asdict(self)
        d["project"] = str(self.project)
        d["input"] = str(self.input)
        return d


def check_config(cfg: ProcessConfig) -> None:
    if cfg.matcher not in MATCHERS:
        raise SplatError(f"--matcher {cfg.matcher!r}: expected one of {', '.join(MATCHERS)}")
    if cfg.max_size is not None and cfg.max_size < 32:
        raise SplatError(f"--max-size {cfg.max_size}: must be at least 32 pixels")
    if cfg.fps is not None and not (cfg.fps > 0 and math.isfinite(cfg.fps)):
        raise SplatError(f"--fps {cfg.fps}: must be a positive number")
    if cfg.num_frames < MIN_IMAGES:
        raise SplatError(f"--num-frames {cfg.num_frames}: must be at least {MIN_IMAGES}")
    if cfg.cameras not in CAMERA_MODES:
        raise SplatError(f"cameras {cfg.cameras!r}: expected one of {', '.join(CAMERA_MODES)}")
    if cfg.camera_model not in CAMERA_MODELS:
        raise SplatError(f"--camera-model {cfg.camera_model!r}: expected one of {', '.join(CAMERA_MODELS)}")
    if cfg.max_features < 64:
        raise SplatError(f"max_features {cfg.max_features}: must be at least 64")


def sift_max_size(cfg: ProcessConfig, *, posed: bool) -> int:
    """The longest side SIFT sees: --max-size, else the default for the kind of input."""
    if cfg.max_size is not None:
        return cfg.max_size
    return POSED_MAX_SIZE if posed else SFM_MAX_SIZE
