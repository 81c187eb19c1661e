"""Meshes from trained splats: how close to the true geometry, how long, how much memory.

    .venv/bin/python bench/mesh.py [--sample PROJECT] [--lego PROJECT] [--fox PROJECT] [--no-write]

- **Sample scene** (sample_data/, whose geometry sample_data/make_scene.py knows exactly): the
  project trained at its demo preset (`--sample` reuses one, e.g. a fresh clone's `make demo`;
  else it is processed and trained here). The reference is the true surface seen by the
  ground-truth cameras (ray cast by make_scene: the objects and the ground within 1.8 of the
  centre, not the far wall), moved into the project's frame by the similarity that best maps the
  ground-truth camera centres onto the project's (SfM recovers poses up to one). Then
  `splatcli export --format mesh` and `splatcli eval --mesh REF`: Chamfer distance and F-score at
  1% of the reference's diagonal for the fused mesh and for the naive mesh of the Gaussian centres.
- **lego at 200 px** and **fox at 480 px**: trained here with `--time-budget` (or reused), meshed
  and timed; lego's mesh is drawn (docs/figures/mesh_lego.png) beside splatcli's render of the
  model from the same camera (both made here: no third-party photo goes into the docs).

Results go to the "## Meshes" section of docs/benchmarks.md, with the load average.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from align import umeyama
from common import FIGURES, OUT, ensure_processed, fresh_copy, make_scene, publish, splatcli
from splatcli.model import load_model
from splatcli.project import Project
from splatcli.render import render_camera
from splatcli.views.sources import dataset_views

HEADING = "## Meshes"
REGION = 1.8  # the reference covers |x|, |y| < this (world units of the sample scene; its objects lie within 1.3)


def reference_points(project: Path, out: Path, n: int = 300_000) -> Path:
    """The sample scene's true surface as seen by its cameras, in `project`'s frame, as a .ply."""
    from plyfile import PlyData, PlyElement

    ms = make_scene()
    gt = json.loads((Path(ms.__file__).parent / "scene" / "ground_truth.json").read_text())
    cams = {v.camera.name: v.camera for v in dataset_views(Project(project), "all")}
    src = np.stack([cams[c["name"]].center for c in gt["cameras"] if c["name"] in cams])
    dst = np.stack([-np.asarray(c["viewmat"])[:3, :3].T @ np.asarray(c["viewmat"])[:3, 3]
                    for c in gt["cameras"] if c["name"] in cams])
    to_project = umeyama(dst, src)
    pts = []
    for c in gt["cameras"]:
        o, d = ms.pixel_rays(np.asarray(c["K"]), np.asarray(c["viewmat"]), c["width"], c["height"])
        t, m = ms._cast(o, d)
        p = o + t[:, None] * d
        keep = np.isfinite(t) & (m != ms.WALL) & (m != ms.SKY) & (np.abs(p[:, :2]) < REGION).all(1)
        pts.append(p[keep])
    p = np.concatenate(pts)
    p = to_project.apply(p[np.random.default_rng(0).choice(len(p), min(n, len(p)), replace=False)])
    v = np.empty(len(p), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    v["x"], v["y"], v["z"] = p.T
    out.parent.mkdir(parents=True, exist_ok=True)
    PlyData([PlyElement.describe(v, "vertex")]).write(str(out))
    return out


def trained(scene: str, given: str | None, args: list[str]) -> Path:
    if given:
        return Path(given)
    dest = fresh_copy(ensure_processed(scene), OUT / "mesh" / scene)
    splatcli(["train", str(dest), "--device", "cpu", *args], OUT / "mesh" / f"{scene}-train.log")
    return dest


def mesh(project: Path, name: str) -> tuple[dict, object]:
    r = splatcli(["export", str(project), "--format", "mesh"], OUT / "mesh" / f"{name}-export.log")
    return r.summary, r


def draw(project: Path, out: Path) -> None:
    """The mesh's surface, Lambert-shaded by its normal, from the first test camera (a z-buffer of
    dense surface samples), beside the model's render from that camera."""
    import cv2
    from plyfile import PlyData

    ply = PlyData.read(str(project / "exports" / "mesh.ply"))
    v = np.stack([ply["vertex"][k] for k in "xyz"], 1).astype(np.float64)
    f = np.stack(ply["face"].data["vertex_indices"]).astype(np.int64)
    view = dataset_views(Project(project), "test")[0]
    cam = view.camera.at_resolution(*Project(project).trained_resolution())
    W, H, s = cam.width, cam.height, 2
    vm, K = (x.double().numpy() for x in cam.torch(torch.device("cpu"), torch.float64))
    tri = v[f]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True) + 1e-12
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    rng = np.random.default_rng(0)
    n = 40 * W * H * s * s
    face = rng.choice(len(f), n, p=area / area.sum())
    ab = rng.random((2, n))
    ab = np.where(ab.sum(0) > 1, 1 - ab, ab)
    pts = tri[face, 0] + ab[0, :, None] * (tri[face, 1] - tri[face, 0]) + ab[1, :, None] * (tri[face, 2] - tri[face, 0])
    c = pts @ vm[:3, :3].T + vm[:3, 3]
    u = (c[:, 0] / c[:, 2] * K[0, 0] + K[0, 2]) * s
    w = (c[:, 1] / c[:, 2] * K[1, 1] + K[1, 2]) * s
    ok = (c[:, 2] > 0) & (u >= 0) & (u < W * s) & (w >= 0) & (w < H * s)
    pix = w[ok].astype(int) * W * s + u[ok].astype(int)
    light = np.abs((nrm @ vm[:3, :3].T)[:, 2])
    shade = 0.25 + 0.75 * light[face[ok]]
    order = np.lexsort((c[ok, 2], pix))
    first = np.r_[True, pix[order][1:] != pix[order][:-1]]
    img = np.zeros(H * s * W * s)
    img[pix[order][first]] = shade[order][first]
    img = cv2.resize((img.reshape(H * s, W * s) * 255).astype(np.uint8), (W, H), interpolation=cv2.INTER_AREA)
    model = load_model(project, torch.device("cpu")).gaussians
    bg = torch.tensor(Project(project).background() or (0.0, 0.0, 0.0))
    render = (render_camera(model, cam, bg).image.clamp(0, 1) * 255).round().to(torch.uint8).numpy()[..., ::-1]
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), np.concatenate([render, cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)], 1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sample", help="a trained sample-scene project (demo preset) to reuse")
    ap.add_argument("--lego", help="a trained lego project (200 px) to reuse")
    ap.add_argument("--fox", help="a trained fox project (480 px) to reuse")
    ap.add_argument("--no-write", action="store_true")
    a = ap.parse_args()
    sample = trained("sample", a.sample, ["--preset", "demo"])
    ref = reference_points(sample, OUT / "mesh" / "sample-reference.ply")
    rows, timing = [], []
    s, r = mesh(sample, "sample")
    timing.append(("sample scene (demo preset)", s, r))
    e = splatcli(["eval", str(sample), "--mesh", str(ref), "--no-plots"], OUT / "mesh" / "sample-eval.log").summary["mesh"]
    for name, k in (("fused depth (export --format mesh)", "fused"), ("Gaussian centres, voxelised", "centres")):
        m = e[k]
        rows.append(f"| {name} | {m['chamfer']:.4f} | {m['precision']:.3f} | {m['recall']:.3f} | {m['fscore']:.3f} |")
    for scene, given, args in (("lego", a.lego, ["--max-size", "200", "--time-budget", "120"]),
                               ("fox", a.fox, ["--max-size", "480", "--time-budget", "300"])):
        proj = trained(scene, given, args)
        s, r = mesh(proj, scene)
        timing.append((scene, s, r))
        if scene == "lego":
            draw(proj, FIGURES / "mesh_lego.png")
    text = [HEADING, "",
            "`python bench/mesh.py` on this machine (2 cores): `splatcli export PROJ --format mesh` with no other "
            "option (the median depth of the training views fused at 1/256 of the volume's side, marching cubes), "
            f"then `splatcli eval PROJ --mesh REF`. tau = 1% of the reference's diagonal ({e['tau']:.4f} in the "
            "project's units).", "",
            "**Against the true geometry** (the sample scene, its demo preset; reference: the surface the "
            f"ground-truth cameras see within {REGION} of the centre, objects and ground):", "",
            "| mesh | Chamfer | precision | recall | F-score at 1% |", "| --- | ---: | ---: | ---: | ---: |", *rows, "",
            "**Time and memory** (whole command, peak resident memory; load average before → after):", "",
            "| scene | views | volume | triangles | seconds | peak MB | load |", "| --- | ---: | --- | ---: | ---: | ---: | --- |",
            *[f"| {n} | {s['views']} | {'×'.join(map(str, s['grid']))} | {s['faces']:,} | {r.wall_s:.0f} | "
              f"{r.peak_mb} | {r.load[0]:.2f} → {r.load[1]:.2f} |" for n, s, r in timing], "",
            "![lego's mesh beside splatcli's render of the model](figures/mesh_lego.png)", ""]
    publish(HEADING, "\n".join(text), write=not a.no_write)


if __name__ == "__main__":
    main()
