"""PlayCanvas SOG (`.sog`, version 2): lossless WebP images and a `meta.json`, zipped.

Written from PlayCanvas's published SOG format. Gaussian i is pixel i (row-major) of
each image, W = ceil(sqrt(N) / 4) * 4 wide and ceil(N / W / 4) * 4 high, in Morton
order; the frame is the .ply's (OpenCV), so nothing is flipped.

    means_l/u.webp   RGB = low / high byte of x, y, z as 16 bits between meta means.mins
                     and maxs of sign(x) ln(|x| + 1)
    quats.webp       RGB = the three smaller of (w, x, y, z), each (c sqrt 2 + 1) / 2 * 255;
                     A = 252 + the index of the largest (dropped, made positive)
    scales.webp      RGB = indices into meta scales.codebook (256 log scales)
    sh0.webp         RGB = indices into meta sh0.codebook (256 DC values); A = sigmoid(opacity) * 255
    shN_labels.webp  RG = 16-bit index of the Gaussian's SH palette entry
    shN_centroids.webp  palette entry i is row i // 64, columns (i % 64) * C + j for its C
                     coefficients; RGB = indices into meta shN.codebook (256 values)

Every codebook is a 1-D k-means of the values it stands for; the SH palette is a k-means
of the Gaussians' SH vectors (`SogOptions.palette` entries). The images are lossless
(Pillow's WebP with `exact`, so no pixel is changed).
"""

from __future__ import annotations

import io
import json
import math
import os
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .. import __version__
from ..files.atomic import atomic_write_bytes
from ..gaussians import Gaussians, morton_order
from .codec import MAX_RATIO, Arrays, logit, pack_smallest_three, refuse, sigmoid, unpack_smallest_three

MAX_META = 64 << 20


@dataclass(frozen=True)
class SogOptions:
    palette: int | None = None  # SH palette entries; None: palette_size(N), a power of two near N/16, 256 to 4096
    iterations: int = 10  # k-means iterations (codebooks and palette)
    seed: int = 0


def palette_size(n: int) -> int:
    """The default SH palette: a power of two near N/16, from 256 to 4096. More entries lose
    less PSNR for a larger file, and k-means of N rows against K entries costs N K 45
    multiply-adds, which the cap bounds (docs/benchmarks.md, "formats")."""
    return int(min(4096, max(256, 2 ** math.floor(math.log2(max(n, 1) / 16))))) if n else 0


def kmeans_1d(values: np.ndarray, k: int = 256, iterations: int = 10, alpha: float = 0.5,
              bins: int = 4096) -> tuple[np.ndarray, np.ndarray]:
    """A 1-D codebook [k] (sorted) and each value's index [M] uint8 (k <= 256): Lloyd's
    k-means on a fine histogram whose bins weigh count^alpha, so sparse tails (the
    largest Gaussians, saturated colours) keep entries of their own."""
    v = values.reshape(-1).astype(np.float32)
    if v.size == 0:
        return np.zeros(k, np.float32), np.zeros(0, np.uint8)
    lo, hi = float(v.min()), float(v.max())
    if hi - lo < 1e-20:
        return np.full(k, lo, np.float32), np.zeros(v.size, np.uint8)
    b = np.minimum(((v - lo) / (hi - lo) * bins).astype(np.int64), bins - 1)
    cnt = np.bincount(b, minlength=bins)
    x = (np.bincount(b, weights=v, minlength=bins)[cnt > 0] / cnt[cnt > 0])
    wgt = cnt[cnt > 0].astype(np.float64) ** alpha
    cw = np.cumsum(wgt)
    c = np.unique(x[np.minimum(np.searchsorted(cw, (np.arange(k) + 0.5) / k * cw[-1]), len(x) - 1)])
    for _ in range(iterations):
        idx = np.searchsorted((c[1:] + c[:-1]) / 2, x)
        ws = np.bincount(idx, weights=wgt, minlength=len(c))
        c = np.unique(np.where(ws > 0, np.bincount(idx, weights=wgt * x, minlength=len(c)) / np.maximum(ws, 1e-300), c))
    c = np.concatenate([c, np.full(k - len(c), c[-1])]).astype(np.float32)  # pad to k (unused entries)
    idx = np.searchsorted((c[1:] + c[:-1]) / 2, v)
    return c, np.minimum(idx, k - 1).astype(np.uint8)


def kmeans(x: torch.Tensor, k: int, iterations: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Centroids [k, D] and labels [N] of the rows of x [N, D] (float32): Lloyd's iterations
    on a sample of at most 16 rows per centroid, then every row assigned once."""
    n = x.shape[0]
    if n <= k:
        return x.clone(), torch.arange(n)
    gen = torch.Generator().manual_seed(seed)
    sample = x[torch.randperm(n, generator=gen)[: min(n, 16 * k)]]
    c = sample[:k].clone()
    for _ in range(iterations):
        lab = _nearest(sample, c)
        sums = torch.zeros_like(c).index_add_(0, lab, sample)
        counts = torch.bincount(lab, minlength=k).to(c.dtype)
        c = torch.where(counts[:, None] > 0, sums / counts.clamp_min(1)[:, None], c)
    return c, _nearest(x, c)


def _nearest(x: torch.Tensor, c: torch.Tensor, chunk: int = 16384) -> torch.Tensor:
    cn = (c * c).sum(1)
    out = torch.empty(x.shape[0], dtype=torch.long)
    for i in range(0, x.shape[0], chunk):  # |x - c|^2 - |x|^2 = |c|^2 - 2 x.c, in one fused kernel
        out[i:i + chunk] = torch.addmm(cn[None], x[i:i + chunk], c.T, alpha=-2).argmin(1)
    return out


def _webp(rgba: np.ndarray) -> bytes:  # [H, W, 4] uint8
    from PIL import Image

    b = io.BytesIO()
    Image.fromarray(rgba, "RGBA").save(b, "WEBP", lossless=True, quality=100, method=2, exact=True)  # method 2: smaller than 0, as fast
    return b.getvalue()


def _texture(n: int, w: int, h: int, channels: np.ndarray, alpha: np.ndarray | int = 255) -> bytes:  # [n, <= 3]
    img = np.zeros((w * h, 4), np.uint8)
    img[:n, :channels.shape[1]] = channels
    img[:n, 3] = alpha
    return _webp(img.reshape(h, w, 4))


def encode_sog(g: Gaussians, options: SogOptions = SogOptions()) -> tuple[bytes, int]:
    """The .sog (zip) bytes of the finite rows of `g`, and the number of rows dropped."""
    a, dropped = Arrays.of(g)
    n = len(a)
    order = morton_order(torch.from_numpy(a.means)).numpy() if n else np.zeros(0, np.int64)
    w = max(4, math.ceil(math.sqrt(n) / 4) * 4)
    h = max(4, math.ceil(n / w / 4) * 4)
    files: dict[str, bytes] = {}
    meta: dict = {"version": 2, "asset": {"generator": f"splatcli {__version__}"}, "count": n}

    lt = np.sign(a.means[order]) * np.log1p(np.abs(a.means[order]))
    lo, hi = (lt.min(0), lt.max(0)) if n else (np.zeros(3), np.zeros(3))
    u = np.round((lt - lo) / np.where(hi > lo, hi - lo, 1.0) * 65535).astype(np.uint32)
    files["means_l.webp"] = _texture(n, w, h, u & 255)
    files["means_u.webp"] = _texture(n, w, h, u >> 8)
    meta["means"] = {"mins": lo.tolist(), "maxs": hi.tolist(), "files": ["means_l.webp", "means_u.webp"]}

    big, rest = pack_smallest_three(a.quats[order])
    q = np.clip(np.round((rest * np.sqrt(2.0) + 1.0) / 2.0 * 255.0), 0, 255).astype(np.uint8)
    files["quats.webp"] = _texture(n, w, h, q, (252 + big).astype(np.uint8))
    meta["quats"] = {"files": ["quats.webp"]}

    book, idx = kmeans_1d(a.log_scales[order], 256, options.iterations)
    files["scales.webp"] = _texture(n, w, h, idx.reshape(n, 3))
    meta["scales"] = {"codebook": book.tolist(), "files": ["scales.webp"]}

    book, idx = kmeans_1d(a.sh[order, 0], 256, options.iterations)
    opacity = np.clip(np.round(sigmoid(a.opacity_logits[order]) * 255.0), 0, 255).astype(np.uint8)
    files["sh0.webp"] = _texture(n, w, h, idx.reshape(n, 3), opacity)
    meta["sh0"] = {"codebook": book.tolist(), "files": ["sh0.webp"]}

    coeffs = a.sh.shape[1] - 1
    if coeffs and n:
        vec = torch.from_numpy(np.ascontiguousarray(a.sh[order, 1:].transpose(0, 2, 1).reshape(n, -1), np.float32))
        k = min(options.palette or palette_size(n), 65536)
        cents, labels = kmeans(vec, k, options.iterations, options.seed)
        k = cents.shape[0]
        book, cidx = kmeans_1d(cents.numpy(), 256, options.iterations)
        cidx = cidx.reshape(k, 3, coeffs)  # channel-major, as the vector
        rows = math.ceil(k / 64)
        cimg = np.zeros((rows * 64, coeffs, 4), np.uint8)
        cimg[:k, :, :3] = cidx.transpose(0, 2, 1)
        cimg[:, :, 3] = 255
        files["shN_centroids.webp"] = _webp(cimg.reshape(rows, 64 * coeffs, 4))
        lab = labels.numpy().astype(np.uint32)
        files["shN_labels.webp"] = _texture(n, w, h, np.stack([lab & 255, lab >> 8], 1))
        meta["shN"] = {"count": int(k), "bands": int(round(math.sqrt(coeffs + 1))) - 1, "codebook": book.tolist(),
                       "files": ["shN_centroids.webp", "shN_labels.webp"]}

    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as z:  # WebP is compressed already
        for name, data in {"meta.json": json.dumps(meta).encode(), **files}.items():
            # A fixed timestamp (zip's earliest), not the clock's: the same model gives the same bytes.
            info = zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0))
            info.external_attr = 0o644 << 16  # rw-r--r-- when unzipped
            z.writestr(info, data)
    return out.getvalue(), dropped


def write_sog(path: str | os.PathLike, g: Gaussians, options: SogOptions = SogOptions()) -> tuple[int, int, int]:
    """Write `g` as .sog (atomically): (rows written, rows dropped, bytes)."""
    data, dropped = encode_sog(g, options)
    atomic_write_bytes(path, data)
    return len(g) - dropped, dropped, len(data)


def _open_bundle(path: Path) -> tuple[Callable[[str], bytes], bytes, int]:
    """(a member's bytes by name, meta.json's bytes, the bytes stored) of a .sog zip or a meta.json folder."""
    try:
        if path.name.lower().endswith(".json"):
            stored = sum(f.stat().st_size for f in path.parent.iterdir() if f.is_file())
            return (lambda name: (path.parent / Path(name).name).read_bytes(),  # no paths out of the folder
                    path.read_bytes()[:MAX_META + 1], stored)
        stored = path.stat().st_size
        z = zipfile.ZipFile(path)
        members = {i.filename: i for i in z.infolist()}
        if any(i.file_size > MAX_RATIO * max(i.compress_size, 1) + 4096 for i in members.values()):
            raise refuse(path, "a member expands far beyond its stored size")

        def get(name: str) -> bytes:
            if name not in members:
                raise refuse(path, f"names {name!r}, which the archive does not hold")
            return z.read(name)

        meta_raw = get("meta.json") if "meta.json" in members else b""
        if not meta_raw:
            raise refuse(path, "no meta.json in the archive")
        return get, meta_raw, stored
    except (OSError, zipfile.BadZipFile, zipfile.LargeZipFile, ValueError) as exc:
        raise refuse(path, f"not a readable SOG file ({type(exc).__name__}: {' '.join(str(exc).split())[:80]})") from None


def _read_meta(path: Path, meta_raw: bytes, stored: int) -> dict[str, Any]:
    """meta.json, checked: version 2, the shapes of its bounds and codebooks, a count the file can hold."""
    try:
        meta = json.loads(meta_raw)
        n = int(meta["count"])
        if meta.get("version") != 2:
            raise refuse(path, f"SOG version {meta.get('version', 1)} is not supported (2 is)")
        shapes = [np.asarray(meta["means"][k], np.float64).shape for k in ("mins", "maxs")]
        shapes += [np.asarray(meta[k]["codebook"], np.float64).shape for k in ("scales", "sh0")]
        if shapes != [(3,), (3,), (256,), (256,)] or n < 0:
            raise ValueError("means, codebooks or count have the wrong shape")
    except (ValueError, KeyError, TypeError) as exc:
        raise refuse(path, f"meta.json is not SOG metadata ({' '.join(str(exc).split())[:80]})") from None
    if n * 20 > MAX_RATIO * stored:
        raise refuse(path, f"claims {n:,} Gaussians, more than its {stored:,} bytes can hold")
    return meta


def _image_reader(path: Path, get: Callable[[str], bytes]) -> Callable[..., np.ndarray]:
    """A reader of the bundle's WebP images as [pixels, 4] RGBA, refusing one that does not fit its entries."""
    from PIL import Image

    def image(name: str, min_pixels: int, width: int | None = None) -> np.ndarray:
        try:
            im = Image.open(io.BytesIO(get(name)))
            w, h = im.size
            if im.format != "WEBP" or w * h < min_pixels or w * h > 4 * max(min_pixels, 1024) or (width and w != width):
                raise ValueError(f"{name}: a {w}x{h} {im.format} image does not fit {min_pixels:,} entries")
            return np.asarray(im.convert("RGBA")).reshape(-1, 4)
        except OSError as exc:
            raise refuse(path, f"{name}: not a readable WebP image ({exc})") from None
        except ValueError as exc:
            raise refuse(path, str(exc)) from None

    return image


def _read_shn(path: Path, shn: dict[str, Any], files: list[str | None], n: int,
              image: Callable[..., np.ndarray]) -> np.ndarray:  # -> [n, C, 3] float32, the higher SH bands
    try:
        bands, k, book = int(shn["bands"]), int(shn["count"]), np.asarray(shn["codebook"], np.float64)
        coeffs = [0, 3, 8, 15][bands]
        if book.shape != (256,) or not 0 < k <= 65536:
            raise ValueError
    except (ValueError, KeyError, TypeError, IndexError):
        raise refuse(path, "meta.json shN is not SOG metadata") from None
    cent = image(files[0], 64 * coeffs * math.ceil(k / 64), 64 * coeffs)
    labels = image(files[1], n)[:n]
    lab = labels[:, 0].astype(np.int64) | (labels[:, 1].astype(np.int64) << 8)
    if (lab >= k).any():
        raise refuse(path, "shN_labels.webp indexes past the palette")
    pal = book.astype(np.float32)[cent[:, :3]].reshape(-1, coeffs, 3)  # [rows*64, C, 3]
    return pal[lab]


def read_sog(path: str | os.PathLike, device: torch.device | str = "cpu") -> Gaussians:
    """A .sog bundle (or an unbundled meta.json beside its images) as Gaussians. A
    truncated, garbled or lying file is a one-line SplatError; nothing larger than
    what the file can hold is decoded."""
    path = Path(path)
    get, meta_raw, stored = _open_bundle(path)
    meta = _read_meta(path, meta_raw, stored)
    n, image = int(meta["count"]), _image_reader(path, get)
    files = lambda key, k: (meta[key]["files"] + [None] * k)[:k]  # noqa: E731
    lo, hi = np.asarray(meta["means"]["mins"], np.float64), np.asarray(meta["means"]["maxs"], np.float64)
    ml, mu = (image(f, n)[:n].astype(np.uint32) for f in files("means", 2))
    t = (ml[:, :3] | (mu[:, :3] << 8)).astype(np.float64) / 65535.0
    lt = lo + (hi - lo) * t
    means = np.sign(lt) * np.expm1(np.abs(lt))
    qi = image(files("quats", 1)[0], n)[:n]
    tag = qi[:, 3].astype(np.int64)
    if ((tag < 252) | (tag > 255)).any():
        raise refuse(path, "quats.webp holds a largest-component tag outside 252-255")
    quats = unpack_smallest_three(tag - 252, (qi[:, :3].astype(np.float64) / 255.0 * 2.0 - 1.0) / np.sqrt(2.0))
    si = image(files("scales", 1)[0], n)[:n]
    log_scales = np.asarray(meta["scales"]["codebook"], np.float64)[si[:, :3]]
    ci = image(files("sh0", 1)[0], n)[:n]
    dc = np.asarray(meta["sh0"]["codebook"], np.float64)[ci[:, :3]]
    opacity = logit(ci[:, 3].astype(np.float64) / 255.0, 0.5 / 255.0)
    sh = dc[:, None, :].astype(np.float32)
    if meta.get("shN"):
        sh = np.concatenate([sh, _read_shn(path, meta["shN"], files("shN", 2), n, image)], axis=1)
    return Arrays(means, quats, log_scales, opacity, sh).gaussians(device)
