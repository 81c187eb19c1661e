"""Benchmark `splatcli process`: SfM speed on the fox capture, pose accuracy on the sample scene.

    python bench/process.py [--baseline] [--no-accuracy]

fox: the 50 raw photos of ../shared/data/fox/images (or $SPLATCLI_DATA/fox),
shrunk to 400 px wide, through SfM: registered images, reprojection error, seconds per
stage, and pose agreement with the capture's own transforms.json (which has its
own errors, so this is a sanity check, not ground truth). `--baseline` also runs
COLMAP's defaults (8192 SIFT features on the upsampled octave, all pairs) for
the ratio, measured in the same run. `--unordered` renames the same photos by a hash of their
names (no order left) and runs all pairs against `auto` (pairs by retrieval), with the poses of
each against the other's. Skips cleanly when the data is absent.

sample scene: sample_data/scene (sample_data/make_scene.py's defaults) through process,
then poses against the exact ground truth after a similarity alignment (common.pose_errors).

Results: bench/out/process.json (common.report), the table printed.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from common import REPO, data_dir, pose_errors, report
from splatcli.camera import Camera
from splatcli.inputs.transforms import read_transforms
from splatcli.process.run import ProcessConfig, ProcessResult, process
from splatcli.project import Project
from splatcli.sfm.colmap import read_scene

FOX_WIDTH = 400  # the baseline was measured at 400 px wide


def process_timed(src: Path, cfg: ProcessConfig, tmp: Path, label: str) -> tuple[ProcessResult, Path, float]:
    out = tmp / label
    t_cpu = time.process_time()
    r = process(src, out, cfg)
    cpu = time.process_time() - t_cpu
    print(f"{label}: {r.registered}/{r.total} registered, {r.points} points, "
          f"reproj {r.mean_reprojection_error:.3f} px, {r.seconds['total']:.1f} s wall, {cpu:.1f} s CPU, "
          f"{json.dumps(r.seconds)}", flush=True)
    return r, out, cpu


def fox_reference(fox: Path) -> list[Camera]:
    ts = read_transforms(fox / "transforms.json")
    return [Camera(f.name, 1, 1, np.eye(3), f.viewmat) for f in ts.frames]


def errors_of(project: Path, reference: list[Camera]) -> dict:
    return pose_errors(read_scene(Project(project).sparse_dir).cameras, reference)


def fox_at_width(fox_images: Path, out: Path, width: int = FOX_WIDTH) -> Path:
    """The fox photos shrunk to `width` px wide (area filter, JPEG quality 95),
    the input the baseline was measured on."""
    import cv2

    out.mkdir(parents=True)
    for p in sorted(fox_images.glob("*.jpg")):
        img = cv2.imread(str(p))
        h, w = img.shape[:2]
        img = cv2.resize(img, (width, round(h * width / w)), interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(out / p.name), img, [cv2.IMWRITE_JPEG_QUALITY, 95])
    return out


def renamed(images: Path, out: Path) -> Path:
    """`images` copied under names that give no order (a hash of each name)."""
    out.mkdir(parents=True)
    for p in sorted(images.glob("*.jpg")):
        shutil.copyfile(p, out / f"{hashlib.sha1(p.name.encode()).hexdigest()[:12]}.jpg")
    return out


def unordered_rows(images: Path, tmp: Path, ref: list[Camera]) -> list[dict]:
    """All pairs, then auto (retrieval), on the photos renamed: each against the capture's poses,
    and retrieval's against all pairs' (by the renamed names)."""
    shuffled = renamed(images, tmp / "fox-unordered")
    by_hash = {f"{hashlib.sha1(c.name.encode()).hexdigest()[:12]}.jpg": c for c in ref}
    ref_h = [Camera(n, 1, 1, np.eye(3), c.viewmat) for n, c in by_hash.items()]
    rows = []
    re, pe, ce = process_timed(shuffled, ProcessConfig(matcher="exhaustive"), tmp, "unordered-exhaustive")
    rows.append(row("fox 400 px renamed, all pairs", re, ce, errors_of(pe, ref_h)))
    ra, pa, ca = process_timed(shuffled, ProcessConfig(), tmp, "unordered-auto")
    rows.append(row("fox 400 px renamed, auto (retrieval)", ra, ca, errors_of(pa, ref_h)))
    vs = errors_of(pa, read_scene(Project(pe).sparse_dir).cameras)
    rows[-1]["against all pairs"] = f"{vs['max_rot_deg']:.3f} deg / {vs['max_centre_pct']:.3f}%"
    return rows


def row(label: str, r: ProcessResult, cpu: float, e: dict | None) -> dict:
    return {"run": label, "registered": f"{r.registered}/{r.total}", "points": r.points,
            "reproj_px": r.mean_reprojection_error, **{f"{k} s": v for k, v in r.seconds.items()}, "cpu_s": cpu,
            "matching": f"{r.matcher}, {r.pairs} pairs",
            **{k: (e or {}).get(k) for k in ("max_rot_deg", "mean_rot_deg", "max_centre_pct", "mean_centre_pct")}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--baseline", action="store_true", help="also run COLMAP's defaults on fox (~100 s)")
    ap.add_argument("--no-accuracy", action="store_true", help="skip the sample-scene accuracy run")
    ap.add_argument("--unordered", action="store_true", help="also fox renamed out of order: all pairs against auto")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory(prefix="splatcli-bench-") as t:
        tmp = Path(t)
        fox = data_dir() / "fox"
        if (fox / "images").is_dir() and (fox / "transforms.json").is_file():
            # against the capture's own COLMAP poses (OPENCV camera, full resolution): a sanity check
            ref = fox_reference(fox)
            images = fox_at_width(fox / "images", tmp / "fox400")
            r, proj, cpu = process_timed(images, ProcessConfig(), tmp, "fox")
            rows.append(row("fox 400 px, splatcli defaults", r, cpu, errors_of(proj, ref)))
            if args.baseline:  # same run, same load
                base = ProcessConfig(max_features=8192, first_octave=-1, matcher="exhaustive")
                rb, projb, cpub = process_timed(images, base, tmp, "fox-baseline")
                rows.append(row("fox 400 px, COLMAP defaults (8192 SIFT, upsampled octave, all pairs)", rb, cpub,
                                errors_of(projb, ref)))
            if args.unordered:
                rows += unordered_rows(images, tmp, ref)
        else:
            print(f"fox data not found under {fox}; skipping the SfM speed benchmark")
        if not args.no_accuracy:  # exact ground truth
            scene = REPO / "sample_data" / "scene"
            gt = json.loads((scene / "ground_truth.json").read_text())
            truth = [Camera(c["name"], c["width"], c["height"], np.asarray(c["K"], float),
                            np.asarray(c["viewmat"], float)) for c in gt["cameras"]]
            r, proj, cpu = process_timed(scene, ProcessConfig(), tmp, "sample")
            rows.append(row(f"sample scene, {len(truth)} views", r, cpu, errors_of(proj, truth)))
    # goals: fox 50/50 registered, reprojection under 0.7 px, under 45 s; sample scene rotation
    # under 1 degree, centre under 1% of the extent (camera.scene_extent)
    report("process", rows)


if __name__ == "__main__":
    main()
