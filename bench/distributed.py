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

import argparse
import json
import os
import shlex
from pathlib import Path

from common import (
    FIGURES,
    REPO,
    SCENES,
    TOL_DB,
    ensure_processed,
    figure,
    fresh_copy,
    plot_psnr_curves,
    psnr_curve,
    save_figure,
    seconds_to,
    splatcli,
    write_section,
)

OUT = REPO / "bench" / "out" / "distributed"


def train_k(scene: str, k: int, args: list[str]) -> dict:
    proj = fresh_copy(ensure_processed(scene), OUT / scene / f"k{k}")
    cmd = ["train", str(proj), "--device", "cpu", "--nproc", str(k), *args]
    print(f"[{scene}/K={k}] {' '.join(cmd)}", flush=True)
    r = splatcli(cmd, OUT / scene / f"k{k}.log", env={**os.environ, "OMP_NUM_THREADS": "1"})
    s = r.summary
    return {"k": k, "steps": s["steps"], "train_seconds": s["train_seconds"], "final_psnr": s["psnr"],
            "num_gaussians": s["num_gaussians"], "comm_seconds": s.get("comm_seconds"),
            "wall_seconds": round(r.wall_s, 1), "curve": psnr_curve(proj), "args": args,
            "load_before": [r.load[0]], "load_after": [r.load[1]]}


def plot(scene: str, runs: list[dict], path: Path) -> bool:
    made = figure(10, 4, ncols=2)
    if made is None:
        return False
    fig, (ax, bx) = made
    plot_psnr_curves(ax, {f"{r['k']} process(es)": r["curve"] for r in runs}, f"{scene}: PSNR against training time")
    ks = [r["k"] for r in runs]
    t1 = runs[0]["train_seconds"]
    bx.plot(ks, [t1 / r["train_seconds"] for r in runs], "o-", label="measured")
    bx.plot(ks, ks, "--", color="grey", label="ideal")
    bx.set_xlabel("processes")
    bx.set_ylabel("speed-up over one process")
    bx.set_title(f"{scene}: scaling (same images seen)")
    bx.grid(alpha=0.3)
    bx.legend(fontsize=8)
    save_figure(fig, path)
    return True


def markdown(results: dict) -> str:
    lines = ["## data-parallel training", "",
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
    for scene, r in results.items():
        runs = r["runs"]
        one = runs[0]
        t_one = seconds_to(one["curve"], one["final_psnr"])
        for run in runs:
            t = seconds_to(run["curve"], one["final_psnr"])
            sp = t_one / t if t and t_one else None
            comm = f"{100 * run['comm_seconds'] / run['train_seconds']:.1f}%" if run.get("comm_seconds") else "–"
            lines.append(
                f"| {scene} | {run['k']} | `{' '.join(run['args'])}` | {run['steps']} | {run['train_seconds']:.0f} | "
                f"{run['train_seconds'] / one['train_seconds']:.2f} | {run['final_psnr']:.2f} | "
                f"{'–' if t is None else f'{t:.0f}'} | {'–' if sp is None else f'{sp:.2f}x'} | "
                f"{'–' if sp is None else format(100 * sp / run['k'], '.0f') + '%'} | {comm} | {run['num_gaussians']} | "
                f"{run['load_before'][0]} → {run['load_after'][0]} |")
        if r.get("figure"):
            lines += ["", f"![{scene}](figures/{Path(r['figure']).name})", ""]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="lego,fox")
    ap.add_argument("--nprocs", default="1,2")
    ap.add_argument("--train-args", default="--preset fast")
    ap.add_argument("--iterations", default="lego=2000,fox=1000", help="per scene, in views seen")
    ap.add_argument("--eval-every", type=int, default=250)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    iters = dict(kv.split("=") for kv in args.iterations.split(",") if kv)
    path = OUT / "results.json"
    results = json.loads(path.read_text()) if path.exists() else {}
    for scene in [s for s in args.scenes.split(",") if s]:
        common = shlex.split(args.train_args) + [*SCENES[scene][2], "--eval-every", str(args.eval_every)]
        if scene in iters:
            common += ["--iterations", iters[scene]]
        runs = [train_k(scene, int(k), common) for k in args.nprocs.split(",")]
        fig = FIGURES / f"distributed_{scene}.png"
        results[scene] = {"runs": runs, "figure": str(fig) if plot(scene, runs, fig) else None}
        path.write_text(json.dumps(results, indent=1))
    text = markdown(results)
    if not args.no_write:
        write_section("## data-parallel training", text)
    print(text)


if __name__ == "__main__":
    main()
