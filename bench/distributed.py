"""Data-parallel training (`train --nproc K`), side by side with one process, in one run.

    .venv/bin/python bench/distributed.py [--scenes lego,fox] [--nprocs 1,2] [--train-args "--preset fast"]
                                          [--iterations lego=2000,fox=1000] [--eval-every 250] [--no-write]

For each scene (processed once, as bench/train.py does) it trains the same schedule
with K = 1, 2, ... processes, one after the other on the same machine, one torch thread
per process. Each run sees the same number of images (steps count views seen). It
reports training seconds, the final held-out PSNR, the seconds to reach the
one-process run's final PSNR (within 0.1 dB), the speed-up and parallel efficiency
against K = 1, and the share of rank 0's training time spent in collectives
(exchanging gradients and waiting for the slower rank). Results go to
bench/out/distributed/results.json, docs/figures/distributed_<scene>.png and the
"## data-parallel training" section of docs/benchmarks.md, with the load average
before and after each run.
"""

from __future__ import annotations

import os
from pathlib import Path

from common import REPO, TOL_DB, fmt, load_span, psnr_figure, scene_benchmark, scene_parser, train_fresh

OUT = REPO / "bench" / "out" / "distributed"


def train_k(scene: str, k: int, args: list[str]) -> dict:
    return train_fresh(scene, OUT / scene / f"k{k}", ["--nproc", str(k), *args],
                       env={**os.environ, "OMP_NUM_THREADS": "1"}, k=k, args=args)


def plot(scene: str, runs: list[dict], path: Path) -> bool:
    def scaling(bx) -> None:
        ks = [r["k"] for r in runs]
        t1 = runs[0]["train_seconds"]
        bx.plot(ks, [t1 / r["train_seconds"] for r in runs], "o-", label="measured")
        bx.plot(ks, ks, "--", color="grey", label="ideal")
        bx.set_xlabel("processes")
        bx.set_ylabel("speed-up over one process")
        bx.set_title(f"{scene}: scaling (same images seen)")
        bx.grid(alpha=0.3)
        bx.legend(fontsize=8)

    return psnr_figure(path, scene, {f"{r['k']} process(es)": r["curve"] for r in runs}, scaling)


HEAD = ["## data-parallel training", "",
       "Measured by `python bench/distributed.py`: the same scene and schedule trained with K processes "
       "(`train --nproc K`, one torch thread each), one after the other in one run. Every run sees the same "
       "number of images; K processes take 1/K of the steps with K views each (docs/guide.md, \"Many "
       "processes\"). *train s* is rank 0's training time (evaluation excluded); *to 1-proc PSNR* is the "
       f"first held-out evaluation within {TOL_DB} dB of the one-process run's final PSNR; *comm* is the "
       "share of rank 0's training time spent in collectives (exchanging gradients, and waiting for the "
       "slower rank).", "",
       "| scene | K | arguments | views seen | train s | time vs K=1 | final PSNR | s to 1-proc PSNR | "
       "speed-up | efficiency | comm | Gaussians | load before → after |",
       "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]


def row(scene: str, run: dict, one: dict, t: float | None, sp: float | None) -> str:
    comm = f"{100 * run['comm_seconds'] / run['train_seconds']:.1f}%" if run.get("comm_seconds") else "–"
    return (f"| {scene} | {run['k']} | `{' '.join(run['args'])}` | {run['steps']} | {run['train_seconds']:.0f} | "
            f"{run['train_seconds'] / one['train_seconds']:.2f} | {run['final_psnr']:.2f} | "
            f"{fmt(t, '.0f')} | {'–' if sp is None else f'{sp:.2f}x'} | "
            f"{'–' if sp is None else format(100 * sp / run['k'], '.0f') + '%'} | {comm} | {run['num_gaussians']} | "
            f"{load_span(run)} |")


def main() -> None:
    ap = scene_parser(__doc__, "lego,fox", "--preset fast")
    ap.add_argument("--nprocs", default="1,2")
    ap.add_argument("--iterations", default="lego=2000,fox=1000", help="per scene, in views seen")
    args = ap.parse_args()
    iters = dict(kv.split("=") for kv in args.iterations.split(",") if kv)

    def each_k(scene: str, common: list[str]) -> list[dict]:
        common = common + (["--iterations", iters[scene]] if scene in iters else [])
        return [train_k(scene, int(k), common) for k in args.nprocs.split(",")]

    scene_benchmark(args, OUT, "distributed", each_k, plot, HEAD, row)


if __name__ == "__main__":
    main()
