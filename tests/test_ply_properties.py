"""Property tests: the .ply reader never fails with anything but its own PlyError,
whatever bytes it is given, and never allocates beyond the file's size."""

from __future__ import annotations

import tempfile
from pathlib import Path

import torch
from hypothesis import HealthCheck, given, settings, strategies as st

from splatcli.formats.ply import PlyError, read_ply, write_ply
from splatcli.gaussians import Gaussians


def _valid_ply_bytes() -> bytes:
    g = torch.Generator().manual_seed(0)
    n = 4
    gs = Gaussians(means=torch.randn(n, 3, generator=g), quats=torch.randn(n, 4, generator=g),
                   log_scales=torch.randn(n, 3, generator=g), opacity_logits=torch.randn(n, generator=g),
                   sh=torch.randn(n, 4, 3, generator=g))
    with tempfile.TemporaryDirectory() as d:
        write_ply(Path(d) / "v.ply", gs)
        return (Path(d) / "v.ply").read_bytes()


VALID = _valid_ply_bytes()
HEADER_END = VALID.index(b"end_header\n") + len(b"end_header\n")
SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def _read(data: bytes) -> None:
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "x.ply"
        p.write_bytes(data)
        try:
            r = read_ply(p)
        except PlyError as e:
            assert "\n" not in str(e) and str(p) in str(e)
            return
        # when it succeeds, the result is consistent
        n = len(r.gaussians)
        assert 0 < n <= r.num_vertices and bool(r.gaussians.finite_mask().all())


@SETTINGS
@given(st.binary(max_size=2048))
def test_random_bytes(data: bytes) -> None:
    _read(data)


@SETTINGS
@given(st.binary(max_size=512))
def test_random_bytes_after_ply_magic(data: bytes) -> None:
    _read(b"ply\nformat binary_little_endian 1.0\n" + data)


@SETTINGS
@given(st.integers(0, len(VALID)))
def test_truncations(cut: int) -> None:
    _read(VALID[:cut])


@SETTINGS
@given(st.lists(st.tuples(st.integers(0, len(VALID) - 1), st.integers(0, 255)), min_size=1, max_size=8))
def test_byte_mutations(muts: list[tuple[int, int]]) -> None:
    b = bytearray(VALID)
    for i, v in muts:
        b[i] = v
    _read(bytes(b))


@SETTINGS
@given(st.integers(0, HEADER_END), st.text(alphabet="0123456789 \nabcdefghijklmnopqrstuvwxyz_", max_size=40))
def test_header_insertions(pos: int, text: str) -> None:
    _read(VALID[:pos] + text.encode() + VALID[pos:])


@SETTINGS
@given(st.integers(0, 10**30))
def test_lying_vertex_counts(count: int) -> None:
    _read(VALID.replace(b"element vertex 4\n", f"element vertex {count}\n".encode()))
