"""Checkpoints: round trip, atomicity, and refusal of unsafe or broken files."""

from __future__ import annotations

import os
import pickle
import re
from pathlib import Path

import pytest
import torch

from splatcli.errors import SplatError
from splatcli.files.checkpoint import CHECKPOINT_SCHEMA, load_checkpoint, load_gaussians, save_checkpoint
from splatcli.gaussians import Gaussians


def _gaussians(n: int = 7, degree: int = 3) -> Gaussians:
    g = torch.Generator().manual_seed(1)
    r = lambda *s: torch.randn(*s, generator=g)  # noqa: E731
    return Gaussians(r(n, 3), r(n, 4), r(n, 3), r(n), r(n, (degree + 1) ** 2, 3))


def _save(path: Path, **over) -> Path:
    kw = dict(
        step=123,
        gaussians=_gaussians(),
        sh_degree=1,
        optimizer={"means": {"state": {0: {"step": torch.tensor(3.0), "exp_avg": torch.ones(7, 3)}},
                             "param_groups": [{"lr": 1e-3, "betas": (0.9, 0.999), "params": [0]}]}},
        strategy={"grad2d": torch.zeros(7), "count": torch.zeros(7)},
        rng={"torch": torch.get_rng_state()},
        config={"iterations": 10, "preset": "demo"},
        extra={"elapsed_s": 1.5},
    )
    kw.update(over)
    return save_checkpoint(path, **kw)


def test_round_trip(tmp_path):
    p = _save(tmp_path / "step-000000123.pt")
    ck = load_checkpoint(p, "cpu")
    assert ck.schema == CHECKPOINT_SCHEMA and ck.step == 123 and ck.sh_degree == 1
    ref = _gaussians()
    for k, v in ref.as_dict().items():
        assert torch.equal(getattr(ck.gaussians, k), v)  # bitwise: resume relies on it
    assert ck.optimizer["means"]["param_groups"][0]["betas"] == (0.9, 0.999)
    assert torch.equal(ck.rng["torch"], torch.get_rng_state())
    assert ck.config == {"iterations": 10, "preset": "demo"}
    assert ck.extra["elapsed_s"] == 1.5
    m = load_gaussians(p, "cpu")
    assert m.sh.shape == (7, 4, 3) and m.sh_degree == 1  # truncated to the active degree
    assert torch.equal(m.sh, ref.sh[:, :4])
    assert not list(tmp_path.glob(".*tmp"))  # the atomic temp file is gone


def test_pickled_payload_is_refused_and_never_runs(tmp_path):
    marker = tmp_path / "pwned"

    class Evil:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    p = tmp_path / "evil.pt"
    torch.save({"format": "splatcli-checkpoint", "schema": 1, "x": Evil()}, p)
    with pytest.raises(SplatError) as ei:
        load_checkpoint(p)
    msg = str(ei.value)
    assert str(p) in msg and "refused" in msg and "\n" not in msg
    assert not marker.exists()
    # A raw (non-zip) pickle stream is refused as well.
    q = tmp_path / "raw.pt"
    q.write_bytes(pickle.dumps(Evil()))
    with pytest.raises(SplatError):
        load_checkpoint(q)
    assert not marker.exists()


def test_truncated_checkpoint_is_one_line_error(tmp_path):
    p = _save(tmp_path / "c.pt")
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    with pytest.raises(SplatError) as ei:
        load_checkpoint(p)
    assert str(p) in str(ei.value) and "\n" not in str(ei.value)
    p.write_bytes(b"")
    with pytest.raises(SplatError):
        load_checkpoint(p)


def test_checkpoint_declaring_huge_tensors_is_refused_without_allocating(tmp_path):
    """A few edited bytes can make a tensor claim 4 GB. torch checks each tensor's
    record size in the archive before allocating, so memory stays bounded by the file."""
    import resource
    import zipfile

    p = _save(tmp_path / "c.pt")
    z = zipfile.ZipFile(p)
    pkl = next(n for n in z.namelist() if n.endswith("data.pkl"))
    data = z.read(pkl)
    # Every storage size (BININT1/BININT2/BININT after the device string) -> 2^30 elements.
    edited, n = re.subn(rb"(X\x03\x00\x00\x00cpuq.)(K.|M..|J....)", lambda m: m.group(1) + b"J\x00\x00\x00\x40", data)
    assert n > 0
    evil = tmp_path / "evil.pt"
    with zipfile.ZipFile(evil, "w", compression=zipfile.ZIP_STORED) as out:
        for name in z.namelist():
            out.writestr(name, edited if name == pkl else z.read(name))
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(SplatError) as ei:
        load_checkpoint(evil)
    assert "\n" not in str(ei.value)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 512 * 1024  # KiB: far below 4 GB


def _saved_and_edited(tmp_path, edit) -> Path:
    p = _save(tmp_path / "c.pt")
    raw = torch.load(p, weights_only=True)
    edit(raw)
    torch.save(raw, p)
    return p


def test_newer_schema_is_refused(tmp_path):
    p = _saved_and_edited(tmp_path, lambda raw: raw.update(schema=CHECKPOINT_SCHEMA + 1))
    with pytest.raises(SplatError, match="newer") as ei:
        load_checkpoint(p)
    assert str(p) in str(ei.value)


@pytest.mark.parametrize("drop", ["gaussians", "step", "config"])
def test_missing_keys(tmp_path, drop):
    p = _saved_and_edited(tmp_path, lambda raw: raw.pop(drop))
    with pytest.raises(SplatError, match=drop):
        load_checkpoint(p)


def test_bad_shapes_and_missing_file(tmp_path):
    g = _gaussians()
    g.quats = g.quats[:, :3]
    p = _save(tmp_path / "c.pt", gaussians=g)
    with pytest.raises(SplatError, match="quats"):
        load_checkpoint(p)
    with pytest.raises(SplatError, match="not found"):
        load_checkpoint(tmp_path / "nope.pt")


def test_save_keeps_old_file_when_write_fails(tmp_path, monkeypatch):
    p = _save(tmp_path / "c.pt")
    before = p.read_bytes()

    def boom(obj, f, *a, **k):
        Path(f).write_bytes(b"partial")
        raise KeyboardInterrupt

    monkeypatch.setattr(torch, "save", boom)
    with pytest.raises(KeyboardInterrupt):
        _save(p, step=999)
    assert p.read_bytes() == before
    assert not list(tmp_path.glob(".*tmp"))
