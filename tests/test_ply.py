"""The interchange .ply: exact 3DGS layout, round trip, and what other tools write."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import plyfile
import pytest
import torch

from splatcli.formats.ply import PlyError, ply_bytes, ply_header, ply_property_names, read_ply, write_ply
from splatcli.gaussians import Gaussians, num_sh_bases


def random_gaussians(n: int, d: int, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.randn(*s, generator=g)  # noqa: E731
    return Gaussians(means=r(n, 3), quats=r(n, 4), log_scales=r(n, 3) - 3, opacity_logits=r(n), sh=r(n, num_sh_bases(d), 3))


def expected_names(d: int) -> list[str]:
    n_rest = 3 * ((d + 1) ** 2 - 1)
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(n_rest)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def plyfile_reference_bytes(g: Gaussians) -> bytes:
    """What the original 3DGS save_ply produces: a plyfile vertex element of f4
    attributes, f_rest flattened channel-major ([N, K-1, 3] -> [N, 3, K-1])."""
    n, k = len(g), g.sh.shape[1]
    names = expected_names(g.sh_degree)
    dc = g.sh[:, 0, :].numpy()
    rest = g.sh[:, 1:, :].transpose(1, 2).reshape(n, -1).numpy()
    attrs = np.concatenate([g.means.numpy(), np.zeros((n, 3), np.float32), dc, rest,
                            g.opacity_logits[:, None].numpy(), g.log_scales.numpy(), g.quats.numpy()], axis=1)
    el = np.empty(n, dtype=[(a, "f4") for a in names])
    el[:] = list(map(tuple, attrs))
    buf = io.BytesIO()
    plyfile.PlyData([plyfile.PlyElement.describe(el, "vertex")]).write(buf)
    assert k == num_sh_bases(g.sh_degree)
    return buf.getvalue()


@pytest.mark.parametrize("d", [0, 1, 2, 3])
def test_layout_is_exactly_3dgs(tmp_path: Path, d: int) -> None:
    g = random_gaussians(7, d, seed=d)
    path = tmp_path / "s.ply"
    res = write_ply(path, g)
    data = path.read_bytes()
    assert data == plyfile_reference_bytes(g)  # byte-identical to plyfile/3DGS
    assert len(data) == res.bytes == ply_bytes(7, d)
    ply = plyfile.PlyData.read(str(path))
    v = ply["vertex"]
    assert [p.name for p in v.properties] == expected_names(d) == ply_property_names(d)
    assert all(v.data.dtype[p.name] == np.dtype("<f4") for p in v.properties)
    assert ply.byte_order == "<" and not ply.text
    # f_rest channel-major: f_rest_0 is band 1 of R, f_rest_{K-1} is band 1 of G
    if d > 0:
        k = num_sh_bases(d)
        np.testing.assert_array_equal(v["f_rest_0"], g.sh[:, 1, 0].numpy())
        np.testing.assert_array_equal(v[f"f_rest_{k - 1}"], g.sh[:, 1, 1].numpy())
        np.testing.assert_array_equal(v[f"f_rest_{2 * (k - 1)}"], g.sh[:, 1, 2].numpy())


@pytest.mark.parametrize("d", [0, 3])
def test_round_trip_exact(tmp_path: Path, d: int) -> None:
    g = random_gaussians(11, d, seed=5)
    write_ply(tmp_path / "a.ply", g)
    r = read_ply(tmp_path / "a.ply")
    assert r.sh_degree == d and r.num_vertices == 11 and r.num_dropped == 0 and r.has_normals
    assert not r.notes and not r.extra_properties
    for name, t in g.as_dict().items():
        torch.testing.assert_close(getattr(r.gaussians, name), t, rtol=0, atol=0)


def test_ply_bytes_matches_3dgs_size() -> None:
    # 62 floats per Gaussian at degree 3, as in every 3DGS release
    assert ply_bytes(1000, 3) - ply_bytes(0, 3) == 1000 * 62 * 4 + (len("1000") - 1)
    assert ply_bytes(5, 0) == len(ply_header(5, 0)) + 5 * 17 * 4


def test_write_drops_non_finite_rows(tmp_path: Path) -> None:
    g = random_gaussians(6, 1)
    g.means[1, 0] = float("nan")
    g.sh[4, 2, 1] = float("inf")
    res = write_ply(tmp_path / "a.ply", g)
    assert (res.num_written, res.num_dropped) == (4, 2)
    r = read_ply(tmp_path / "a.ply")
    keep = torch.tensor([0, 2, 3, 5])
    torch.testing.assert_close(r.gaussians.means, g.means[keep], rtol=0, atol=0)


def _write_custom(path: Path, fields: dict[str, np.ndarray], byte_order: str = "<", extra_elements=()) -> None:
    n = len(next(iter(fields.values())))
    el = np.empty(n, dtype=[(k, byte_order + v.dtype.str[1:]) for k, v in fields.items()])
    for k, v in fields.items():
        el[k] = v
    els = list(extra_elements) + [plyfile.PlyElement.describe(el, "vertex")]
    plyfile.PlyData(els, byte_order=byte_order).write(str(path))


def _sh0_fields(n: int, rng: np.random.Generator, dtype=np.float32) -> dict[str, np.ndarray]:
    f = {k: rng.normal(size=n).astype(dtype) for k in ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
                                                        "scale_0", "scale_1", "scale_2"]}
    q = rng.normal(size=(n, 4)) * 3.0  # unnormalised, as many tools leave them
    for i in range(4):
        f[f"rot_{i}"] = q[:, i].astype(dtype)
    return f


def test_reads_sh0_without_normals_other_order_extras(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    f = _sh0_fields(9, rng)
    # shuffled order, no normals, extra properties of other types (as e.g. SuperSplat/Polycam add)
    order = list(f)[::-1]
    f = {k: f[k] for k in order}
    f["red"] = rng.integers(0, 255, 9).astype(np.uint8)
    f["segment_id"] = rng.integers(0, 9, 9).astype(np.int32)
    _write_custom(tmp_path / "x.ply", f)
    r = read_ply(tmp_path / "x.ply")
    assert r.sh_degree == 0 and not r.has_normals and r.num_vertices == 9
    assert r.extra_properties == ["red", "segment_id"]
    assert any("red" in n for n in r.notes)
    np.testing.assert_array_equal(r.gaussians.means.numpy(), np.stack([f["x"], f["y"], f["z"]], 1))
    np.testing.assert_array_equal(r.gaussians.quats[:, 2].numpy(), f["rot_2"])  # kept unnormalised
    assert r.gaussians.sh.shape == (9, 1, 3)


def test_reads_double_big_endian_and_other_elements(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    f = _sh0_fields(5, rng, dtype=np.float64)
    for i in range(9):
        f[f"f_rest_{i}"] = rng.normal(size=5)
    cam = np.zeros(2, dtype=[("a", ">f4"), ("b", ">i4")])
    _write_custom(tmp_path / "b.ply", f, byte_order=">", extra_elements=[plyfile.PlyElement.describe(cam, "camera")])
    r = read_ply(tmp_path / "b.ply")
    assert r.sh_degree == 1
    np.testing.assert_allclose(r.gaussians.opacity_logits.numpy(), f["opacity"].astype(np.float32))
    np.testing.assert_allclose(r.gaussians.sh[:, 2, 0].numpy(), f["f_rest_1"].astype(np.float32))
    assert any("camera" in n for n in r.notes)


def test_reader_drops_nan_rows_and_refuses_all_invalid(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    f = _sh0_fields(4, rng)
    f["opacity"][1] = np.nan
    f["rot_0"][2] = f["rot_1"][2] = f["rot_2"][2] = f["rot_3"][2] = 0.0
    _write_custom(tmp_path / "n.ply", f)
    r = read_ply(tmp_path / "n.ply")
    assert r.num_dropped == 2 and len(r.gaussians) == 2 and "dropped 2 of 4" in r.notes[0]
    f["x"][:] = np.inf
    _write_custom(tmp_path / "n.ply", f)
    with pytest.raises(PlyError, match="none of its 4 Gaussians is valid"):
        read_ply(tmp_path / "n.ply")


def _refused(path: Path, match: str) -> None:
    with pytest.raises(PlyError, match=match):
        read_ply(path)


def test_refusals(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    p = tmp_path / "p.ply"
    # plain point cloud
    _write_custom(p, {"x": rng.normal(size=3).astype(np.float32), "y": np.zeros(3, np.float32),
                      "z": np.zeros(3, np.float32), "red": np.zeros(3, np.uint8)})
    _refused(p, "plain point cloud")
    # zero vertices
    write_ply(p, random_gaussians(0, 0))
    _refused(p, "zero Gaussians")
    # wrong property type
    f = _sh0_fields(3, rng)
    f["opacity"] = np.array([1, 2, 3], np.uint8)
    _write_custom(p, f)
    _refused(p, "'opacity' is uchar")
    # truncated / lying header
    write_ply(p, random_gaussians(10, 1))
    data = p.read_bytes()
    p.write_bytes(data[:-5])
    _refused(p, "header claims 10 vertices")
    p.write_bytes(data.replace(b"element vertex 10\n", b"element vertex 99999999999999\n"))
    _refused(p, "header claims 99999999999999 vertices")
    # SH count of no degree
    f = _sh0_fields(3, rng)
    for i in range(5):
        f[f"f_rest_{i}"] = np.zeros(3, np.float32)
    _write_custom(p, f)
    _refused(p, "5 f_rest_")
    # not a ply at all
    p.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    _refused(p, "not a PLY file")
    _refused(tmp_path / "missing.ply", "no such file")
    # errors are one line and name the file
    try:
        read_ply(p)
    except PlyError as e:
        assert str(p) in str(e) and "\n" not in str(e) and isinstance(e, ValueError)


def test_refusals_plyfile_would_not_bound(tmp_path: Path) -> None:
    """What `_check_head` keeps from plyfile: an unbounded header, ASCII and list
    elements (plyfile would allocate the claimed count), plus a misnamed f_rest."""
    p = tmp_path / "p.ply"
    p.write_bytes(b"ply\nformat binary_little_endian 1.0\ncomment " + b"a" * (3 << 20))
    _refused(p, "no end_header within 1048576 bytes")
    write_ply(p, random_gaussians(3, 0))
    data = p.read_bytes()
    p.write_bytes(data.replace(b"element vertex 3\n", b"element face 100000000000\nproperty list uchar int vi\nelement vertex 3\n"))
    _refused(p, "'vi' is list uchar int")
    p.write_bytes(data.replace(b"binary_little_endian", b"ascii"))
    _refused(p, "ASCII PLY is not supported")
    # "f_rest_08" is an extra property, not f_rest_8 (this used to escape as a KeyError)
    write_ply(p, random_gaussians(3, 1))
    p.write_bytes(p.read_bytes().replace(b"f_rest_8\n", b"f_rest_08\n"))
    _refused(p, "8 f_rest_")
