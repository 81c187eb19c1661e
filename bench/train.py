"""Training benchmark: speed against held-out error on real scenes, time to quality, and what
--compact, --max-gaussians and --time-budget cost.

    .venv/bin/python bench/train.py [--scenes lego,fox,fox-photos,sample] [--variants default,compact,budget]
                                    [--preset fast] [--iterations N] [--threads N] [--resume]

For each scene it processes the data once (bench/out/train/<scene>/base), then
runs `splatcli train` as a subprocess per variant on a copy of that project:

  default   the preset as is
  compact   + --compact (resumes a copy of the default run: only the prune and fine-tune cost)
  budget    + --max-gaussians (a third of the default run's final count)
  time      + --time-budget (lego 90 s, fox 300 s, sample 60 s: docs/benchmarks.md, "Time budgets")
  plain     `splatcli train PROJECT` and nothing else, as a new user runs it

and records steps/s, held-out PSNR/SSIM at 1k, 3k and 7k steps, the training
seconds to reach 30 dB, wall time, peak RSS (sampled every 0.5 s from /proc),
the RSS the run logged at each log line (memory must stay flat once densification
stops), the final Gaussian count and .ply size, and the load average before and
after. Results: bench/out/train.json (common.report), the table printed.

Scenes (../shared/data, or $SPLATCLI_DATA):
  lego    NeRF synthetic, trained at 200x200 on a white background, every 8th image held out
  fox     instant-ngp's fox, 50 photos, trained at ~270x480
  fox-photos  the same photos without their poses (structure from motion at 400 px), trained at ~270x480
  sample  sample_data/scene (what `make demo` uses), --preset demo
"""

from __future__ import annotations

import argparse
import json
import os
import shutil

from common import OUT as ALL_OUT, PROCESSED as OUT, SCENES, ensure_processed, fresh_copy, report, splatcli
from splatcli.eval.curve import read_log
from splatcli.project import Project

MILESTONES = (1000, 3000, 7000)
TARGET_DB = 30.0
TIME_BUDGETS = {"lego": 90, "fox": 300, "fox-photos": 300, "sample": 60}  # seconds, for the `time` variant


def train_variant(scene: str, variant: str, extra: list[str], preset: str, iterations: int | None,
                  resume: bool = False) -> dict:
    """One `splatcli train` run of `scene` (bench/out/train/<scene>/<variant>): what the table keeps of it."""
    proj = OUT / scene / variant
    _, _, targs, scene_preset = SCENES[scene]
    preset = scene_preset or preset
    if resume and Project(proj).latest_checkpoint() is not None:
        # An interrupted run continues from its last checkpoint (bitwise what an uninterrupted run
        # gives); its training seconds count from step 0, its wall time and peak RSS the resumed part.
        args = ["train", str(proj), "--resume", "--device", "cpu"]
    elif variant == "compact":  # bitwise what a --compact run from scratch gives (tests/test_train.py)
        src = OUT / scene / "default"
        if not Project(src).checkpoints_dir.is_dir():
            raise SystemExit(f"[{scene}/compact] needs the default run first ({src})")
        if proj.exists():
            shutil.rmtree(proj)
        shutil.copytree(src, proj)
        args = ["train", str(proj), "--resume", "--compact", "--device", "cpu"]
    elif variant == "plain":
        args = ["train", str(fresh_copy(ensure_processed(scene), proj))]
    else:
        fresh_copy(ensure_processed(scene), proj)
        args = ["train", str(proj), "--preset", preset, "--device", "cpu", "--eval-every", "1000", *targs, *extra]
        if iterations:
            args += ["--iterations", str(iterations)]
    print(f"[{scene}/{variant}] splatcli {' '.join(args)}", flush=True)
    r = splatcli(args, OUT / scene / f"{variant}.log")
    s = r.summary
    log = read_log(Project(proj).train_log_path)
    evals = {x["step"]: x for x in log if "psnr" in x}
    hit = next((x for x in log if x.get("psnr", 0) >= TARGET_DB), None)
    row = {"scene": scene, "variant": variant, "args": " ".join(args[2:]), "steps": s["steps"],
           "steps_per_s": s["steps"] / max(s["train_seconds"], 1e-9), "resumed_from": s.get("resumed_from")}
    for m in MILESTONES:
        row[f"psnr {m}"], row[f"ssim {m}"] = (evals[m]["psnr"], evals[m]["ssim"]) if m in evals else (None, None)
    row.update({"final_psnr": s["psnr"], "final_ssim": s["ssim"], "s_to_30db": hit["elapsed_s"] if hit else None,
                "train_s": s["train_seconds"], "wall_s": round(r.wall_s, 1), "peak_rss_mb": r.peak_mb,
                "gaussians": s["num_gaussians"], "ply_mb": s["ply_bytes"] / 1e6, "processes": s.get("nproc"),
                "load_before": r.load[0], "load_after": r.load[1], "compact": s.get("compact"),
                "chosen": s.get("chosen"), "rss_by_step": [(x["step"], x["rss_mb"]) for x in log if "rss_mb" in x],
                "rss_samples": r.rss[:: max(1, len(r.rss) // 200)]})
    print(f"[{scene}/{variant}] {row['steps']} steps, {row['steps_per_s']:.2f} steps/s, PSNR {row['final_psnr']}, "
          f"{row['gaussians']} Gaussians, peak RSS {r.peak_mb} MB", flush=True)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="lego,fox,sample")
    ap.add_argument("--variants", default="default,compact,budget")
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--iterations", type=int, default=None)
    ap.add_argument("--threads", type=int, default=None,
                    help="OMP_NUM_THREADS for the runs (1 when the cores are shared: OpenMP spin-waits collapse "
                         "under oversubscription)")
    ap.add_argument("--resume", action="store_true",
                    help="continue a variant whose run was interrupted, from its last checkpoint")
    args = ap.parse_args()
    if args.threads:
        os.environ["OMP_NUM_THREADS"] = str(args.threads)
    last = ALL_OUT / "train.json"  # the previous run's default counts, for a budget run on its own
    rows, earlier = [], json.loads(last.read_text())["rows"] if last.is_file() else []
    for scene in [x for x in args.scenes.split(",") if x]:
        for variant in [x for x in args.variants.split(",") if x]:
            if scene == "sample" and variant not in ("default", "time", "plain"):
                continue
            extra = {"time": ["--time-budget", str(TIME_BUDGETS[scene])]}.get(variant, [])
            if variant == "budget":
                prev = [r for r in earlier + rows if r["scene"] == scene and r["variant"] == "default"]
                if not prev:
                    print(f"[{scene}/budget] skipped: needs the default run's count", flush=True)
                    continue
                extra = ["--max-gaussians", str(max(1, prev[-1]["gaussians"] // 3))]
            rows.append(train_variant(scene, variant, extra, args.preset, args.iterations, args.resume))
    report("train", rows, preset=args.preset, threads=os.environ.get("OMP_NUM_THREADS"))


if __name__ == "__main__":
    main()
