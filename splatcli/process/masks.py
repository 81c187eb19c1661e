"""Masks given as files: found beside the images or named by a transforms.json, checked
against their images, and staged in the project's convention.

Conventions read (as COLMAP and nerfstudio write them): a `masks/` folder beside the
images folder (or inside it), holding `<image name>.png` (COLMAP's `name.jpg.png`) or
`<image stem>.png`; nerfstudio's per-frame `mask_path`. Black (0) is masked out, white
(255) kept; `--invert-masks` flips them. Grey levels are cut at inputs/images.MASK_KEEP, so
the project's masks are 0 or 255. An image's alpha channel is the third source
(inputs/images.stage_image); when files are given too, the files are the masks.

Staged masks are PNG files at work/masks/<image name>.png (COLMAP's naming, so that
feature extraction reads them as they are).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import SplatError
from ..events import Stages
from ..inputs.images import MASK_KEEP, ImageError, StagedImage, read_mask, write_image

MASKS_DIR = "masks"


def staged_mask(work: Path, name: str) -> Path:
    """Where the stage folder keeps image `name`'s mask (COLMAP's naming, PNG)."""
    return work / MASKS_DIR / f"{name}.png"


def find_masks_dir(images_dir: Path) -> Path | None:
    """A `masks/` folder beside the images folder, or inside it; None when there is none."""
    for d in (images_dir.parent / MASKS_DIR, images_dir / MASKS_DIR):
        if d.is_dir() and d.resolve() != images_dir.resolve():
            return d
    return None


def mask_file(masks_dir: Path, source_name: str) -> Path | None:
    """The mask of image file `source_name` (a path relative to the images folder):
    `name.jpg.png`, else `name.png`."""
    for cand in (f"{source_name}.png", str(Path(source_name).with_suffix(".png"))):
        if (masks_dir / cand).is_file():
            return masks_dir / cand
    return None


def fill_masks(work: Path, sizes: dict[str, tuple[int, int]]) -> None:
    """Give every image (name -> (width, height)) without a staged mask an all-keep one."""
    for name, (w, h) in sizes.items():
        if not staged_mask(work, name).exists():
            write_image(staged_mask(work, name), np.full((h, w), 255, np.uint8))


def stage_all(found: dict[str, Path | None], staged: list[StagedImage], work: Path, run: Stages, *,
              invert: bool, where: Path | None) -> str | None:
    """Stage the masks SfM and training use: the files in `found` (image name -> mask
    file or None), else the images' alpha; every image then has one. Returns the
    source: "files", "alpha" or None."""
    source = None
    if found and stage_masks(found, staged, work, run, invert=invert, where=where):
        source = "files"
    elif any(s.has_alpha for s in staged):
        source = "alpha"
    if source is not None:
        fill_masks(work, {s.name: (s.width, s.height) for s in staged})
    return source


def stage_masks(found: dict[str, Path | None], staged: list[StagedImage], work: Path, run: Stages, *,
                invert: bool, where: Path | None) -> bool:
    """Write each staged image's mask (`found`: image name -> its mask file, None
    when it has none) as work/masks/<name>.png, 255 = keep. An image without a mask
    gets an all-keep one (with one warning naming `where`). A mask whose size differs from its
    image's is a SplatError naming the mask. Returns whether any mask was given."""
    if not any(found.get(s.name) for s in staged):
        return False
    absent = []
    with run.stage("read masks", len(staged)) as st:
        for i, s in enumerate(staged):
            src = found.get(s.name)
            if src is None:
                absent.append(s.name)
                m = np.full((s.height, s.width), 255, np.uint8)
            else:
                try:
                    grey = read_mask(src)
                except ImageError as exc:
                    raise SplatError(f"{src}: mask of {s.name}: {exc}") from None
                if (grey.shape[1], grey.shape[0]) != (s.width, s.height):
                    raise SplatError(f"{src}: mask is {grey.shape[1]}x{grey.shape[0]} but its image {s.name} is "
                                     f"{s.width}x{s.height}")
                keep = grey >= MASK_KEEP
                m = np.where(keep != invert, 255, 0).astype(np.uint8)
            write_image(staged_mask(work, s.name), m)
            st.progress(i + 1)
    if absent:
        run.note(f"{len(absent)} image(s) have no mask{f' in {where}' if where else ''} and are kept whole "
                 f"(first: {absent[0]})", "warning")
    return True
