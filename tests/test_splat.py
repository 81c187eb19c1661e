"""The web-viewer .splat: 32-byte rows, sorted by size x opacity."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np
import torch

from splatcli.formats.splat import SPLAT_ROW_BYTES, read_splat, write_splat
from splatcli.gaussians import SH_C0, Gaussians


def _gaussians(n: int, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.randn(*s, generator=g)  # noqa: E731
    return Gaussians(means=r(n, 3), quats=r(n, 4) * 2, log_scales=r(n, 3) - 2, opacity_logits=r(n) * 2,
                     sh=r(n, 4, 3))


def _reference(g: Gaussians) -> bytes:
    """Row by row with struct, following the antimatter15 convention literally."""
    rows = []
    for i in range(len(g)):
        s = g.log_scales[i].double().tolist()
        o = float(g.opacity_logits[i])
        rows.append((-math.exp(sum(s)) / (1 + math.exp(-o)), i))
    rows.sort()  # ascending of -(size * opacity) = descending size * opacity
    out = b""
    for _, i in rows:
        pos = g.means[i].tolist()
        sc = [math.exp(v) for v in g.log_scales[i].double().tolist()]
        dc = g.sh[i, 0].double().tolist()
        col = [0.5 + SH_C0 * c for c in dc] + [1 / (1 + math.exp(-float(g.opacity_logits[i])))]
        q = g.quats[i].double().tolist()
        qn = math.sqrt(sum(v * v for v in q))
        out += struct.pack("<3f3f", *pos, *sc)
        out += bytes(int(min(max(c * 255, 0), 255)) for c in col)
        out += bytes(int(min(max(v / qn * 128 + 128, 0), 255)) for v in q)
    return out


def test_splat_byte_layout(tmp_path: Path) -> None:
    g = _gaussians(50)
    res = write_splat(tmp_path / "s.splat", g)
    data = (tmp_path / "s.splat").read_bytes()
    assert len(data) == res.bytes == 50 * SPLAT_ROW_BYTES and res.num_dropped == 0
    ref = _reference(g)
    a = np.frombuffer(data, np.uint8).reshape(50, 32)
    b = np.frombuffer(ref, np.uint8).reshape(50, 32)
    # float parts identical bit for bit (same order, same float32 values)
    np.testing.assert_array_equal(a[:, :12], b[:, :12])
    np.testing.assert_allclose(np.frombuffer(a[:, 12:24].tobytes(), "<f4"), np.frombuffer(b[:, 12:24].tobytes(), "<f4"),
                               rtol=1e-6)  # exp in float64 then rounded to float32 both ways: one ulp at most
    # uint8 parts: truncation of values computed in float64 both ways; allow one step
    # where a value lands within rounding of an integer boundary
    assert np.abs(a[:, 24:].astype(int) - b[:, 24:].astype(int)).max() <= 1


def test_splat_sorted_and_decodes(tmp_path: Path) -> None:
    g = _gaussians(40, seed=3)
    g.means[5, 1] = float("nan")
    res = write_splat(tmp_path / "s.splat", g)
    assert res.num_dropped == 1 and res.num_written == 39
    t = read_splat(tmp_path / "s.splat")
    logit = g.opacity_logits.double().numpy()
    ls = g.log_scales.double().numpy()
    keep = np.isfinite(g.means.numpy()).all(1)
    # rows appear in descending size x opacity: decode sizes (exact float32) and check
    size = np.log(t["scale"].astype(np.float64)).sum(1)
    order = np.argsort(-(ls.sum(1) - np.log1p(np.exp(-logit)))[keep], kind="stable")
    np.testing.assert_allclose(size, ls[keep][order].sum(1), rtol=1e-5)  # log(float32(exp(x))) ~ x
    # the first row is the largest size x opacity Gaussian
    i = int(np.argmax(np.where(keep, ls.sum(1) - np.log1p(np.exp(-logit)), -np.inf)))
    np.testing.assert_array_equal(t["position"][0], g.means[i].numpy())
    # quaternion decodes to the normalised one within quantisation
    q = g.quats[i].double().numpy()
    np.testing.assert_allclose((t["rot"][0].astype(np.float64) - 128) / 128, q / np.linalg.norm(q), atol=1 / 128 + 1e-9)
