"""Data-parallel training (`train --nproc K`), side by side with one process, in one run.

    .venv/bin/python bench/distributed.py [--scenes lego,fox] [--nprocs 1,2] [--train-args "--preset fast"]
                                          [--iterations lego=2000,fox=1000] [--eval-every 250]

For each scene (processed once, as bench/train.py does) it trains the same schedule
with K = 1, 2, ... processes, one after the other on the same machine, one torch thread
per process. Each run sees the same number of images (steps count views seen;
docs/guide.md, "Many processes"). It reports rank 0's training seconds, the final
held-out PSNR, the seconds to reach the one-process run's final PSNR (the first held-out
evaluation within 0.1 dB of it), the speed-up and parallel efficiency against K = 1, the
share of rank 0's training time spent in collectives (exchanging gradients and waiting
for the slower rank), the held-out curve, and the load average before and after each
run. Results: bench/out/distributed.json (common.report), the table printed.
"""

from __future__ import annotations

import argparse
import os
import shlex

from common import OUT, SCENES, ensure_processed, fresh_copy, psnr_curve, report, splatcli

TOL_DB = 0.1  # "reached" a PSNR: the first held-out evaluation within this of it


def train_k(scene: str, k: int, args: list[str]) -> dict:
    """`train --nproc k ARGS` on a fresh copy of the processed scene: what the table keeps of it."""
    proj = fresh_copy(ensure_processed(scene), OUT / "distributed" / scene / f"k{k}")
    cmd = ["train", str(proj), "--device", "cpu", "--nproc", str(k), *args]
    print(f"[{scene}/k{k}] splatcli {' '.join(cmd)}", flush=True)
    r = splatcli(cmd, proj.parent / f"k{k}.log", env={**os.environ, "OMP_NUM_THREADS": "1"})
    s = r.summary
    return {"scene": scene, "k": k, "args": " ".join(args), "views_seen": s["steps"], "train_s": s["train_seconds"],
            "final_psnr": s["psnr"],
            "comm_share": s["comm_seconds"] / s["train_seconds"] if s.get("comm_seconds") else None,
            "gaussians": s["num_gaussians"], "load_before": r.load[0], "load_after": r.load[1],
            "curve": psnr_curve(proj)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="lego,fox", help="comma-separated (bench/common.py SCENES)")
    ap.add_argument("--train-args", default="--preset fast", help="train's arguments (each scene adds its own)")
    ap.add_argument("--eval-every", type=int, default=250)
    ap.add_argument("--nprocs", default="1,2")
    ap.add_argument("--iterations", default="lego=2000,fox=1000", help="per scene, in views seen")
    args = ap.parse_args()
    iters = dict(kv.split("=") for kv in args.iterations.split(",") if kv)
    rows = []
    for scene in [s for s in args.scenes.split(",") if s]:
        common = shlex.split(args.train_args) + [*SCENES[scene][2], "--eval-every", str(args.eval_every)]
        common += ["--iterations", iters[scene]] if scene in iters else []
        runs = [train_k(scene, int(k), common) for k in args.nprocs.split(",")]
        one = runs[0]
        to = [next((t for t, p in r["curve"] if p >= one["final_psnr"] - TOL_DB), None) for r in runs]
        for r, t in zip(runs, to):
            sp = to[0] / t if t and to[0] else None
            r.update({"time_vs_k1": r["train_s"] / one["train_s"], "s_to_1proc_psnr": t, "speedup": sp,
                      "efficiency": sp / r["k"] if sp else None})
        rows += runs
    report("distributed", rows, nprocs=args.nprocs, iterations=iters)


if __name__ == "__main__":
    main()
