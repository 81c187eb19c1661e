"""Benchmark `splatcli process`: SfM speed on the fox capture, pose accuracy on the sample scene.

    python bench/process.py [--baseline] [--no-accuracy] [--no-write]

fox: the 50 raw photos of ../shared/data/fox/images (or $SPLATCLI_DATA/fox),
shrunk to 400 px wide, through SfM: registered images, reprojection error, seconds per
stage, and pose agreement with the capture's own transforms.json (which has its
own errors, so this is a sanity check, not ground truth). `--baseline` also runs
COLMAP's defaults (8192 SIFT features on the upsampled octave, all pairs) for
the ratio, measured in the same run. Skips cleanly when the data is absent.

sample scene: sample_data/make_scene.py rendered at its defaults, then process,
then poses against the exact ground truth after a similarity alignment.

Writes the "## process" section of docs/benchmarks.md (other sections kept).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from align import PoseErrors, compare_poses
from common import DOC, REPO, data_dir, make_scene, write_section
from splatcli.camera import Camera
from splatcli.device import cpu_name
from splatcli.io.transforms import read_transforms
from splatcli.process.run import ProcessConfig, ProcessResult, process
from splatcli.project import Project
from splatcli.sfm.colmap import read_scene

FOX_WIDTH = 400  # the baseline was measured at 400 px wide
SECTION = "## process"


CHOICES = (
    "What the defaults change, each measured on this capture: SIFT on the image's own resolution "
    "(`first_octave` 0) instead of the upsampled octave: about 760 features per image instead of about 2,500 "
    "and 3x less extraction time (table), still 50/50 at 0.61 px; the upsampled octave is kept when SIFT's "
    "image is under 400 px, where it is needed to register at all (16 sample views at 256x192: 3/16 registered "
    "without it, 16/16 with it); sequential pairs for numbered captures and video (each image with its next 5 "
    "and those 8, 16, 32 further: 329 pairs instead of 1,225; an overlap of 10 cost about 25% more CPU in total "
    "for the same result), with any image this leaves out then matched against every image; at most 4,096 "
    "features; matching calls of at least 100 pairs (calls of 19 pairs cost 50% more CPU). Tried and not kept: "
    "fewer RANSAC trials, no watermark check, fewer bundle-adjustment iterations (no measurable gain)."
)


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


def errors_of(project: Path, reference: list[Camera]) -> PoseErrors:
    return compare_poses(read_scene(Project(project).sparse_dir).cameras, reference)


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


def stage_row(label: str, r: ProcessResult, cpu: float, e: PoseErrors | None) -> str:
    s = r.seconds
    acc = f"{e.max_rotation_deg:.2f}° / {100 * e.max_center_error_rel:.2f}%" if e else "-"
    return (f"| {label} | {r.registered}/{r.total} | {r.points} | {r.mean_reprojection_error:.3f} | "
            f"{s.get('extract features', 0):.1f} | {s.get('match', 0):.1f} | {s.get('map', 0):.1f} | "
            f"{s.get('undistort', 0):.1f} | **{s['total']:.1f}** | {cpu:.1f} | {r.matcher}, {r.pairs} | {acc} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--baseline", action="store_true", help="also run COLMAP's defaults on fox (~100 s)")
    ap.add_argument("--no-accuracy", action="store_true", help="skip the sample-scene accuracy run")
    ap.add_argument("--no-write", action="store_true", help="print only; leave docs/benchmarks.md alone")
    args = ap.parse_args()

    load0 = os.getloadavg()[0]
    out = [SECTION, "", f"Measured by `python bench/process.py{' --baseline' if args.baseline else ''}` on "
           f"{cpu_name()}, {os.cpu_count()} CPU cores shared with other jobs (load average {load0:.1f} "
           "at the start: wall times stretch with it; CPU seconds are this process's and do not). "
           "Stage columns are wall seconds.", ""]
    complete = not args.no_accuracy  # only a full run replaces the figures in the docs
    with tempfile.TemporaryDirectory(prefix="splatcli-bench-") as t:
        tmp = Path(t)
        fox = data_dir() / "fox"
        if (fox / "images").is_dir() and (fox / "transforms.json").is_file():
            ref = fox_reference(fox)
            rows = []
            images = fox_at_width(fox / "images", tmp / "fox400")
            r, proj, cpu = process_timed(images, ProcessConfig(), tmp, "fox")
            e = errors_of(proj, ref)
            rows.append(stage_row("splatcli defaults", r, cpu, e))
            ratio = ""
            if args.baseline:
                base = ProcessConfig(max_features=8192, first_octave=-1, matcher="exhaustive")
                rb, projb, cpub = process_timed(images, base, tmp, "fox-baseline")
                rows.append(stage_row("COLMAP defaults (8192 SIFT, upsampled octave, all pairs)", rb, cpub,
                                      errors_of(projb, ref)))
                ratio = (f"Same run, same load: the defaults take {cpub / cpu:.1f}x less CPU time and "
                         f"{rb.seconds['total'] / r.seconds['total']:.1f}x less wall time than COLMAP's defaults "
                         f"(load average {os.getloadavg()[0]:.1f} at the end).")
            out += [
                f"### fox: {r.total} photos, 400 px wide, structure from motion",
                "",
                "| configuration | registered | points | reproj. error (px) | extract | match | map | undistort "
                "| total (s) | CPU (s) | matching, pairs | vs. transforms.json (max rot. / max centre) |",
                "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
                *rows,
                "",
                *([ratio, ""] if ratio else []),
                "Goal: 50/50 registered, reprojection error under 0.7 px, under 45 s. The reference poses of "
                "`transforms.json` come from the capture's own COLMAP run with an OPENCV camera at full "
                "resolution, so they carry their own error; they are a sanity check here.",
                "",
                CHOICES,
                "",
            ]
        else:
            print(f"fox data not found under {fox}; skipping the SfM speed benchmark")
            out += ["fox data absent: speed benchmark skipped.", ""]
            complete = False

        if not args.no_accuracy:
            scene = REPO / "sample_data" / "scene"
            if not (scene / "ground_truth.json").is_file():
                scene = make_scene().render_scene(tmp / "scene")
            gt = json.loads((scene / "ground_truth.json").read_text())
            truth = [Camera(c["name"], c["width"], c["height"], np.asarray(c["K"], float),
                            np.asarray(c["viewmat"], float)) for c in gt["cameras"]]
            r, proj, cpu = process_timed(scene, ProcessConfig(), tmp, "sample")
            e = errors_of(proj, truth)
            print(f"sample: rotation error max {e.max_rotation_deg:.3f}° mean {e.mean_rotation_deg:.3f}°, "
                  f"centre error max {100 * e.max_center_error_rel:.3f}% mean {100 * e.mean_center_error_rel:.3f}% "
                  f"of the extent")
            w, h = truth[0].width, truth[0].height
            out += [
                f"### Pose accuracy: sample scene ({len(truth)} views, {w}x{h}, exact ground truth)",
                "",
                "| registered | points | reproj. error (px) | max rotation error | mean rotation error "
                "| max centre error | mean centre error | total (s) |",
                "| --- | --- | --- | --- | --- | --- | --- | --- |",
                f"| {r.registered}/{r.total} | {r.points} | {r.mean_reprojection_error:.3f} | "
                f"{e.max_rotation_deg:.3f}° | {e.mean_rotation_deg:.3f}° | {100 * e.max_center_error_rel:.3f}% | "
                f"{100 * e.mean_center_error_rel:.3f}% | {r.seconds['total']:.1f} |",
                "",
                "Errors after a similarity alignment of the camera centres (Umeyama); the extent is "
                "`camera.scene_extent` (1.1 x the largest distance of a camera from their mean). "
                "Goal: rotation under 1°, centre under 1% of the extent.",
                "",
            ]
    text = "\n".join(out)
    if args.no_write or not complete:
        print(text)
        if not args.no_write:
            print(f"{DOC} left unchanged: only a full run (fox data present, accuracy run) rewrites it")
    else:
        write_section(SECTION, text)
        print(f"wrote the process section of {DOC}")


if __name__ == "__main__":
    main()
