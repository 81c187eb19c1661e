"""Which photos share a camera (one focal length, one distortion) in structure from motion.

Photos taken by one camera at one zoom share intrinsics; forcing photos from several
cameras onto one camera gives every one of them the wrong focal length, and SfM
then finds no model. The rule (`--single-camera` and `--per-image-cameras` override it):

  * frames of one video share one camera;
  * photos whose EXIF names a camera share one when make, model, focal length and
    image size (as oriented) agree: one camera per group;
  * photos without such EXIF share one camera when all of them have the same size
    (one folder of one capture), else each gets its own. When under half of them
    register sharing it, SfM maps again with one camera each (`Grouping.split`):
    photos stripped of their EXIF may still come from several cameras.

The grouping goes into the process summary (the manifest's `steps.process.summary.cameras`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..errors import SplatError
from ..inputs.exif import ExifCamera, read_exif_camera
from ..inputs.images import StagedImage

CAMERA_MODES = ("auto", "single", "per-image")
# COLMAP camera models SfM may fit (the dataset is always undistorted to PINHOLE).
CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "OPENCV_FISHEYE",
                 "FULL_OPENCV", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE")


@dataclass(frozen=True)
class CameraGroup:
    names: list[str]  # images sharing the camera
    width: int
    height: int
    source: str  # "exif", "size" (same-size photos without EXIF), "video", "single", "image"
    exif: ExifCamera | None = None

    def summary(self) -> dict:
        d: dict = {"images": len(self.names), "width": self.width, "height": self.height, "source": self.source}
        if self.exif is not None and not self.exif.empty:
            d.update(make=self.exif.make, model=self.exif.model, focal_mm=self.exif.focal_mm,
                     focal_35mm=self.exif.focal_35mm)
        d["names"] = list(self.names)
        return d


@dataclass
class Grouping:
    groups: list[CameraGroup]  # largest first
    rule: str  # how they were made: "video", "exif", "single", "per-image"
    reason: str  # one sentence for the notes and the summary
    problems: list[str]  # EXIF fields dropped: "name: why"

    def split(self) -> Grouping | None:
        """The same with the photos that share a camera for want of EXIF apart (one camera
        each), for SfM to compare with (sfm/reconstruct.py); None when there are none."""
        if not any(g.source == "size" and len(g.names) > 1 for g in self.groups):
            return None
        groups = [h for g in self.groups for h in ([CameraGroup([n], g.width, g.height, "image") for n in g.names]
                                                    if g.source == "size" else [g])]
        return Grouping(groups, self.rule, f"{len(groups)} camera(s): the photos without EXIF camera data one each, "
                        "which fit them better than one shared camera (more registered, or focal lengths "
                        "that differ)", self.problems)


def group_cameras(staged: list[StagedImage], sources: dict[str, Path] | None, mode: str, *,
                  video: bool) -> Grouping:
    """Cameras for `staged` images. `sources`: image name -> its file (EXIF is read
    from it); None for video frames."""
    if mode not in CAMERA_MODES:
        raise SplatError(f"camera mode {mode!r}: expected one of {', '.join(CAMERA_MODES)}")
    sizes = {(s.width, s.height) for s in staged}
    if mode == "per-image":
        return Grouping([CameraGroup([s.name], s.width, s.height, "image") for s in staged], "per-image",
                        "one camera per image (--per-image-cameras)", [])
    if mode == "single" or video:
        if len(sizes) > 1:
            shown = ", ".join(f"{w}x{h}" for w, h in sorted(sizes)[:4])
            raise SplatError(f"--single-camera: the images come in {len(sizes)} sizes ({shown}); one camera "
                             "needs one size (leave it out, or resize the photos)")
        (w, h), = sizes
        why = "one camera for every frame of the video" if video else "one camera for every image (--single-camera)"
        return Grouping([CameraGroup([s.name for s in staged], w, h, "video" if video else "single")],
                        "video" if video else "single", why, [])
    exif = {s.name: read_exif_camera(sources[s.name]) if sources else ExifCamera() for s in staged}
    problems = [f"{n}: {p}" for n, e in exif.items() for p in e.problems]
    keyed: dict[tuple, list[StagedImage]] = {}
    bare: list[StagedImage] = []
    for s in staged:
        e = exif[s.name]
        if e.empty:
            bare.append(s)
        else:
            keyed.setdefault((e.make, e.model, e.focal_mm, e.focal_35mm, s.width, s.height), []).append(s)
    groups = [CameraGroup([s.name for s in members], members[0].width, members[0].height, "exif",
                          exif[members[0].name]) for members in keyed.values()]
    bare_sizes = {(s.width, s.height) for s in bare}
    if len(bare_sizes) == 1:
        groups.append(CameraGroup([s.name for s in bare], bare[0].width, bare[0].height, "size"))
    else:
        groups += [CameraGroup([s.name], s.width, s.height, "image") for s in bare]
    groups.sort(key=lambda g: (-len(g.names), g.names[0]))
    parts = []
    if keyed:
        parts.append(f"{len(keyed)} by their EXIF (make, model, focal length, size)")
    if len(bare_sizes) == 1:
        parts.append(f"1 for the {len(bare)} image(s) without EXIF camera data, all {bare[0].width}x{bare[0].height}")
    elif bare:
        parts.append(f"{len(bare)} image(s) without EXIF camera data in {len(bare_sizes)} sizes; "
                     "using one camera per image")
    return Grouping(groups, "exif", f"{len(groups)} camera(s): " + "; ".join(parts), problems)
