"""Benchmark issue 38: posed captures with real points, LLFF, cameras grouped by EXIF, SfM in pieces.

    python bench/posed.py [--train] [--no-write]

fox (../shared/data/fox or $SPLATCLI_DATA/fox):
  * from transforms.json, with and without triangulated points (`--no-triangulate`):
    process seconds per stage, points, reprojection error; with `--train`, each
    project trained one after the other (`train --preset fast --iterations 1000
    --max-size 480 --eval-every 250`, under `nice -n 10`) and scored held out;
  * from its photos (`--input-type images --max-size 400`, the no-regression target);
  * as an LLFF capture: poses_bounds.npy written from transforms.json (axes to
    [down, right, back], h w f, near/far from the triangulated points' depths), imported,
    and its poses compared with SfM's on the same photos after a similarity alignment.
lego (NeRF synthetic): how many points triangulate on a synthetic object.
Two cameras (rendered sample scene, half the views zoomed 1.25x, EXIF per half): EXIF
grouping against `--single-camera`. No photo collection of several cameras is here.

Every row says the load average beside it (2 shared cores: wall times stretch with it).
Writes the "## process: photo collections and posed captures (issue 38)" section of
docs/benchmarks.md (other sections kept).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from align import compare_poses
from common import REPO, data_dir, make_scene, publish, zoom_about_centre
from splatcli.camera import Camera
from splatcli.io.llff import to_poses_bounds
from splatcli.io.transforms import read_transforms
from splatcli.process.run import ProcessConfig, ProcessResult, process
from splatcli.project import Project
from splatcli.sfm.colmap import read_scene

SECTION = "## process: photo collections and posed captures (issue 38)"
TRAIN = ["--preset", "fast", "--iterations", "1000", "--max-size", "480", "--eval-every", "250"]


def load() -> str:
    return " / ".join(f"{v:.1f}" for v in os.getloadavg())


def run(src: Path, out: Path, cfg: ProcessConfig) -> tuple[ProcessResult, str]:
    before = load()
    r = process(src, out, cfg)
    s = r.seconds
    print(f"{out.name}: {r.registered}/{r.total}, {r.points} points, {s['total']:.1f} s, {json.dumps(s)}, "
          f"load {before} -> {load()}", flush=True)
    return r, before


def stages(r: ProcessResult) -> str:
    return ", ".join(f"{k} {v:.1f}" for k, v in r.seconds.items() if k != "total")


def train(project: Path) -> tuple[float, float, str]:
    """(held-out PSNR at the last step, wall seconds, load at the start) of the benchmark's training."""
    before = load()
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    t0 = time.perf_counter()
    subprocess.run(["nice", "-n", "10", sys.executable, "-m", "splatcli", "train", str(project), *TRAIN, "--quiet"],
                   check=True, env=env)
    wall = time.perf_counter() - t0
    rows = [json.loads(ln) for ln in Project(project).train_log_path.read_text().splitlines() if ln.strip()]
    psnr = [r for r in rows if r.get("psnr") is not None][-1]
    print(f"train {project.name}: step {psnr['step']} held-out {psnr['psnr']:.2f} dB, {wall:.0f} s, "
          f"load {before} -> {load()}", flush=True)
    return float(psnr["psnr"]), wall, before


def fox_llff(fox: Path, posed: Path, out: Path) -> Path:
    """fox as an LLFF capture: its photos (linked) and poses_bounds.npy from transforms.json,
    near/far from the depths of the triangulated points each camera sees (1st, 99th percentile)."""
    ts = read_transforms(fox / "transforms.json")
    (out / "images").mkdir(parents=True)
    pts = read_scene(Project(posed).sparse_dir).points
    vms, hwf, bounds = [], [], []
    for f in ts.frames:
        (out / "images" / f.name).symlink_to(f.source)
        _, params = f.intrinsics.resolve(int(f.intrinsics.w), int(f.intrinsics.h), "fox")
        vms.append(f.viewmat)
        hwf.append((f.intrinsics.h, f.intrinsics.w, 0.5 * (params[0] + params[1])))
        z = (pts @ f.viewmat[:3, :3].T + f.viewmat[:3, 3])[:, 2]
        z = z[z > 0]
        bounds.append((float(np.percentile(z, 1)), float(np.percentile(z, 99))))
    np.save(out / "poses_bounds.npy", to_poses_bounds(vms, hwf, bounds))
    return out


def two_camera_scene(out: Path, zoom: float = 1.25, exif: bool = True) -> tuple[Path, list[Camera]]:
    """The sample scene (16 views, 256x192) with every other view zoomed `zoom` x, EXIF per half (or none)."""
    import cv2
    from PIL import Image

    render_scene = make_scene().render_scene

    scene = out / "scene"
    if not scene.is_dir():
        render_scene(scene, num_views=16, width=256, height=192)
    gt = json.loads((scene / "ground_truth.json").read_text())["cameras"]
    src = out / ("two" if exif else "two-stripped")
    src.mkdir()
    cams = []
    for i, c in enumerate(gt):
        img = cv2.imread(str(scene / "images" / c["name"]))
        h, w = img.shape[:2]
        ex = Image.Exif()
        if i % 2:
            img = zoom_about_centre(img, zoom)
            ex[0x010F], ex[0x0110] = "Panasonic", "DMC-FZ150"
            ex.get_ifd(0x8769)[0x920A] = 62.5
        else:
            ex[0x010F], ex[0x0110] = "Canon", "Canon EOS 60D"
            ex.get_ifd(0x8769)[0x920A] = 50.0
        Image.fromarray(img[..., ::-1]).save(src / c["name"], exif=ex if exif else Image.Exif(), quality=95)
        cams.append(Camera(c["name"], w, h, np.asarray(c["K"], float), np.asarray(c["viewmat"], float)))
    return src, cams


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--train", action="store_true", help="also train fox from both projects (~20 min on 2 cores)")
    ap.add_argument("--no-write", action="store_true", help="print only; leave docs/benchmarks.md alone")
    args = ap.parse_args()
    fox, lego = data_dir() / "fox", data_dir() / "lego"
    if not (fox / "transforms.json").is_file():
        print(f"fox data not found under {fox}; nothing to measure")
        return
    out = [SECTION, "", f"Measured by `python bench/posed.py{' --train' if args.train else ''}` on 2 CPU cores shared "
           "with other jobs; the load average (1, 5, 15 min) is beside each row, taken as the row started.", ""]
    with tempfile.TemporaryDirectory(prefix="splatcli-bench-") as t:
        tmp = Path(t)
        r0, l0 = run(fox, tmp / "fox-random", ProcessConfig(triangulate=False))
        r1, l1 = run(fox, tmp / "fox-points", ProcessConfig())
        out += [
            "### fox from transforms.json: triangulated points against random ones",
            "",
            "| process | points | reproj. error (px) | track length | pairs | stages (s) | total (s) | load |",
            "| --- | --- | --- | --- | --- | --- | --- | --- |",
            f"| `--no-triangulate` (as before) | 0 (random) | - | - | - | {stages(r0)} | **{r0.seconds['total']:.1f}** "
            f"| {l0} |",
            f"| default (1,000 px SIFT, {r1.pairs} pairs by pose) | {r1.points} | {r1.mean_reprojection_error:.2f} | "
            f"{r1.mean_track_length:.1f} | {r1.pairs} | {stages(r1)} | **{r1.seconds['total']:.1f}** | {l1} |",
            "",
            f"Triangulation costs {r1.seconds['total'] - r0.seconds['total']:+.1f} s here (target: at most +60 s).",
            "",
        ]
        if args.train:
            p0, w0, t0 = train(tmp / "fox-random")
            p1, w1, t1 = train(tmp / "fox-points")
            out += [
                "| training (`train " + " ".join(TRAIN) + "`, `nice -n 10`, one after the other) | held-out PSNR "
                "at step 1,000 | wall (s) | load |",
                "| --- | --- | --- | --- |",
                f"| from random points | {p0:.2f} dB | {w0:.0f} | {t0} |",
                f"| from triangulated points | **{p1:.2f} dB** ({p1 - p0:+.2f}) | {w1:.0f} | {t1} |",
                "",
                "Target: at least +2 dB.",
                "",
            ]
        rp, lp = run(fox / "images", tmp / "fox-photos", ProcessConfig(input_type="images", max_size=400))
        llff = fox_llff(fox, tmp / "fox-points", tmp / "fox-llff")
        rl, ll = run(llff, tmp / "fox-llff-p", ProcessConfig())
        sfm = read_scene(Project(tmp / "fox-photos").sparse_dir).cameras
        e = compare_poses(read_scene(Project(tmp / "fox-llff-p").sparse_dir).cameras, sfm)
        et = compare_poses(read_scene(Project(tmp / "fox-points").sparse_dir).cameras, sfm)
        out += [
            "### fox from its photos, and as an LLFF capture",
            "",
            "| input | registered | points | reproj. error (px) | stages (s) | total (s) | load |",
            "| --- | --- | --- | --- | --- | --- | --- |",
            f"| photos, `--input-type images --max-size 400` | {rp.registered}/{rp.total} | {rp.points} | "
            f"{rp.mean_reprojection_error:.2f} | {stages(rp)} | **{rp.seconds['total']:.1f}** | {lp} |",
            f"| LLFF (poses_bounds.npy from transforms.json) | {rl.registered}/{rl.total} | {rl.points} | "
            f"{rl.mean_reprojection_error or 0:.2f} | {stages(rl)} | **{rl.seconds['total']:.1f}** | {ll} |",
            "",
            f"LLFF poses against SfM's on the same photos, after a similarity alignment: max rotation "
            f"{e.max_rotation_deg:.2f}° (mean {e.mean_rotation_deg:.2f}°), max centre error "
            f"{100 * e.max_center_error_rel:.2f}% of the extent (mean {100 * e.mean_center_error_rel:.2f}%), over "
            f"{len(e.names)} cameras (target: 1°, 1%). The transforms.json import gives the same figures "
            f"({et.max_rotation_deg:.2f}°, {100 * et.max_center_error_rel:.2f}%): the LLFF conversion loses nothing "
            "(tests/test_process.py checks it exactly); what remains is SfM at 400 px against the capture's own "
            "COLMAP run at full resolution.",
            "",
        ]
        if (lego / "transforms_train.json").is_file():
            rg, lg = run(lego, tmp / "lego", ProcessConfig())
            out += [
                "### lego (NeRF synthetic)",
                "",
                f"{rg.triangulated} points triangulated at {rg.mean_reprojection_error or 0:.2f} px "
                f"(initialisation: {rg.init}) in {rg.seconds['total']:.1f} s ({stages(rg)}; load {lg}): the "
                "object carries texture enough, and the alpha masks keep SIFT off the white background, so it is "
                "no featureless object; the fallback to random points (under 1,000 points) is for those.",
                "",
            ]
            if args.train:
                run(lego, tmp / "lego-random", ProcessConfig(triangulate=False))
                q0, v0, s0 = train(tmp / "lego-random")
                q1, v1, s1 = train(tmp / "lego")
                out += [
                    "| lego training (as fox's) | held-out PSNR at step 1,000 | wall (s) | load |",
                    "| --- | --- | --- | --- |",
                    f"| from random points | {q0:.2f} dB | {v0:.0f} | {s0} |",
                    f"| from triangulated points | **{q1:.2f} dB** ({q1 - q0:+.2f}) | {v1:.0f} | {s1} |",
                    "",
                ]
        src, gt = two_camera_scene(tmp / "two")
        stripped, _ = two_camera_scene(tmp / "two", exif=False)
        rows = []
        for label, photos, cfg in (("EXIF grouping (default)", src, ProcessConfig()),
                                   ("`--single-camera`", src, ProcessConfig(cameras="single")),
                                   ("EXIF stripped (default: one shared camera, then one each)", stripped,
                                    ProcessConfig())):
            proj = tmp / f"two-{photos.name}-{cfg.cameras}"
            try:
                r, lr = run(photos, proj, cfg)
            except Exception as exc:  # a failure is a result here
                rows.append(f"| {label} | failed: {exc} | | | | |")
                continue
            e2 = compare_poses(read_scene(Project(proj).sparse_dir).cameras, gt)
            rows.append(f"| {label} | {len(r.cameras)} | {r.registered}/{r.total} | "
                        f"{r.mean_reprojection_error:.3f} | {e2.max_rotation_deg:.2f}° / "
                        f"{100 * e2.max_center_error_rel:.2f}% | {r.seconds['total']:.1f} | {lr} |")
        out += [
            "### Two cameras (rendered sample scene, 16 views; every other one zoomed 1.25x, EXIF per half)",
            "",
            "| cameras | count | registered | reproj. error (px) | max rot. / centre error vs truth | total (s) | load |",
            "| --- | --- | --- | --- | --- | --- | --- |",
            *rows,
            "",
            "No collection of photos from several cameras is on this machine (the issue's 40 photos from a "
            "photo-sharing site are not here), so the several-cameras target (more registered than plain "
            "pycolmap's largest model) could not be measured on one; \"process: several cameras, simulated\" "
            "measures it on fox's photos cropped as four zooms.",
            "",
        ]
    publish(SECTION, "\n".join(out), write=not args.no_write)


if __name__ == "__main__":
    main()
