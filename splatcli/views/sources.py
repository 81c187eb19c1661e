"""Where render and eval look from: the project's dataset cameras per split
(`dataset_views`), or the cameras of a `transforms.json` (`transforms_views`, through
the one reader inputs/transforms.py); `resize_views` applies --width/--height/--downscale.

Every camera is returned in the project's convention: OpenCV axes (x right,
y down, z forward), `viewmat` world-to-camera, pixel centres at +0.5.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..errors import SplatError
from ..inputs.images import ImageError, read_image
from ..inputs.transforms import read_transforms
from ..project import Project
from ..sfm.colmap import read_project_scene

SPLITS = ("test", "train", "all")


@dataclass(frozen=True)
class View:
    """One camera to render. `image` is the ground-truth photo when the camera
    comes from the dataset (eval compares against it); `out_name` names the PNG."""

    camera: Camera
    out_name: str  # file name of the rendered PNG, e.g. "frame_0001.png"
    image: Path | None = None


def out_name_for(name: str) -> str:
    """A source image name -> the rendered PNG's name (sub-folders flattened)."""
    p = Path(name.replace("\\", "/"))
    stem = "_".join([*p.parent.parts, p.stem]) if p.parent.parts else p.stem
    return f"{stem}.png"


# ---------------------------------------------------------------------------
# dataset splits
# ---------------------------------------------------------------------------


def dataset_views(project: Project, split: str) -> list[View]:
    """The cameras of `split` (test | train | all) with their ground-truth images."""
    if split not in SPLITS:
        raise SplatError(f"--split {split!r} is not known; allowed values: {', '.join(SPLITS)}")
    cams = read_project_scene(project).cameras  # sorted by image name
    if split != "all":
        wanted = set(project.splits([c.name for c in cams])[split])
        cams = [c for c in cams if c.name in wanted]
    if not cams:
        other = "train" if split == "test" else "all"
        raise SplatError(f"{project.root}: the {split} split has no registered cameras; try --split {other}")
    return [View(camera=c, out_name=out_name_for(c.name), image=project.images_dir / c.name) for c in cams]


# ---------------------------------------------------------------------------
# transforms.json
# ---------------------------------------------------------------------------


def _image_size(path: Path | None) -> tuple[int, int] | None:
    """(width, height) of an image file as the one image loader reads it (oriented),
    or None when it cannot be read."""
    if path is None or not path.is_file():
        return None
    try:
        img, _, _ = read_image(path, orient=True)
    except ImageError:
        return None
    return int(img.shape[1]), int(img.shape[0])


def transforms_views(path: str | Path, *, notes: list[str] | None = None,
                     default_size: tuple[int, int] | None = None) -> list[View]:
    """The cameras of a nerfstudio / instant-ngp / Blender transforms file, in the
    project's convention. The size of a frame is its `w`, `h`, else its image
    file's, else `default_size` (width, height). Distortion is ignored (with a
    note): renders are pinhole."""
    path = Path(path)
    scene = read_transforms(path, images=False)
    views: list[View] = []
    size_cache: tuple[int, int] | None = None
    distorted = False
    for i, f in enumerate(scene.frames):
        intr = f.intrinsics
        if intr.w is not None and intr.h is not None:
            w, h = int(round(intr.w)), int(round(intr.h))
        else:
            size_cache = size_cache or _image_size(f.source) or default_size
            if size_cache is None:
                raise SplatError(f"{path}: frame {i}: no w/h and its image cannot be read to find the size; "
                                 "pass --width and --height")
            w, h = size_cache
        _, params = intr.resolve(w, h, f"{path}: frame {i}")
        fx, fy, cx, cy = params[:4]
        distorted |= intr.distorted
        cam = Camera(name=f.name, width=w, height=h, K=np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]),
                     viewmat=f.viewmat)
        views.append(View(camera=cam, out_name=f"{Path(f.name).stem}.png"))
    if distorted and notes is not None:
        notes.append(f"{path.name}: distortion coefficients are ignored; frames are rendered as pinhole cameras")
    names = [v.out_name for v in views]
    if len(set(names)) != len(names):  # two frames of one image name: number them instead
        views = [replace(v, out_name=f"{i:05d}_{v.out_name}") for i, v in enumerate(views)]
    return views


def resize_views(views: list[View], *, width: int | None = None, height: int | None = None,
                 downscale: float = 1.0) -> list[View]:
    """Apply --downscale, then --width/--height (one of them alone keeps the aspect);
    `views.output.check_config` has checked their ranges."""
    out = []
    for v in views:
        c = v.camera.scaled(1.0 / downscale) if downscale != 1.0 else v.camera
        if width is not None or height is not None:
            w = width if width is not None else max(1, round(c.width * height / c.height))
            h = height if height is not None else max(1, round(c.height * width / c.width))
            c = c.resized(int(w), int(h))
        out.append(replace(v, camera=c))
    return out


ANTIALIAS = ("auto", "on", "off")  # render / eval --antialias


def zoom_factor(project: Project, drawn: Sequence[View], views: Sequence[View]) -> float | None:
    """How much larger the drawn views sample the scene than `views` (the project's
    cameras) did at the resolution trained: the ratio of their median focal lengths in
    pixels (1 at the trained resolution; None when the manifest does not say)."""
    try:
        res = project.trained_resolution()
    except SplatError:
        return None
    fx = lambda cams: float(np.median([c.K[0, 0] for c in cams]))  # noqa: E731
    return fx(v.camera for v in drawn) / fx(v.camera.at_resolution(*res) for v in views)


def choose_antialias(mode: str, trained_with: bool | None, zoom: float | None) -> tuple[bool, str | None]:
    """Whether to draw with the 2D filter (rasterize(antialiased=True)), and a line
    saying why when it is on. `zoom`: drawn over trained resolution (zoom_factor),
    None when unknown. auto: on for a model trained with it (`train --mip-filter`),
    or when drawing smaller than trained, where the 0.3-pixel dilation alone would
    thicken fine detail into aliasing. Drawn larger it stays off: the filter is a
    box filter for one screen pixel, and a plain model zoomed in scores lower with it
    (docs/guide.md, "Rendering at other resolutions"); what zooming in needs is the 3D filter."""
    if mode not in ANTIALIAS:
        raise SplatError(f"--antialias {mode!r} is not known; allowed values: {', '.join(ANTIALIAS)}")
    if mode != "auto":
        return mode == "on", "drawn with the 2D antialiasing filter (--antialias on)" if mode == "on" else None
    if trained_with:
        return True, "drawn with the 2D antialiasing filter, as the model was trained (--mip-filter)"
    if zoom is not None and zoom < 0.99:
        return True, (f"drawn with the 2D antialiasing filter: at {zoom:.2f}x the resolution trained "
                      "(--antialias off draws without it)")
    return False, None
