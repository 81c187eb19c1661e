"""Training against a peer as a user meets it: OpenSplat's CPU trainer and `splatcli train` with no
options, on the same processed project and the same machine, one after the other, for the same wall time;
both scored by `splatcli eval` on the project's held-out views.

    .venv/bin/python bench/peer_train.py --opensplat PATH/TO/opensplat [--scenes fox,lego] [--minutes 10]

The peer is a build of OpenSplat (recorded commit: 15b7e80; AGPL, never vendored here) for the CPU:
`cmake -DGPU_RUNTIME=CPU -DCMAKE_PREFIX_PATH=$(python -c 'import torch; print(torch.utils.cmake_prefix_path)')`
(OpenCV's development files needed; without internet, FETCHCONTENT_SOURCE_DIR_NLOHMANN_JSON, _NANOFLANN,
_CXXOPTS and _GLM name local checkouts of the versions its CMakeLists.txt asks for). It trains on a COLMAP
model of the training views alone (written here; the points coloured from the photos), at our training
size (`-d`), with its defaults otherwise, its splat in the project's frame (`--keep-crs`) and saved every
`--save-every` steps; it is stopped after `--minutes` and each saved splat is scored with
`splatcli eval P --model FILE`. Ours: `splatcli train` with no options on a copy of the same project (a
10-minute plan), its held-out curve from its log and its end from `eval`. Results: bench/out/peer_train.json.
"""

from __future__ import annotations

import argparse
import re
import struct
import subprocess
import time
from pathlib import Path

import pycolmap

from common import OUT, ensure_processed, fresh_copy, loadavg, psnr_curve, report, splatcli
from splatcli.project import Project


def training_model(project: Project, dest: Path) -> None:
    """COLMAP's binary model of the project's training views alone, into dest/sparse/0 (dest/images: the photos)."""
    rec = pycolmap.Reconstruction(str(project.sparse_dir))
    rec.extract_colors_for_all_images(str(project.images_dir))
    test = set(project.splits([im.name for im in rec.images.values()])["test"])
    out = dest / "sparse" / "0"
    out.mkdir(parents=True, exist_ok=True)
    (dest / "images").unlink(missing_ok=True)
    (dest / "images").symlink_to(project.images_dir.resolve())
    with open(out / "cameras.bin", "wb") as f:
        f.write(struct.pack("<Q", len(rec.cameras)))
        for cid, c in rec.cameras.items():
            f.write(struct.pack("<iiQQ", cid, int(c.model.value), c.width, c.height) + struct.pack(
                f"<{len(c.params)}d", *c.params))
    images = [(i, im) for i, im in rec.images.items() if im.name not in test]
    with open(out / "images.bin", "wb") as f:
        f.write(struct.pack("<Q", len(images)))
        for i, im in images:
            pose = im.cam_from_world() if callable(im.cam_from_world) else im.cam_from_world
            x, y, z, w = pose.rotation.quat
            f.write(struct.pack("<i4d3di", i, w, x, y, z, *pose.translation, im.camera_id) + im.name.encode() + b"\0"
                    + struct.pack("<Q", 0))
    with open(out / "points3D.bin", "wb") as f:
        f.write(struct.pack("<Q", len(rec.points3D)))
        for pid, p in rec.points3D.items():
            f.write(struct.pack("<Q3d3BdQ", pid, *p.xyz, *(int(v) for v in p.color), p.error, 0))


def peer(binary: str, project: Project, scored: Path, work: Path, downscale: float, minutes: float,
         save_every: int) -> list[dict]:
    """OpenSplat for `minutes` of wall time; each saved splat's step, seconds and held-out scores (as `eval`
    scores project `scored`: its views, at the size it trained at)."""
    training_model(project, work)
    saved, t0 = [], time.monotonic()
    with (work / "opensplat.log").open("w") as log:
        p = subprocess.Popen([binary, str(work), "-o", str(work / "splat.ply"), "-s", str(save_every), "-n", "100000",
                              "-d", str(downscale), "--keep-crs", "--cpu"], stdout=subprocess.PIPE, stderr=log, text=True)
        for line in p.stdout:  # its "Step N: loss (x%)" lines, and a file written at every save
            log.write(line)
            m = re.match(r"Step (\d+):", line)
            if m and int(m.group(1)) % save_every == 0:
                saved.append((int(m.group(1)), time.monotonic() - t0))
            if time.monotonic() - t0 > 60 * minutes:
                p.kill()
                break
        p.wait()
    rows = []
    for step, seconds in sorted(set(saved[1::max(1, len(saved) // 6)] + saved[-1:])):
        ply = work / f"splat_{step}.ply"
        if ply.exists():
            s = splatcli(["eval", str(scored), "--model", str(ply), "--budgets", "1", "--out",
                          str(work / f"eval_{step}")], work / f"eval_{step}.log").summary
            rows.append({"steps": step, "seconds": round(seconds), "psnr": s.get("psnr"),
                         "compensated": s.get("compensated_psnr"), "gaussians": s.get("num_gaussians")})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--opensplat", required=True, help="the opensplat binary, built for the CPU")
    ap.add_argument("--scenes", default="fox,lego")
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--save-every", type=int, default=250)
    args = ap.parse_args()
    rows = []
    for scene in args.scenes.split(","):
        base = ensure_processed(scene)
        ours = fresh_copy(base, OUT / "peer_train" / scene / "ours")
        load = loadavg()
        t = splatcli(["train", str(ours)], ours.parent / "train.log").summary
        e = splatcli(["eval", str(ours), "--budgets", "1"], ours.parent / "eval.log").summary
        curve = psnr_curve(ours)
        rows += [{"scene": scene, "trainer": "splatcli", "seconds": round(s), "psnr": v}  # (held-out, as train logs it)
                 for s, v in curve[1::max(1, len(curve) // 6)]]
        rows.append({"scene": scene, "trainer": "splatcli", "steps": t["steps"], "seconds": round(t["train_seconds"]),
                     "psnr": e["psnr"], "compensated": e.get("compensated_psnr"), "gaussians": e["num_gaussians"],
                     "load": load})
        size = Project(ours).manifest()["steps"]["train"]["config"]["max_size"]  # what `train` chose
        longest = max(max(c.width, c.height) for c in pycolmap.Reconstruction(str(Project(base).sparse_dir)).cameras.values())
        rows += [{"scene": scene, "trainer": "OpenSplat", **r, "load": loadavg()} for r in
                 peer(args.opensplat, Project(base), ours, OUT / "peer_train" / scene / "opensplat", max(1.0, longest / size),
                      args.minutes, args.save_every)]
    report("peer_train", rows, ["scene", "trainer", "steps", "seconds", "psnr", "compensated", "gaussians", "load"],
           minutes=args.minutes)


if __name__ == "__main__":
    main()
