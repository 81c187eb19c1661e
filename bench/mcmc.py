"""`--strategy mcmc` against the default strategy at the same `--max-gaussians`, one after the other.

    .venv/bin/python bench/mcmc.py [--scenes lego,fox] [--iterations 3000] [--no-write]

The budget is a third of the default run's final count (bench/out/train/results.json, else
--counts), as bench/train.py's "budget" variant and issue 15 set it. Each scene trains the preset
(`fast`) with `--max-gaussians B`, then with `--strategy mcmc --max-gaussians B`, and
reports held-out PSNR/SSIM, training seconds and the final count. Results go to
bench/out/train/mcmc.json and the "## MCMC at one budget" section of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import time

from common import loadavg, publish
from train import OUT, train_variant


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", default="lego,fox")
    ap.add_argument("--iterations", type=int, default=None, help="default: the preset's")
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--counts", default="lego=88657,fox=159631,sample=20000",
                    help="the default run's final count per scene, where bench/out/train/results.json has none "
                         "(these: docs/benchmarks.md, \"train\", fast preset; the demo preset's own budget)")
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    path = OUT / "results.json"
    prev = json.loads(path.read_text())["results"] if path.exists() else []
    counts = {k: int(v) for k, v in (kv.split("=") for kv in args.counts.split(",") if kv)}
    scenes = [s for s in args.scenes.split(",") if s]
    kept = OUT / "mcmc.json"  # each scene's last pair: a run of some scenes keeps the others'
    rows = [r for r in (json.loads(kept.read_text()) if kept.exists() else []) if r["scene"] not in scenes]
    for scene in scenes:
        runs = [r for r in prev if r["scene"] == scene and r["variant"] == "default"]
        full = {"num_gaussians": runs[-1]["num_gaussians"] if runs else counts[scene]}
        budget = max(1, full["num_gaussians"] // 3)
        for variant, extra in (("budget", []), ("mcmc", ["--strategy", "mcmc"])):
            load0 = loadavg()
            r = train_variant(scene, variant, ["--max-gaussians", str(budget), *extra], args.preset, args.iterations, 1)
            r.update(date=time.strftime("%Y-%m-%d"), budget=budget, default_count=full["num_gaussians"],
                     load=[load0, loadavg()])
            rows.append(r)
    kept.write_text(json.dumps(rows, indent=1))
    lines = ["## MCMC at one budget", "",
             "Measured by `python bench/mcmc.py`: each scene's preset (bench/train.py: `fast`, the sample scene `demo`)"
             + " with `--max-gaussians` a third of the default run's final count, once with the default strategy "
             "and once with `--strategy mcmc`, one after the other on this machine (one torch thread).", "",
             "| date | scene | strategy | budget (default run's count) | steps | train s | held-out PSNR / SSIM | Gaussians | load |",
             "| --- | --- | --- | --- | ---: | ---: | --- | ---: | --- |"]
    for r in rows:
        lines.append(f"| {r.get('date', '')} | {r['scene']} | {'mcmc' if r['variant'] == 'mcmc' else 'default'} | {r['budget']:,} "
                     f"({r['default_count']:,}) | {r['steps']} | {r['train_seconds']:.0f} | "
                     f"{r['final_psnr']:.2f} / {r['final_ssim']:.4f} | {r['num_gaussians']:,} | "
                     f"{r['load'][0]} → {r['load'][1]} |")
    publish("## MCMC at one budget", "\n".join(lines) + "\n", write=not args.no_write)


if __name__ == "__main__":
    main()
