"""`--mask-mode ignore` against unmasked training on a scene with a moving distractor.

    .venv/bin/python bench/masks.py [--views 28] [--width 320] [--height 240] [--preset demo]
                                    [--iterations N] [--threads 1] [--no-write]

Renders the sample scene with `make_scene.py --distractor` (a ball rolling across the
floor while the photographs are taken, so each view sees it somewhere else; masks in
masks/NNN.jpg.png; the held-out views, every 8th, never show it), processes it once (the
masks keep SIFT off the ball, so both runs share the same poses and points), then trains two copies with the
same schedule, one after the other in this run: `--mask-mode ignore` and `--mask-mode
off`. Reports held-out PSNR/SSIM of both and the gain into bench/out/masks/results.json
and the "## masks" section of docs/benchmarks.md (issue 15's target: at least 2 dB).
Smoke run: --views 12 --width 160 --height 120 --iterations 100 --no-write.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import time

from common import REPO, loadavg, make_scene, publish, splatcli

OUT = REPO / "bench" / "out" / "masks"
HEADING = "## masks"
TARGET_DB = 2.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--views", type=int, default=28)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--preset", default="demo")
    ap.add_argument("--iterations", type=int, default=None, help="default: the preset's")
    ap.add_argument("--threads", type=int, default=1, help="torch threads per training run")
    ap.add_argument("--no-write", action="store_true", help="print the section, leave docs/benchmarks.md alone")
    args = ap.parse_args()

    env = {**os.environ, "OMP_NUM_THREADS": str(args.threads)}
    OUT.mkdir(parents=True, exist_ok=True)
    scene = OUT / "scene"
    shutil.rmtree(scene, ignore_errors=True)
    t0 = time.perf_counter()
    make_scene().render_scene(scene, num_views=args.views, width=args.width, height=args.height, distractor=True)
    moved = json.loads((scene / "ground_truth.json").read_text())["distractor_views"]
    print(f"rendered {args.views} views ({len(moved)} with the distractor) in {time.perf_counter() - t0:.0f} s",
          flush=True)
    base = OUT / "base"
    p = splatcli(["process", str(scene), "-o", str(base), "--overwrite"], OUT / "process.log", env=env).summary
    print(f"processed: {p['registered']}/{p['total']} registered, masks from {p['mask_source']}", flush=True)

    rows = []
    for mode in ("ignore", "off"):
        proj = OUT / mode
        shutil.rmtree(proj, ignore_errors=True)
        shutil.copytree(base, proj)
        cmd = ["train", str(proj), "--preset", args.preset, "--device", "cpu", "--mask-mode", mode]
        if args.iterations:
            cmd += ["--iterations", str(args.iterations)]
        load0 = loadavg()
        print(f"[{mode}] splatcli {' '.join(cmd)}", flush=True)
        s = splatcli(cmd, OUT / f"{mode}.log", env=env).summary
        rows.append({"mode": mode, "psnr": s["psnr"], "ssim": s["ssim"], "steps": s["steps"],
                     "train_seconds": s["train_seconds"], "num_gaussians": s["num_gaussians"],
                     "mask_mode": s["mask_mode"], "load": [load0, loadavg()]})
        print(f"[{mode}] held-out PSNR {s['psnr']:.2f} dB in {s['train_seconds']:.0f} s", flush=True)
    gain = rows[0]["psnr"] - rows[1]["psnr"]
    result = {"views": args.views, "width": args.width, "height": args.height, "distractor_views": len(moved),
              "test_views": p["test"], "preset": args.preset, "iterations": args.iterations, "threads": args.threads,
              "runs": rows, "gain_db": gain, "target_db": TARGET_DB}
    (OUT / "results.json").write_text(json.dumps(result, indent=1))

    lines = [HEADING, "",
             f"Measured by `python bench/masks.py`: the sample scene rendered by `make_scene.py --distractor` "
             f"({args.views} views at {args.width}x{args.height}; a violet ball rolls across the floor in front of the "
             f"objects while the photographs are taken and shows in {len(moved)} of them, with its masks; the "
             f"{p['test']} held-out views never show it), processed once (the masks keep SIFT off the ball), then "
             f"trained with `--preset "
             f"{args.preset}`" + (f" cut to {args.iterations} steps" if args.iterations else "")
             + f" twice, one after the other in one run ({args.threads} torch thread): masked pixels ignored, "
             "and masks off (the distractor fitted like the scene).", "",
             "| --mask-mode | steps | train s | held-out PSNR / SSIM | Gaussians | load |",
             "| --- | ---: | ---: | --- | ---: | --- |"]
    for r in rows:
        lines.append(f"| {r['mode']} | {r['steps']} | {r['train_seconds']:.0f} | {r['psnr']:.2f} / {r['ssim']:.4f} "
                     f"| {r['num_gaussians']:,} | {r['load'][0]} → {r['load'][1]} |")
    verdict = "met" if gain >= TARGET_DB else "not met"
    lines += ["", f"Gain of `--mask-mode ignore`: **{gain:+.2f} dB** held-out PSNR (issue 15's target, at least "
              f"+{TARGET_DB:.0f} dB: {verdict}).", ""]
    publish(HEADING, "\n".join(lines), write=not args.no_write)


if __name__ == "__main__":
    main()
