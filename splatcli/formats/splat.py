"""The `.splat` format of the web viewers (antimatter15/splat and those that
followed it): 32 bytes per Gaussian, no header.

    offset  0  position  float32 x 3   world units
    offset 12  scale     float32 x 3   activated: exp(log_scale)
    offset 24  colour    uint8 x 4     R, G, B = (0.5 + SH_C0 * dc) * 255, A = sigmoid(opacity) * 255
    offset 28  rotation  uint8 x 4     w, x, y, z of the normalised quaternion, q * 128 + 128

Rows are sorted by descending exp(s0 + s1 + s2) * sigmoid(opacity) (volume times
opacity), which is the order those viewers stream and expect. Values are
clipped to [0, 255] and truncated to uint8, as their converter does.

What is lost: every SH band above degree 0 (view-dependent colour), colour
precision (8 bits, and colours outside [0, 1] are clipped), opacity precision
(8 bits) and quaternion precision (about 1/128). Use .ply to keep the model
exact.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..errors import SplatError
from ..files.atomic import atomic_write_bytes
from ..gaussians import SH_C0, Gaussians

SPLAT_ROW_BYTES = 32
SPLAT_DTYPE = np.dtype([("position", "<f4", (3,)), ("scale", "<f4", (3,)), ("rgba", "u1", (4,)), ("rot", "u1", (4,))])
assert SPLAT_DTYPE.itemsize == SPLAT_ROW_BYTES


@dataclass(frozen=True)
class SplatWriteResult:
    path: Path
    num_written: int
    num_dropped: int  # rows with NaN/Inf or a zero quaternion
    bytes: int


def splat_rows(g: Gaussians) -> tuple[np.ndarray, int]:
    """The sorted structured table [M] of SPLAT_DTYPE and the number of rows dropped."""
    g = g.detach()
    f64 = lambda t: t.to(device="cpu", dtype=torch.float64).numpy()  # noqa: E731
    means = f64(g.means).reshape(-1, 3)
    log_s = f64(g.log_scales).reshape(-1, 3)
    opac = f64(g.opacity_logits).reshape(-1)
    dc = f64(g.sh[:, 0, :]).reshape(-1, 3)
    q = f64(g.quats).reshape(-1, 4)
    qn = np.linalg.norm(q, axis=1)
    ok = (np.isfinite(means).all(1) & np.isfinite(log_s).all(1) & np.isfinite(opac) & np.isfinite(dc).all(1)
          & np.isfinite(q).all(1) & (qn > 0))
    dropped = int((~ok).sum())
    means, log_s, opac, dc, q, qn = means[ok], log_s[ok], opac[ok], dc[ok], q[ok], qn[ok]

    alpha = 1.0 / (1.0 + np.exp(-opac))
    # volume x opacity, in log space so that huge scales do not overflow to ties
    key = log_s.sum(1) + np.log(np.maximum(alpha, 1e-300))
    order = np.argsort(-key, kind="stable")

    out = np.empty(len(order), dtype=SPLAT_DTYPE)
    out["position"] = means[order].astype(np.float32)
    out["scale"] = np.exp(log_s[order]).astype(np.float32)
    rgba = np.concatenate([0.5 + SH_C0 * dc[order], alpha[order, None]], axis=1) * 255.0
    out["rgba"] = np.clip(rgba, 0, 255).astype(np.uint8)  # truncation, as the viewers' converter
    out["rot"] = np.clip(q[order] / qn[order, None] * 128.0 + 128.0, 0, 255).astype(np.uint8)
    return out, dropped


def write_splat(path: str | os.PathLike, gaussians: Gaussians) -> SplatWriteResult:
    """Write the web-viewer .splat (atomically)."""
    rows, dropped = splat_rows(gaussians)
    data = rows.tobytes()
    atomic_write_bytes(path, data)
    return SplatWriteResult(path=Path(path), num_written=int(len(rows)), num_dropped=dropped, bytes=len(data))


def read_splat(path: str | os.PathLike) -> np.ndarray:
    """A .splat file as a structured array of SPLAT_DTYPE (for tests and inspection)."""
    path = Path(path)
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise SplatError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if size % SPLAT_ROW_BYTES:
        raise SplatError(f"{path}: {size} bytes is not a whole number of {SPLAT_ROW_BYTES}-byte splats")
    return np.fromfile(path, dtype=SPLAT_DTYPE)


def splat_gaussians(rows: np.ndarray, device: torch.device | str = "cpu") -> Gaussians:
    """.splat rows (formats/splat.SPLAT_DTYPE) back as Gaussians (SH degree 0)."""
    scale = rows["scale"].astype(np.float64)
    if not np.isfinite(rows["position"]).all() or not (np.isfinite(scale).all() and (scale > 0).all()):
        raise SplatError("a .splat row holds a non-finite position or a scale that is not positive")
    rgba = rows["rgba"].astype(np.float64) / 255.0
    alpha = np.clip(rgba[:, 3], 0.5 / 255.0, 1 - 0.5 / 255.0)
    q = (rows["rot"].astype(np.float64) - 128.0) / 128.0
    q[np.linalg.norm(q, axis=1) == 0] = (1.0, 0.0, 0.0, 0.0)
    t = lambda x: torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32)).to(device)  # noqa: E731
    return Gaussians(t(rows["position"]), t(q), t(np.log(scale)), t(np.log(alpha) - np.log1p(-alpha)),
                     t(((rgba[:, :3] - 0.5) / SH_C0)[:, None, :]))
