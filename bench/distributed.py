"""Data-parallel training (`train --nproc K`), side by side with one process, in one run.

    .venv/bin/python bench/distributed.py [--scenes lego,fox] [--nprocs 1,2] [--train-args "--preset fast"]
                                          [--iterations lego=2000,fox=1000] [--eval-every 250]
    .venv/bin/python bench/distributed.py --exchange 18000,58000 [--reps 40]

For each scene (processed once, as bench/train.py does) it trains the same schedule
with K = 1, 2, ... processes, one after the other on the same machine, one torch thread
per process. Each run sees the same number of images (steps count views seen;
docs/guide.md, "Many processes"). It reports rank 0's training seconds, the final
held-out PSNR, the seconds to reach the one-process run's final PSNR (the first held-out
evaluation within 0.1 dB of it), the speed-up and parallel efficiency against K = 1, the
share of rank 0's training time spent in collectives (exchanging gradients and waiting
for the slower rank), the held-out curve, and the load average before and after each
run. Results: bench/out/distributed.json (common.report), the table printed.

--exchange N,...: the gradient exchange alone (`Comm.reduce_step`) of a model of N Gaussians
(SH degree 3), in two ranks on this machine, through gloo's all-reduce and through shared
memory, taking turns; medians and quartiles of the slower rank in ms (bench/out/exchange.json).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import shlex
import statistics
import tempfile
import time
from pathlib import Path

import torch
import torch.distributed as dist
import torch.multiprocessing as mp

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


def _exchange_rank(rank: int, tmp: str, sizes: list[int], reps: int) -> None:
    from splatcli.train.distributed import Comm

    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{tmp}/store", rank=rank, world_size=2)
    comms = {"gloo": Comm(rank=rank, world=2), "shared memory": Comm(rank=rank, world=2, shared=True)}
    rows = []
    for n in sizes:  # a model of n Gaussians: means, quats, scales, opacity, SH (degree 3)
        params = [torch.nn.Parameter(torch.randn(n, k)) for k in (3, 4, 3, 1, 3, 45)]
        times = {k: [] for k in comms}
        for _, (name, comm) in itertools.product(range(reps), comms.items()):  # taking turns
            for p in params:
                p.grad = torch.randn_like(p)
            dist.barrier()
            t = time.perf_counter()
            comm.reduce_step(dict(enumerate(params)), torch.tensor(1.0), False)
            dt = torch.tensor([time.perf_counter() - t])
            dist.all_reduce(dt, op=dist.ReduceOp.MAX)  # the slower rank's
            times[name].append(1e3 * float(dt))
        rows += [{"gaussians": n, "exchange": k, "median_ms": statistics.median(ts),
                  "q1_ms": statistics.quantiles(ts, n=4)[0], "q3_ms": statistics.quantiles(ts, n=4)[2]}
                 for k, ts in times.items()]
    if rank == 0:
        Path(tmp, "rows.json").write_text(json.dumps(rows))
    dist.destroy_process_group()


def exchange(sizes: list[int], reps: int) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        mp.spawn(_exchange_rank, args=(tmp, sizes, reps), nprocs=2, join=True)
        report("exchange", json.loads(Path(tmp, "rows.json").read_text()), reps=reps)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="lego,fox", help="comma-separated (bench/common.py SCENES)")
    ap.add_argument("--train-args", default="--preset fast", help="train's arguments (each scene adds its own)")
    ap.add_argument("--eval-every", type=int, default=250)
    ap.add_argument("--nprocs", default="1,2")
    ap.add_argument("--iterations", default="lego=2000,fox=1000", help="per scene, in views seen")
    ap.add_argument("--exchange", default="", help="Gaussian counts: time the gradient exchange alone")
    ap.add_argument("--reps", type=int, default=40)
    args = ap.parse_args()
    if args.exchange:
        return exchange([int(n) for n in args.exchange.split(",")], args.reps)
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
