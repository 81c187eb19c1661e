"""How close a mesh is to a reference surface: Chamfer distance and F-score (`eval --mesh REF`).

Both surfaces become points: a mesh is sampled uniformly by area (seeded), a point cloud is
taken as it is. Distances go both ways through a k-d tree (scipy, with the `mesh` extra):
precision is the share of the mesh's points within tau of the reference, recall the share of
the reference's points within tau of the mesh, F the harmonic mean, and the Chamfer distance
the mean of the two mean distances. tau defaults to 1% of the reference's bounding-box
diagonal. Mesh points outside the reference's bounding box are left out: a reference covers
a region (the objects), a mesh also holds what surrounds it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from plyfile import PlyData

from ..errors import SplatError
from ..files.atomic import atomic_write_json
from ..model import load_model
from ..project import Project
from ..views.sources import dataset_views
from .fuse import centres_mesh, grid_for, scene_box

SAMPLES = 200_000  # points sampled on a mesh
TAU = 0.01  # of the reference's diagonal


@dataclass
class SurfaceScore:
    chamfer: float  # world units (the mesh's frame)
    precision: float
    recall: float
    fscore: float
    tau: float  # world units


def sample_surface(verts: np.ndarray, faces: np.ndarray, n: int = SAMPLES, seed: int = 0) -> np.ndarray:  # [n, 3]
    """Points uniform by area on a triangle mesh (verts [V, 3], faces [F, 3])."""
    tri = verts[faces].astype(np.float64)  # [F, 3, 3]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if len(faces) == 0 or area.sum() <= 0:
        raise SplatError("the mesh has no area to sample")
    rng = np.random.default_rng(seed)
    f = rng.choice(len(faces), size=n, p=area / area.sum())
    a, b = rng.random((2, n))
    flip = a + b > 1
    a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
    t = tri[f]
    return t[:, 0] + a[:, None] * (t[:, 1] - t[:, 0]) + b[:, None] * (t[:, 2] - t[:, 0])


def read_surface(path: str | Path, seed: int = 0) -> np.ndarray:  # [n, 3]
    """A .ply's surface as points: sampled from its faces, or its vertices when it has none."""
    try:
        ply = PlyData.read(str(path))
        v = ply["vertex"]
        verts = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64)
    except (OSError, ValueError, KeyError) as e:
        raise SplatError(f"{path}: not a readable .ply with vertices ({type(e).__name__})") from None
    if "face" in ply and len(ply["face"].data):
        faces = np.stack(ply["face"].data["vertex_indices"]).astype(np.int64)
        return sample_surface(verts, faces, seed=seed)
    return verts


def surface_score(points: np.ndarray, reference: np.ndarray, tau: float | None = None) -> SurfaceScore:
    """points [n, 3] (a mesh's samples) against reference [m, 3]."""
    from scipy.spatial import cKDTree

    lo, hi = reference.min(0), reference.max(0)
    diag = float(np.linalg.norm(hi - lo))
    tau = TAU * diag if tau is None else tau
    points = points[((points >= lo) & (points <= hi)).all(1)]
    if len(points) == 0:
        raise SplatError("no mesh point lies near the reference (are they in the same frame?)")
    d_pr = cKDTree(reference).query(points, workers=-1)[0]
    d_rp = cKDTree(points).query(reference, workers=-1)[0]
    p, r = float((d_pr < tau).mean()), float((d_rp < tau).mean())
    return SurfaceScore(chamfer=float(0.5 * (d_pr.mean() + d_rp.mean())), precision=p, recall=r,
                        fscore=0.0 if p + r == 0 else 2 * p * r / (p + r), tau=tau)


@dataclass
class MeshReport:
    reference: str
    tau: float
    fused: SurfaceScore  # exports/mesh.ply (export --format mesh)
    centres: SurfaceScore  # the naive mesh of the Gaussian centres, on the same grid

    def to_json(self) -> dict[str, Any]:
        return asdict(self)  # the scores nest as dicts of their fields


def score_mesh(root: str | Path, reference: str | Path) -> MeshReport:
    """`eval PROJ --mesh REF`: the project's exported mesh and the naive mesh of its Gaussian
    centres (fuse.centres_mesh, on the export's default grid), against the reference surface;
    also written to PROJECT/reports/mesh.json."""
    project = Project.open(root)
    path = project.exports_dir / "mesh.ply"
    if not path.is_file():
        raise SplatError(f"{path}: no mesh yet; run `splatcli export {project.root} --format mesh` first")
    if not Path(reference).is_file():
        raise SplatError(f"--mesh {reference}: no such file (a .ply of the reference surface: points or triangles)")
    ref = read_surface(reference)
    g = load_model(project.root, torch.device("cpu")).gaussians
    lo, hi = scene_box(g, [v.camera for v in dataset_views(project, "train")])
    voxel, shape = grid_for(lo, hi, None)
    naive = centres_mesh(g, lo, voxel, shape)
    fused = surface_score(read_surface(path), ref)
    report = MeshReport(str(reference), fused.tau, fused, surface_score(sample_surface(naive.verts, naive.faces), ref))
    atomic_write_json(project.reports_dir / "mesh.json", report.to_json())
    return report
