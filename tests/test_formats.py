"""Compressed formats (.spz, .compressed.ply) and .splat: round trips within each
format's quantisation step, the frame convention, refusals of bad files, export as
a converter, and the check by a real third-party client (PlayCanvas splat-transform)."""

from __future__ import annotations

import gzip
import math
import os
import random
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from splatcli.camera import Camera
from splatcli.errors import SplatError
from splatcli.gaussians import Gaussians
from splatcli.io.compressed_ply import read_compressed_ply, write_compressed_ply
from splatcli.io.formats import FORMATS, format_of, read_format, write_format
from splatcli.io.ply import write_ply
from splatcli.io.sog import SogOptions, kmeans_1d, read_sog, write_sog
from splatcli.io.spz import SpzOptions, read_spz, write_spz
from splatcli.model import load_model
from splatcli.render import render_camera
from splatcli.views.paths import look_at
from tiny_project import assert_user_error, make_tiny_project, run_cli


def scene(n: int = 600, seed: int = 0, sh_degree: int = 3) -> Gaussians:
    """Gaussians in the ranges trained models have (colours and SH inside what every
    format can hold: SPZ's DC spans +-3.3, its SH +-1, compressed-ply's SH +-4)."""
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.randn(*s, generator=g)  # noqa: E731
    sh = r(n, (sh_degree + 1) ** 2, 3).clamp(-3, 3) * 0.1
    sh[:, 0] = r(n, 3).clamp(-2.5, 2.5)
    return Gaussians(means=r(n, 3) * 0.6, quats=r(n, 4), log_scales=r(n, 3) * 0.3 - 3.0,
                     opacity_logits=r(n) * 2, sh=sh)


def _matched(a: Gaussians, b: Gaussians) -> Gaussians:
    """`b` reordered to `a`'s rows (compressed-ply writes in Morton order): nearest means."""
    d = torch.cdist(a.means.double(), b.means.double())
    return b.select(d.argmin(1))


def _errors(a: Gaussians, b: Gaussians) -> dict[str, float]:
    qa = a.quats / a.quats.norm(dim=1, keepdim=True)
    qb = b.quats / b.quats.norm(dim=1, keepdim=True)
    return {
        "means": float((a.means - b.means).abs().max()),
        "log_scales": float((a.log_scales - b.log_scales).abs().max()),
        "alpha": float((torch.sigmoid(a.opacity_logits) - torch.sigmoid(b.opacity_logits)).abs().max()),
        "rotation": float((1 - (qa * qb).sum(1).abs()).max()),  # 1 - |cos(half angle)|
        "dc": float((a.sh[:, 0] - b.sh[:, 0]).abs().max()),
        "sh": float((a.sh[:, 1:] - b.sh[:, 1:]).abs().max()) if a.sh.shape[1] > 1 else 0.0,
    }


def test_spz_round_trip_within_its_quantisation_step(tmp_path):
    g = scene()
    path = tmp_path / "m.spz"
    written, dropped, size = write_spz(path, g)
    assert (written, dropped) == (len(g), 0) and size == path.stat().st_size
    e = _errors(g, read_spz(path))
    # Steps: positions 2^-fb (fb = 16 here: |x| < 128); log scale 1/16 (half a step when
    # rounding); alpha, colour 1/255 of their ranges; SH 8/128 (degree 1, 5 bits) and 16/128
    # (4 bits), each rounded so within half a step plus the first rounding.
    assert e["means"] <= 2 ** -16
    assert e["log_scales"] <= 1 / 32 + 1e-6
    assert e["alpha"] <= 0.5 / 255 + 1e-6
    assert e["dc"] <= 0.5 / 255 / 0.15 + 1e-6
    assert e["sh"] <= (8 + 1) / 128 + 1e-6
    assert e["rotation"] < 2e-5  # 9 bits per smallest component
    # fewer SH bits: a smaller file, a coarser SH
    small = tmp_path / "s.spz"
    write_spz(small, g, SpzOptions(sh1_bits=3, sh_rest_bits=2))
    assert small.stat().st_size < size


def test_compressed_ply_round_trip_within_its_quantisation_step(tmp_path):
    g = scene()
    path = tmp_path / "m.compressed.ply"
    write_compressed_ply(path, g)
    back = read_compressed_ply(path)
    assert len(back) == len(g) and format_of(path) == "compressed-ply"
    e = _errors(g, _matched(g, back))
    # Per-chunk ranges: 11/10 bits of each chunk's box and log-scale range, 8 bits of its
    # colour range; SH 8/256 (truncated, so a whole step).
    assert e["means"] < 0.01 and e["log_scales"] < 0.01 and e["alpha"] <= 0.5 / 255 + 1e-6
    assert e["dc"] < 0.03 and e["sh"] <= 8 / 256 + 1e-6 and e["rotation"] < 5e-6


def test_every_format_renders_like_the_original_in_our_frame(tmp_path):
    """A frame or SH-sign mistake (y/z flips of SPZ) would move or recolour the picture."""
    g = scene(sh_degree=3)
    K = np.array([[60.0, 0, 40], [0, 60.0, 30], [0, 0, 1]])
    cams = [Camera(name=f"c{i}", width=80, height=60, K=K,
                   viewmat=look_at(np.array([3 * math.cos(a), -1.0, 3 * math.sin(a)]), np.zeros(3),
                                   np.array([0.0, -1.0, 0.0]))) for i, a in enumerate((0.3, 2.0, 4.1))]
    bg = torch.zeros(3)
    ref = [render_camera(g, c, bg).image for c in cams]
    # splat drops view-dependent colour; sog's SH palette of random (unclustered) SH is coarse
    floor = {"ply": 80, "spz": 30, "compressed-ply": 30, "sog": 22, "splat": 15}
    for fmt in FORMATS:
        path = tmp_path / f"m.{fmt}"
        write_format(fmt, path, g)
        back = read_format(path, fmt=fmt).gaussians
        for c, r in zip(cams, ref):
            mse = float(((render_camera(back, c, bg).image - r) ** 2).mean())
            assert -10 * math.log10(max(mse, 1e-12)) > floor[fmt], fmt


def test_sog_round_trip_within_its_codebooks(tmp_path):
    g = scene(3000)
    path = tmp_path / "m.sog"
    write_sog(path, g)
    back = _matched(g, read_sog(path))
    e = _errors(g, back)
    # positions: 16 bits of sign(x) ln(1 + |x|); quaternions 8 bits; opacity 8 bits.
    assert e["means"] < 1e-3 and e["rotation"] < 2e-3 and e["alpha"] <= 0.5 / 255 + 1e-6
    # codebooks: small on average (the tails get entries of their own, but fewer)
    assert float((g.log_scales - back.log_scales).abs().mean()) < 0.01
    assert float((g.sh[:, 0] - back.sh[:, 0]).abs().mean()) < 0.02
    # a bigger SH palette is closer (and larger)
    big = tmp_path / "big.sog"
    write_sog(big, g, SogOptions(palette=3000))
    assert float((g.sh[:, 1:] - _matched(g, read_sog(big)).sh[:, 1:]).abs().max()) < 0.02
    assert big.stat().st_size > path.stat().st_size


def test_1d_codebook_covers_the_tails():
    v = np.concatenate([np.random.default_rng(0).normal(-3, 0.3, 20000), [2.0, 2.5]]).astype(np.float32)
    c, i = kmeans_1d(v)
    assert len(c) == 256 and np.all(np.diff(c) >= 0)
    assert abs(c[i[-1]] - 2.5) < 0.3 and np.abs(c[i] - v).mean() < 0.005  # an outlier keeps an entry near it


def test_bad_sog_files_are_refused_in_one_line(tmp_path):
    import io
    import json
    import zipfile

    g = scene(200)
    good = tmp_path / "g.sog"
    write_sog(good, g)
    with zipfile.ZipFile(good) as z:
        members = {n: z.read(n) for n in z.namelist()}

    def bundle(**change) -> bytes:
        b = io.BytesIO()
        with zipfile.ZipFile(b, "w") as z:
            for n, d in {**members, **change}.items():
                if d is not None:
                    z.writestr(n, d)
        return b.getvalue()

    meta = json.loads(members["meta.json"])
    cases = {
        "not a readable SOG": good.read_bytes()[:300],
        "no meta.json": bundle(**{"meta.json": None}),
        "not SOG metadata": bundle(**{"meta.json": b"{}"}),
        "version 1": bundle(**{"meta.json": json.dumps({**meta, "version": 1}).encode()}),
        "more than its": bundle(**{"meta.json": json.dumps({**meta, "count": 10 ** 9}).encode()}),
        "does not fit": bundle(**{"meta.json": json.dumps({**meta, "count": 5000}).encode()}),
        "does not hold": bundle(**{"quats.webp": None}),
        "not a readable WebP": bundle(**{"scales.webp": b"RIFF0000WEBPjunk"}),
    }
    for words, data in cases.items():
        bad = tmp_path / "bad.sog"
        bad.write_bytes(data)
        with pytest.raises(SplatError, match=words) as info:
            read_sog(bad)
        assert "\n" not in str(info.value), words


def _spz_bytes(version=3, n=2, deg=0, payload: bytes | None = None) -> bytes:
    per = 9 + 1 + 3 + 3 + (4 if version == 3 else 3) + ((deg + 1) ** 2 - 1) * 3
    body = struct.pack("<IIIBBBB", 0x5053474E, version, n, deg, 12, 0, 0) + (payload if payload is not None else bytes(n * per))
    return gzip.compress(body, mtime=0)


@pytest.mark.parametrize("data, words", [
    (b"", "no gzip stream"),
    (b"\x1f\x8b" + random.Random(0).randbytes(200), "damaged SPZ stream"),
    (gzip.compress(b"\x00" * 8, mtime=0), "truncated SPZ header"),
    (gzip.compress(struct.pack("<IIIBBBB", 0x12345678, 3, 1, 0, 12, 0, 0), mtime=0), "magic"),
    (_spz_bytes(version=7), "version 7"),
    (b"NGSP" + bytes(60), "version 4"),
    (_spz_bytes(deg=5), "SH degree 5"),
    (_spz_bytes(n=3, payload=bytes(20)), "truncated"),
    (_spz_bytes(n=4_000_000_000, payload=b""), "more than its"),  # a lying count: refused, nothing allocated
], ids=lambda x: x if isinstance(x, str) else None)  # the same test ids in every process (pytest-xdist)
def test_bad_spz_files_are_refused_in_one_line(tmp_path, data, words):
    path = tmp_path / "bad.spz"
    path.write_bytes(data)
    with pytest.raises(SplatError, match=words) as info:
        read_spz(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)


def test_bad_compressed_ply_files_are_refused_in_one_line(tmp_path):
    g = scene(300, sh_degree=1)
    good = tmp_path / "g.compressed.ply"
    write_compressed_ply(good, g)
    raw = good.read_bytes()
    cases = {
        "truncated": raw[:-100],
        "cannot hold": raw.replace(b"element chunk 2", b"element chunk 9"),
        "sh element": raw.replace(b"element sh 300", b"element sh 299"),
        "not a PLY": b"garbage" + raw,
        "binary_little_endian": raw.replace(b"binary_little_endian", b"binary_big_endian"),
        "unexpected PLY header": raw.replace(b"element vertex 300", b"element vertex 300 x"),
    }
    for words, data in cases.items():
        bad = tmp_path / "bad.compressed.ply"
        bad.write_bytes(data)
        with pytest.raises(SplatError, match=words):
            read_compressed_ply(bad)
    # a lying vertex count with a matching chunk count: refused before reading rows
    bad.write_bytes(raw.replace(b"element chunk 2", b"element chunk 3906250").replace(
        b"element vertex 300", b"element vertex 999999999").replace(b"element sh 300", b"element sh 999999999"))
    with pytest.raises(SplatError, match="truncated"):
        read_compressed_ply(bad)


def test_export_converts_between_formats_and_loaders_read_them(tmp_path):
    proj = make_tiny_project(tmp_path / "p")
    r = run_cli("export", proj.root, "--format", "spz", "--json")
    assert r.exit_code == 0, r.output
    spz = proj.root / "exports" / "scene.spz"
    assert spz.is_file()
    # a file source: .spz -> .compressed.ply beside it, then -> .ply elsewhere
    r = run_cli("export", spz, "--format", "compressed-ply")
    assert r.exit_code == 0, r.output
    cply = proj.root / "exports" / "scene.compressed.ply"
    r = run_cli("export", cply, "--format", "ply", "-o", tmp_path / "back.ply")
    assert r.exit_code == 0, r.output
    m = load_model(tmp_path / "back.ply", torch.device("cpu"))
    assert m.kind == "ply" and len(m.gaussians) == len(load_model(proj.root, torch.device("cpu")).gaussians)
    for path, kind in ((spz, "spz"), (cply, "compressed-ply")):
        assert load_model(path, torch.device("cpu")).kind == kind
    # render and eval --model take any format
    r = run_cli("render", spz, "--project", proj.root, "--split", "test", "-o", tmp_path / "frames")
    assert r.exit_code == 0, r.output
    r = run_cli("eval", proj.root, "--model", cply, "--no-plots", "-o", tmp_path / "ev", "--json")
    assert r.exit_code == 0, r.output
    r = run_cli("train", proj.root, "--init-ply", spz, "--iterations", "2", "--eval-every", "0")
    assert r.exit_code == 0, r.output  # and training starts from any format
    assert_user_error(run_cli("export", spz, "--format", "spz", "-o", spz), "source file itself")
    assert_user_error(run_cli("export", proj.root, "--format", "spz", "--spz-sh-bits", "9,4"), "--spz-sh-bits")


def test_eval_formats_reports_size_against_error(tmp_path):
    import json

    proj = make_tiny_project(tmp_path / "p")
    r = run_cli("eval", proj.root, "--formats", "ply,spz,compressed-ply,splat", "--budgets", "1", "--json")
    assert r.exit_code == 0, r.output
    rep = json.loads((proj.root / "reports" / "eval.json").read_text())
    got = {f["format"]: f for f in rep["formats"]}
    assert list(got) == ["ply", "spz", "compressed-ply", "splat"]
    assert got["ply"]["db_lost"] == pytest.approx(0.0, abs=1e-9) and got["ply"]["ratio"] == pytest.approx(1.0, rel=1e-3)
    assert got["spz"]["ratio"] > 3 and got["compressed-ply"]["ratio"] > 2.5  # random SH-1 toy: little to gain
    assert "Size against error, by file format" in (proj.root / "reports" / "eval.md").read_text()
    assert_user_error(run_cli("eval", proj.root, "--formats", "ply,obj"), "--formats 'obj'")


# ---- a real third-party client: PlayCanvas splat-transform -----------------------

def _splat_transform() -> str | None:
    cand = [os.environ.get("SPLAT_TRANSFORM"), shutil.which("splat-transform"),
            str(Path(__file__).resolve().parents[1] / ".ci" / "node" / "node_modules" / ".bin" / "splat-transform")]
    return next((c for c in cand if c and Path(c).is_file()), None)


ST = _splat_transform()
needs_st = pytest.mark.skipif(ST is None, reason="needs PlayCanvas splat-transform (npm i @playcanvas/splat-transform; "
                              ".ci/run installs it under .ci/node)")


def _st(*args: str) -> None:
    r = subprocess.run([ST, "-q", "-w", *args], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr


def _csv(path: Path) -> Gaussians:
    d = np.genfromtxt(path, delimiter=",", names=True)
    n, names = len(d), d.dtype.names
    k = 1 + sum(c.startswith("f_rest") for c in names) // 3
    col = lambda *c: np.stack([d[x] for x in c], 1)  # noqa: E731
    sh = np.zeros((n, k, 3))
    sh[:, 0] = col("f_dc_0", "f_dc_1", "f_dc_2")
    if k > 1:
        sh[:, 1:] = col(*[f"f_rest_{i}" for i in range(3 * (k - 1))]).reshape(n, 3, k - 1).transpose(0, 2, 1)
    t = lambda x: torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32))  # noqa: E731
    return Gaussians(t(col("x", "y", "z")), t(col("rot_0", "rot_1", "rot_2", "rot_3")),
                     t(col("scale_0", "scale_1", "scale_2")), t(d["opacity"]), t(sh))


def _agree(ours: Gaussians, theirs: Gaussians) -> None:
    """Two decoders of one file: equal to float32 rounding, except opacity at the ends
    of its 8 bits, where a decoder picks its own finite stand-in for 0 and 1 (within
    one step of 1/255)."""
    e = _errors(ours, theirs)
    assert e.pop("alpha") <= 1 / 255 + 1e-6
    assert max(e.values()) < 1e-5, e


@needs_st
@pytest.mark.parametrize("fmt", ["spz", "compressed-ply", "sog"])
def test_splat_transform_decodes_our_files_as_we_do(tmp_path, fmt):
    g = scene(700)
    ours = tmp_path / f"m{ {'spz': '.spz', 'sog': '.sog'}.get(fmt, '.compressed.ply')}"
    write_format(fmt, ours, g)
    _st(str(ours), str(tmp_path / "theirs.csv"))
    _agree(read_format(ours, fmt=fmt).gaussians, _csv(tmp_path / "theirs.csv"))


@needs_st
@pytest.mark.parametrize("fmt, suffix", [("spz", ".spz"), ("compressed-ply", ".compressed.ply"), ("sog", ".sog")])
def test_we_read_what_splat_transform_writes_from_our_ply(tmp_path, fmt, suffix):
    g = scene(700)
    write_ply(tmp_path / "m.ply", g)
    theirs = tmp_path / f"theirs{suffix}"
    extra = {"spz": ["--spz-version", "3"], "sog": ["-g", "cpu", "-i", "3"]}.get(fmt, [])  # SOG's SH k-means on the CPU
    _st(str(tmp_path / "m.ply"), *extra, str(theirs))
    _st(str(theirs), str(tmp_path / "theirs.csv"))
    ours = read_format(theirs, fmt=fmt).gaussians
    _agree(ours, _csv(tmp_path / "theirs.csv"))
    # and both are our .ply within the format's step (positions: SPZ's 12 fractional bits)
    e = _errors(g, _matched(g, ours))
    assert e["means"] < {"spz": 2 ** -12, "sog": 1e-3}.get(fmt, 0.01) and e["alpha"] <= 1 / 255 + 1e-6
