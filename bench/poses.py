"""Poses you can trust: `splatcli process` with no options on real captures, in shooting order and
with the names shuffled, what its consistency check says, and how far apart the poses are.

    python bench/poses.py DIR [DIR ...] [--runs K] [--orders ordered,shuffled]

For each folder of photos: `splatcli process DIR` in name order (`ordered`), then on a copy whose
names are a hash of the originals (`shuffled`: no order left). Each run: images registered, wall
time, the check's share of strong pairs that agree and the seconds it took (and their share of
the run), the model kept (the first mapping, the global mapper's, or a consistent part), and the
poses against the first ordered run's after a similarity alignment fitted by RANSAC (so that a
misplaced arc does not pull it): median rotation and centre error, and the share of cameras
within 2 degrees and 2% of the scene's extent (1.1 x the largest camera distance from their
centre). `--runs K` runs each order K times (repeatability: registered set, points, poses of
each run against the first of its order).

Results: bench/out/poses.json (common.report), the table printed. The captures are third-party
and not in ../shared/data; docs/benchmarks.md says where each came from.
"""

from __future__ import annotations

import argparse
import hashlib
import shutil
import tempfile
from pathlib import Path

from common import Run, pose_errors, report, splatcli
from splatcli.camera import Camera
from splatcli.project import Project
from splatcli.sfm.colmap import read_scene

GLOBAL = "the global mapper"


def shuffled(images: Path, out: Path) -> Path:
    """`images` copied under names that give no order (a hash of each name)."""
    out.mkdir(parents=True)
    for p in sorted(images.iterdir()):
        if p.is_file():
            shutil.copyfile(p, out / hashed(p.name))
    return out


def hashed(name: str) -> str:
    return f"{hashlib.sha1(name.encode()).hexdigest()[:12]}{Path(name).suffix.lower()}"


def cameras(project: Path) -> list[Camera]:
    """The raw model's cameras (before undistortion, where there was one)."""
    p = Project(project)
    raw = p.sfm_dir / "distorted"
    return read_scene(raw if raw.is_dir() else p.sparse_dir, pinhole_only=False).cameras


def row(label: str, order: str, k: int, r: Run) -> dict:
    s = r.summary
    check = s.get("consistency") or {}
    kept = next((t["attempt"] for t in reversed(s.get("sfm_tried") or []) if t.get("kept")
                 and t["attempt"] != "the consistency check"), "")
    return {"capture": label, "order": order, "run": k, "registered": f"{s['registered']}/{s['total']}",
            "points": s["points"], "reproj_px": s["mean_reprojection_error"], "wall_s": r.wall_s,
            "check_share_pct": 100 * check.get("share", 0), "strong_pairs": check.get("strong_pairs"),
            "check_s": check.get("seconds"), "check_pct_of_run": 100 * (check.get("seconds") or 0) / r.wall_s,
            "repaired": GLOBAL if kept == GLOBAL else "split" if s.get("placed_apart") else "no",
            "placed_apart": len(s.get("placed_apart") or []), "load": r.load[1]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("captures", nargs="+", type=Path, help="folders of photos")
    ap.add_argument("--runs", type=int, default=1, help="runs of each order (repeatability)")
    ap.add_argument("--orders", default="ordered,shuffled", help="ordered, shuffled or both")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory(prefix="splatcli-poses-") as t:
        tmp = Path(t)
        for src in args.captures:
            label = src.name
            inputs = {"ordered": src, "shuffled": shuffled(src, tmp / f"{label}-shuffled")}
            first: dict[str, list[Camera]] = {}
            for order in args.orders.split(","):
                for k in range(args.runs):
                    out = tmp / f"{label}-{order}-{k}"
                    r = splatcli(["process", str(inputs[order]), "-o", str(out)], tmp / f"{out.name}.log")
                    rows.append(row(label, order, k, r))
                    cams = cameras(out)
                    if order == "shuffled":  # compared under the hashed names
                        cams_ref = first.get("ordered")
                        ref = [Camera(hashed(c.name), c.width, c.height, c.K, c.viewmat) for c in cams_ref] if cams_ref else None
                    else:
                        ref = first.get("ordered")
                    if ref is not None:
                        rows[-1].update(pose_errors(cams, ref))
                    if k > 0:  # repeatability: against the first run of this order
                        same = first[f"{order}-names"] == sorted(c.name for c in cams)
                        e = pose_errors(cams, first[order])
                        rows[-1].update(same_set=same, vs_first_rot_deg=e["max_rot_deg"],
                                        vs_first_centre_pct=e["max_centre_pct"])
                    first.setdefault(order, cams)
                    first.setdefault(f"{order}-names", sorted(c.name for c in cams))
                    shutil.rmtree(out)
    report("poses", rows)


if __name__ == "__main__":
    main()
