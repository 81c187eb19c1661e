"""The one image loader, and the checks and staging of input images (OpenCV).

`read_image` decodes any image we accept (truncation and size checked, EXIF
orientation, 16-bit, grey, alpha); `load_rgb` is what train, eval and render read
through: RGB uint8, alpha composited over the background, resized by one rule.
The header checks are hand-written because OpenCV decodes a truncated JPEG or PNG
without complaint (padding it with grey) and reads no EXIF orientation tag without
decoding twice (Pillow only reads EXIF camera facts, inputs/exif.py).

Staging writes the image the rest of the pipeline sees: oriented (EXIF) when
asked, 8-bit, 3 channels (RGBA composited over the background, the alpha kept
as a mask), at full resolution. An image that needs none of this is copied
byte for byte, so JPEGs are not re-compressed.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path

# Decoding allocates what the header declares: a few bytes can claim a gigapixel. The
# header check below refuses PNG and JPEG above the cap with a clear message; OpenCV's
# own limit (read at decode time) covers TIFF and BMP.
MAX_PIXELS = 1 << 28  # 268 MP: 0.8 GB as 8-bit RGB, far above any photo a capture holds
os.environ.setdefault("OPENCV_IO_MAX_IMAGE_PIXELS", str(MAX_PIXELS))

import cv2
import numpy as np

from ..errors import SplatError
from ..files.atomic import atomic_path

IMAGE_EXTS = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp")
JPEG_QUALITY = 95


class ImageError(Exception):
    """An image that cannot be used; the message says why (without the path)."""


@dataclass(frozen=True)
class StagedImage:
    name: str
    width: int  # pixels, as staged: the source file's (after orientation)
    height: int
    has_alpha: bool


def is_image_name(path: Path) -> bool:
    return path.suffix.lower() in IMAGE_EXTS


def list_folder(folder: Path) -> tuple[list[Path], list[Path]]:
    """(image files, other files) directly in `folder`, sorted; hidden files ignored."""
    images, others = [], []
    for p in sorted(folder.iterdir()):
        if p.name.startswith(".") or not p.is_file():
            continue
        (images if is_image_name(p) else others).append(p)
    return images, others


def check_complete(data: bytes, suffix: str) -> None:
    """Refuse truncated JPEG and PNG files, which decoders silently pad with grey."""
    s = suffix.lower()
    if s in (".jpg", ".jpeg"):
        if data[:2] != b"\xff\xd8":
            raise ImageError("not a JPEG file")
        # Entropy-coded data stuffs 0xFF bytes, so markers cannot occur by chance:
        # a complete file has an end-of-image marker after its last start-of-scan.
        sos = data.rfind(b"\xff\xda")
        if sos < 0 or data.find(b"\xff\xd9", sos) < 0:
            raise ImageError("truncated JPEG (no end-of-image marker)")
    elif s == ".png":
        if data[:8] != b"\x89PNG\r\n\x1a\n":
            raise ImageError("not a PNG file")
        pos = 8
        while True:
            if pos + 8 > len(data):
                raise ImageError("truncated PNG (no IEND chunk)")
            length = int.from_bytes(data[pos : pos + 4], "big")
            kind = data[pos + 4 : pos + 8]
            pos += 12 + length
            if pos > len(data):
                raise ImageError("truncated PNG (a chunk runs past the end)")
            if kind == b"IEND":
                return


def header_size(data: bytes, suffix: str) -> tuple[int, int] | None:
    """(width, height) a PNG or JPEG header declares, or None (other formats, or none found)."""
    s = suffix.lower()
    if s == ".png" and len(data) >= 24 and data[12:16] == b"IHDR":
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    if s in (".jpg", ".jpeg"):
        pos = 2
        while pos + 9 <= len(data) and data[pos] == 0xFF:
            marker, size = data[pos + 1], int.from_bytes(data[pos + 2 : pos + 4], "big")
            if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):  # start of frame
                return int.from_bytes(data[pos + 7 : pos + 9], "big"), int.from_bytes(data[pos + 5 : pos + 7], "big")
            if marker == 0xDA:
                return None
            pos += 2 + size
    return None


def check_size(data: bytes, suffix: str) -> None:
    """Refuse images whose header declares more than MAX_PIXELS, before decoding."""
    wh = header_size(data, suffix)
    if wh is not None and wh[0] * wh[1] > MAX_PIXELS:
        raise ImageError(f"too large ({wh[0]} x {wh[1]} px; at most {MAX_PIXELS / 1e6:.0f} megapixels)")


def read_image(path: Path, *, orient: bool) -> tuple[np.ndarray, np.ndarray | None, bool]:
    """(BGR uint8 [H, W, 3], alpha uint8 [H, W] or None, changed).

    `changed` is True when the pixels differ from what the file stores as is
    (EXIF rotation applied, bit depth or channels converted, alpha present),
    so the file cannot simply be copied."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ImageError(f"cannot read ({exc.strerror or exc})") from None
    check_complete(data, path.suffix)
    check_size(data, path.suffix)
    buf = np.frombuffer(data, np.uint8)
    raw = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)  # no EXIF rotation, keeps alpha and 16 bits
    if raw is None or raw.size == 0:
        raise ImageError("cannot decode (corrupt or unsupported image)")
    changed = False
    if raw.dtype == np.uint16:
        raw = (raw.astype(np.float32) / 257.0 + 0.5).astype(np.uint8)
        changed = True
    elif raw.dtype != np.uint8:
        raise ImageError(f"unsupported pixel type {raw.dtype}")
    alpha = None
    if raw.ndim == 2:
        img = cv2.cvtColor(raw, cv2.COLOR_GRAY2BGR)
        changed = True
    elif raw.shape[2] == 4:
        img, alpha = np.ascontiguousarray(raw[..., :3]), np.ascontiguousarray(raw[..., 3])
        changed = True
        if alpha.min() == 255:  # an opaque alpha channel carries nothing
            alpha = None
    elif raw.shape[2] == 3:
        img = raw
    else:
        img = cv2.cvtColor(raw[..., :1], cv2.COLOR_GRAY2BGR)
        changed = True
    if orient and path.suffix.lower() in (".jpg", ".jpeg") and exif_orientation(data) not in (None, 1):
        oriented = cv2.imdecode(buf, cv2.IMREAD_COLOR)  # OpenCV applies the EXIF rotation here
        if oriented is not None:
            img, changed = oriented, True
    return img, alpha, changed


def exif_orientation(data: bytes) -> int | None:
    """The EXIF orientation tag (1-8) of a JPEG, or None. Reads only the APP1
    segment, so phone photos (always EXIF, nearly always 1) decode once."""
    pos = 2
    while pos + 4 <= len(data) and data[pos] == 0xFF:
        marker, size = data[pos + 1], int.from_bytes(data[pos + 2 : pos + 4], "big")
        if marker == 0xDA:  # start of scan: no more metadata
            return None
        seg = data[pos + 4 : pos + 2 + size]
        if marker == 0xE1 and seg[:6] == b"Exif\x00\x00":
            t = seg[6:]
            if len(t) < 8 or t[:2] not in (b"II", b"MM"):
                return None
            order = "little" if t[:2] == b"II" else "big"
            ifd = int.from_bytes(t[4:8], order)
            if ifd + 2 > len(t):
                return None
            for k in range(int.from_bytes(t[ifd : ifd + 2], order)):
                e = ifd + 2 + 12 * k
                if e + 12 > len(t):
                    return None
                if int.from_bytes(t[e : e + 2], order) == 0x0112:
                    v = int.from_bytes(t[e + 8 : e + 10], order)
                    return v if 1 <= v <= 8 else None
            return None
        pos += 2 + size
    return None


def fit_size(width: int, height: int, max_size: int | None) -> tuple[int, int]:
    """The size after capping the longest side at `max_size` (never enlarges)."""
    if not max_size or max(width, height) <= max_size:
        return width, height
    s = max_size / max(width, height)
    return max(1, int(round(width * s))), max(1, int(round(height * s)))


def composite(img: np.ndarray, alpha: np.ndarray, background: tuple[float, float, float]) -> np.ndarray:
    """img [H, W, 3] BGR uint8 over an RGB background in [0, 1] -> BGR uint8."""
    a = alpha.astype(np.float32)[..., None] / 255.0
    bg = np.array(background[::-1], np.float32) * 255.0  # RGB -> BGR
    out = img.astype(np.float32) * a + bg * (1.0 - a)
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)


def paint_masked(rgb: np.ndarray, keep: np.ndarray,
                 background: tuple[float, float, float]) -> np.ndarray:  # [H, W, 3] uint8, [H, W] bool -> uint8
    """`rgb` (RGB uint8) with its masked pixels (keep False) in the background colour (RGB
    in [0, 1]), rounded as `composite` rounds a transparent pixel: --mask-mode background
    with mask files, for training and the scores alike."""
    fill = np.clip(np.asarray(background, np.float32) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return np.where(keep[..., None], rgb, fill)


def write_image(path: Path, img: np.ndarray, quality: int = JPEG_QUALITY) -> None:
    """Atomically encode `img` in the format of `path`'s suffix (JPEG at `quality`)."""
    suffix = path.suffix.lower()
    params = [cv2.IMWRITE_JPEG_QUALITY, quality] if suffix in (".jpg", ".jpeg") else []
    ok, enc = cv2.imencode(suffix, img, params)
    if not ok:
        raise ImageError(f"cannot encode as {suffix}")
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        tmp.write_bytes(enc.tobytes())


def load_rgb(path: Path, size: tuple[int, int] | None = None,
             background: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:  # -> [H, W, 3] uint8
    """An image file as RGB uint8: oriented (EXIF), alpha composited over `background`
    (RGB in [0, 1]), resized to `size` = (width, height) when given (area filter
    when shrinking, linear when enlarging). Unreadable files are a SplatError."""
    try:
        img, alpha, _ = read_image(Path(path), orient=True)
    except ImageError as exc:
        raise SplatError(f"{path}: {exc}") from None
    if alpha is not None:
        img = composite(img, alpha, background)
    if size is not None and (img.shape[1], img.shape[0]) != tuple(size):
        shrink = size[0] < img.shape[1]
        img = cv2.resize(img, tuple(size), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    return np.ascontiguousarray(img[..., ::-1])


MASK_KEEP = 128  # a mask pixel at or above this keeps its image pixel; below, it is masked out


def read_mask(path: Path) -> np.ndarray:  # -> [H, W] uint8
    """A mask file as grey uint8 (colour masks are converted to grey; an alpha channel
    is ignored), not oriented: masks are drawn on the pixels as stored. Raises ImageError."""
    img, _, _ = read_image(Path(path), orient=False)
    return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)


def load_mask(path: Path, size: tuple[int, int] | None = None) -> np.ndarray:  # -> [H, W] bool
    """A project mask (PROJECT/masks, 255 = keep) resized like `load_rgb` resizes its
    image (area filter), then kept where >= MASK_KEEP. Unreadable files are a SplatError."""
    try:
        m = read_mask(Path(path))
    except ImageError as exc:
        raise SplatError(f"{path}: {exc}") from None
    if size is not None and (m.shape[1], m.shape[0]) != tuple(size):
        shrink = size[0] < m.shape[1]
        m = cv2.resize(m, tuple(size), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    return m >= MASK_KEEP


def stage_image(src: Path, name: str, dst: Path, mask_dst: Path, *,
                background: tuple[float, float, float], orient: bool,
                expect_size: tuple[int, int] | None = None) -> StagedImage:
    """Write the usable version of `src` to `dst` (same format, full resolution: the
    dataset keeps it, train caps what it loads), its alpha to `mask_dst` (PNG) if it
    has one. Raises ImageError."""
    img, alpha, changed = read_image(src, orient=orient)
    h, w = img.shape[:2]
    if expect_size is not None and (w, h) != tuple(expect_size):
        raise ImageError(f"is {w}x{h} but its camera says {expect_size[0]}x{expect_size[1]}")
    if alpha is not None:
        img = composite(img, alpha, background)
    dst.parent.mkdir(parents=True, exist_ok=True)
    if changed:
        write_image(dst, img)
    else:
        shutil.copyfile(src, dst)
    if alpha is not None:
        write_image(mask_dst, alpha)
    return StagedImage(name, w, h, alpha is not None)


def sharpness(img: np.ndarray) -> float:
    """Variance of the Laplacian of the grey image at <= 512 px: higher is sharper."""
    grey = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    h, w = grey.shape
    s = 512 / max(h, w)
    if s < 1:
        grey = cv2.resize(grey, (max(1, int(w * s)), max(1, int(h * s))), interpolation=cv2.INTER_AREA)
    return float(cv2.Laplacian(grey, cv2.CV_64F).var())
