"""Frames from a video (OpenCV), with the blurriest ones dropped before SfM."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..errors import SplatError
from ..inputs.images import sharpness, write_image

VIDEO_EXTS = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv", ".flv", ".3gp", ".mts")


@dataclass(frozen=True)
class VideoFrames:
    names: list[str]  # written frames, sorted (frame order)
    width: int  # pixels, as decoded (frames are kept at full resolution)
    height: int
    fps: float  # the video's frame rate (0 when unknown)
    total_frames: int  # frames in the video
    sampled: int  # frames taken before dropping blurry ones
    dropped: list[str]  # names of the frames dropped as blurry (deleted)
    unreadable: list[int] = field(default_factory=list)  # wanted frame indices that could not be decoded


def is_video_name(path: Path) -> bool:
    return path.suffix.lower() in VIDEO_EXTS


def _open(path: Path) -> cv2.VideoCapture:
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise SplatError(f"{path}: cannot read the video (not a video, or a codec OpenCV lacks)")
    return cap


def count_frames(path: Path) -> tuple[int, float]:
    """(frames, fps). Trusts the container's frame count when it has one (a
    wrong one only shifts which frames are taken); otherwise counts by grabbing
    every frame, which decodes the whole video once more."""
    cap = _open(path)
    fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
    n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
    if n <= 0:
        n = 0
        while cap.grab():
            n += 1
    cap.release()
    if n == 0:
        raise SplatError(f"{path}: cannot read the video (no decodable frames)")
    return n, fps if np.isfinite(fps) and fps > 0 else 0.0


def choose_frames(total: int, fps: float, *, every_fps: float | None, num_frames: int | None) -> list[int]:
    """Frame indices to extract: `every_fps` frames per second of video, or
    `num_frames` evenly spaced ones."""
    if every_fps:
        step = fps / every_fps if fps > 0 else 1.0
        step = max(step, 1.0)
        idx = np.arange(0, total, step)
    else:
        n = min(total, max(1, int(num_frames or 1)))
        idx = np.linspace(0, total - 1, n)
    return sorted({int(round(i)) for i in idx if round(i) < total})


def blurry_frames(scores: list[float], *, ratio: float = 0.6, window: int = 9) -> list[int]:
    """Indices of frames much blurrier than their neighbours: sharpness below
    `ratio` x the median of the `window` frames around them. A uniformly soft
    video keeps its frames; motion-blurred moments are dropped."""
    s = np.asarray(scores, np.float64)
    half = window // 2
    out = []
    for i in range(len(s)):
        lo, hi = max(0, i - half), min(len(s), i + half + 1)
        if s[i] < ratio * float(np.median(s[lo:hi])):
            out.append(i)
    return out


def extract_frames(path: Path, out_dir: Path, *, every_fps: float | None, num_frames: int | None,
                   blur_ratio: float = 0.6,
                   on_progress: Callable[[int, int], None] | None = None) -> VideoFrames:
    """Write the chosen frames as JPEGs `frame_NNNNNN.jpg` (source frame index)."""
    total, fps = count_frames(path)
    wanted = choose_frames(total, fps, every_fps=every_fps, num_frames=num_frames)
    want = set(wanted)
    cap = _open(path)
    out_dir.mkdir(parents=True, exist_ok=True)
    written: list[str] = []
    scores: list[float] = []
    size = (0, 0)
    idx = 0
    failed: list[int] = []
    while idx <= wanted[-1]:
        if not cap.grab():  # a truncated file ends early: the rest of the wanted frames are lost
            failed += [i for i in wanted if i >= idx]
            break
        if idx in want:
            ok, img = cap.retrieve()
            if not (ok and img is not None and img.size):
                failed.append(idx)
            else:
                name = f"frame_{idx:06d}.jpg"
                size = (img.shape[1], img.shape[0])
                write_image(out_dir / name, img)  # written now: a long video must not sit in memory
                written.append(name)
                scores.append(sharpness(img))
                if on_progress is not None:
                    on_progress(len(written), len(wanted))
        idx += 1
    cap.release()
    if not written:
        raise SplatError(f"{path}: cannot read the video (no frame could be decoded)")
    drop = set(blurry_frames(scores, ratio=blur_ratio)) if len(written) >= 3 else set()
    for i in drop:
        (out_dir / written[i]).unlink()
    names = [n for i, n in enumerate(written) if i not in drop]
    return VideoFrames(
        names=names, width=size[0], height=size[1], fps=fps, total_frames=total, sampled=len(written),
        dropped=[written[i] for i in sorted(drop)], unreadable=failed,
    )
