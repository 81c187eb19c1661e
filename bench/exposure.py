"""`train --appearance exposure` against plain training, on the same project in one run.

    .venv/bin/python bench/exposure.py [--scenes sample,lego,fox] [--iterations N] [--per-channel]
                                       [--spread 0.3] [--seed 0] [--no-write]

For each scene: copy its processed project (bench/train.py's, bench/out/train/<scene>/base;
never written to) into bench/out/exposure/<scene>/. On the scenes named by --gained
(default: sample) every TRAINING photo is multiplied by a seeded random gain drawn
uniformly from [1 - spread, 1 + spread] (one per photo; --per-channel: one per colour
channel, a white-balance error too) and clipped to 0..255; held-out photos (the
project's test split, every 8th image) keep gain 1. The other scenes (lego, fox) are
trained as they are, to measure what the option costs when exposure does not vary.
Each scene then trains twice from copies of that one project, one after the other, on
bench/train.py's schedule for it (sample: --preset demo; lego, fox: --preset fast and
their --max-size), without and with --appearance exposure, and `splatcli eval` scores
both: held-out PSNR as rendered, and after the per-view colour fit. For a gained scene
it also reports how well the learnt transforms' gains on grey (the mean row sum of each
3x3 matrix: a gain can sit on the off-diagonal too, since colour channels correlate) follow
the true gains.
Results are merged into bench/out/exposure/results.json (each scene's last run; so
`--scenes sample` and `--scenes lego,fox --iterations 2000` may run apart) and all of
them written to the "## exposure" section of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
from pathlib import Path

import numpy as np

from common import REPO, SCENES, ensure_processed, fresh_copy, loadavg, publish, splatcli
from splatcli.io.checkpoint import load_checkpoint
from splatcli.project import Project

OUT = REPO / "bench" / "out" / "exposure"


def gained_copy(scene: str, dest: Path, spread: float, per_channel: bool, seed: int,
                gained: bool) -> dict[str, list[float]]:
    """`dest` = the scene's processed project without training outputs, its training photos
    multiplied by seeded gains when `gained`; returns each training photo's gains."""
    fresh_copy(ensure_processed(scene), dest)
    if not gained:
        return {}
    import cv2

    names = json.loads((dest / "splatcli.json").read_text())["splits"]["train"]
    rng = np.random.default_rng(seed)
    gains = {}
    for name in names:
        g = rng.uniform(1 - spread, 1 + spread, size=3 if per_channel else 1) * np.ones(3)
        path = dest / "images" / name
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        rgb = img[..., :3].astype(np.float64) * g[::-1]  # OpenCV's BGR order
        img[..., :3] = np.clip(np.round(rgb), 0, 255).astype(img.dtype)
        params = [cv2.IMWRITE_JPEG_QUALITY, 95] if path.suffix.lower() in (".jpg", ".jpeg") else []
        if not cv2.imwrite(str(path), img, params):
            raise SystemExit(f"{path}: could not write")
        gains[name] = [round(float(x), 4) for x in g]
    return gains


def train_and_eval(scene: str, src: Path, appearance: str, iterations: int | None) -> dict:
    proj = src.parent / appearance
    if proj.exists():
        shutil.rmtree(proj)
    shutil.copytree(src, proj)
    _, _, targs, preset = SCENES[scene]
    cmd = ["train", str(proj), "--preset", preset or "fast", "--device", "cpu", "--eval-every", "0", "--appearance",
           appearance, *targs]
    if iterations:
        cmd += ["--iterations", str(iterations)]
    load0 = loadavg()
    print(f"[{scene}/{appearance}] splatcli {' '.join(cmd)}", flush=True)
    tr = splatcli(cmd, src.parent / f"{appearance}.train.log")
    t, peak_mb = tr.summary, tr.peak_mb
    e = splatcli(["eval", str(proj), "--budgets", "1", "--no-plots", "--device", "cpu"],
                 src.parent / f"{appearance}.eval.log").summary
    r = {"scene": scene, "appearance": appearance, "steps": t["steps"], "train_seconds": t["train_seconds"],
         "num_gaussians": t["num_gaussians"], "psnr": e["psnr"], "ssim": e["ssim"], "psnr_color_fit": e["psnr_color_fit"],
         "peak_rss_mb": peak_mb, "load": [load0, loadavg()], "project": str(proj)}
    print(f"[{scene}/{appearance}] PSNR {r['psnr']:.2f} dB, after colour fit {r['psnr_color_fit']:.2f} dB, "
          f"{r['train_seconds']:.0f} s", flush=True)
    return r


def learnt_gains(project: Path) -> list[float]:
    """Each training photo's learnt transform as a gain: its mean row sum (what it does to grey)."""
    t = load_checkpoint(Project.open(project).latest_checkpoint()).appearance["transforms"]
    return t[:, :, :3].sum(2).mean(1).tolist()


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", default="sample,lego,fox")
    ap.add_argument("--gained", default="sample", help="scenes whose training photos get random gains")
    ap.add_argument("--iterations", type=int, default=None, help="default: each scene's preset")
    ap.add_argument("--spread", type=float, default=0.3, help="gains are uniform in [1 - spread, 1 + spread]")
    ap.add_argument("--per-channel", action="store_true", help="one gain per colour channel (default: one per photo)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", default="1", help="OMP_NUM_THREADS of the training runs")
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    os.environ["OMP_NUM_THREADS"] = args.threads
    gained = {s for s in args.gained.split(",") if s}
    rows = []
    for scene in [s for s in args.scenes.split(",") if s]:
        src = OUT / scene / "photos"
        gains = gained_copy(scene, src, args.spread, args.per_channel, args.seed, scene in gained)
        photos = (f"gains in [{1 - args.spread:.2f}, {1 + args.spread:.2f}], "
                  f"{'per channel' if args.per_channel else 'per photo'}, seed {args.seed}") if gains else "as taken"
        pair = [train_and_eval(scene, src, a, args.iterations) for a in ("none", "exposure")]
        for r in pair:
            r.update(photos=photos, gains=gains)
        if gains:
            true = np.array([np.mean(g) for g in gains.values()])
            learnt = np.array(learnt_gains(Path(pair[1]["project"])))
            pair[1]["gain_corr"] = float(np.corrcoef(true, learnt)[0, 1])
            pair[1]["gain_mae"] = float(np.abs(true - learnt).mean())
        rows += pair
    # Runs of other scenes stay (the sample scene and the real ones can be measured apart).
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / "results.json"
    done = {r["scene"] for r in rows}
    old = [r for r in (json.loads(path.read_text()).get("rows", []) if path.exists() else []) if r["scene"] not in done]
    rows = old + rows
    path.write_text(json.dumps({"rows": rows}, indent=1))

    lines = ["## exposure", "",
             "Measured by `python bench/exposure.py` (bench/out/exposure/results.json keeps each scene's last run): on "
             "a gained scene every training photo is multiplied by a seeded random gain (clipped to 0..255), held-out "
             "photos untouched; the other scenes are as taken. Each scene trained twice from one copy of its project, "
             "one after the other on this machine (one torch thread), on bench/train.py's schedule (sample: demo; "
             "lego, fox: fast) or the steps shown, without and with `--appearance exposure`; held-out PSNR from "
             "`splatcli eval`, as rendered (the identity transform) and after each view's least-squares colour fit. "
             "*Learnt gains*: the correlation of each training photo's true gain with its transform's gain on grey "
             "(the mean row sum of its matrix), and their mean absolute difference.",
             "", "| scene | photos | --appearance | steps | train s | held-out PSNR / SSIM | after colour fit | "
             "gain (dB) | learnt gains | load |",
             "| --- | --- | --- | ---: | ---: | --- | ---: | ---: | --- | --- |"]
    for r in rows:
        base = next(x for x in rows if x["scene"] == r["scene"] and x["appearance"] == "none")
        d = f"{r['psnr'] - base['psnr']:+.2f}" if r["appearance"] == "exposure" else "–"
        fit = f"r = {r['gain_corr']:.3f}, {r['gain_mae']:.3f}" if "gain_corr" in r else "–"
        lines.append(f"| {r['scene']} | {r['photos']} | {r['appearance']} | {r['steps']} | {r['train_seconds']:.0f} | "
                     f"{r['psnr']:.2f} / {r['ssim']:.4f} | {r['psnr_color_fit']:.2f} | {d} | {fit} | "
                     f"{r['load'][0]} → {r['load'][1]} |")
    publish("## exposure", "\n".join(lines) + "\n", write=not args.no_write)


if __name__ == "__main__":
    main()
