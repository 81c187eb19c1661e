"""What a photo's EXIF says about the camera that took it: make, model, focal length.

`process` groups photos into cameras by these (process/cameras.py). Read through
Pillow, which parses the header and metadata without decoding pixels. EXIF is
written by cameras, phones and editors, and it lies: fields of the wrong type,
focal lengths of 0 or of kilometres, names full of control characters. Whatever
is implausible is dropped and said in `ExifCamera.problems`; an unreadable EXIF
block is no EXIF. Nothing here raises.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

_EXIF_IFD = 0x8769
_MAKE, _MODEL = 0x010F, 0x0110
_FOCAL, _FOCAL_35 = 0x920A, 0xA405
MIN_FOCAL_MM, MAX_FOCAL_MM = 0.5, 5000.0  # shorter or longer than any lens a capture is shot with
MAX_NAME = 64  # characters kept of make and model


@dataclass(frozen=True)
class ExifCamera:
    make: str | None = None
    model: str | None = None
    focal_mm: float | None = None  # the lens's focal length, millimetres
    focal_35mm: float | None = None  # its 35 mm film equivalent, millimetres
    problems: tuple[str, ...] = field(default=(), compare=False)  # what was dropped, and why

    @property
    def empty(self) -> bool:
        """No camera facts at all (no EXIF, or none of these tags)."""
        return self.make is None and self.model is None and self.focal_mm is None and self.focal_35mm is None

    def describe(self) -> str:
        name = " ".join(v for v in (self.make, self.model) if v) or "unknown camera"
        if self.focal_mm is not None:
            return f"{name} at {self.focal_mm:g} mm"
        if self.focal_35mm is not None:
            return f"{name} at {self.focal_35mm:g} mm (35 mm equivalent)"
        return name


def _name(v: Any) -> str | None:
    if isinstance(v, bytes):
        v = v.decode("latin-1")
    if not isinstance(v, str):
        return None
    s = " ".join("".join(ch if ch.isprintable() else " " for ch in v).split())[:MAX_NAME]
    return s or None


def _focal(v: Any, what: str, problems: list[str]) -> float | None:
    if v is None:
        return None
    try:
        f = float(v)  # IFDRational, int or float
    except (TypeError, ValueError, ZeroDivisionError, OverflowError):
        problems.append(f"{what} {v!r} is not a number")
        return None
    if not (math.isfinite(f) and MIN_FOCAL_MM <= f <= MAX_FOCAL_MM):
        problems.append(f"{what} {f:g} mm is not a focal length")
        return None
    return round(f, 2)


def read_exif_camera(path: Path) -> ExifCamera:
    """The camera facts in `path`'s EXIF (empty when it has none or they cannot be read)."""
    try:
        from PIL import Image

        with Image.open(path) as im:
            exif = im.getexif()
            main = dict(exif.items())
            sub = dict(exif.get_ifd(_EXIF_IFD).items())
    except Exception:  # any damage in a metadata block Pillow cannot parse: no EXIF
        return ExifCamera()
    problems: list[str] = []
    return ExifCamera(make=_name(main.get(_MAKE)), model=_name(main.get(_MODEL)),
                      focal_mm=_focal(sub.get(_FOCAL), "focal length", problems),
                      focal_35mm=_focal(sub.get(_FOCAL_35), "35 mm focal length", problems),
                      problems=tuple(problems))
