"""The rasterizer of this checkout against another commit's, forward and backward, in one run.

    .venv/bin/python bench/commits.py --base DIR [--only NAME,...] [--reps 5] [--no-write]

DIR holds the other commit's files (`git worktree add DIR COMMIT`, or `git archive COMMIT | tar -x -C DIR`).
Each side renders bench/scenes.py's workloads (as bench/peers.py: rasterize(), the image summed,
backward) in its own processes, one torch thread; per workload the sides take turns, --rounds
processes each, every process timing --reps runs after a warm-up: the base, this checkout eager,
this checkout with its compiled planner (`--compile on`; the first call, which compiles or loads
the kernels, is timed apart).
Results go to the "## Against an earlier commit" section of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

from common import REPO, loadavg, publish

HEADING = "## Against an earlier commit"


def child(name: str, reps: int, mode: str) -> dict:
    import time

    import torch

    from scenes import workloads
    from splatcli.render import rasterize

    torch.set_num_threads(1)
    if mode != "base":
        from splatcli.render import kernels

        kernels.set_mode(mode)
    wl = workloads([name])[0]

    def step() -> float:
        a = [t.detach().clone().requires_grad_(i < 5) for i, t in enumerate(wl.args)]
        t = time.perf_counter()
        rasterize(*a, wl.width, wl.height).image.sum().backward()
        return time.perf_counter() - t

    first = step()
    return {"times": [step() for _ in range(reps)], "first_s": first}


def _summary(runs: list[dict]) -> dict:
    import statistics

    t = [1e3 * x for r in runs for x in r["times"]]
    return {"ms": statistics.median(t), "lo": min(t), "hi": max(t), "first_s": runs[0]["first_s"]}


def run_side(tree: Path, name: str, reps: int, mode: str) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=os.pathsep.join([str(tree), str(REPO / "bench")]))
    out = subprocess.run([sys.executable, __file__, "--child", name, "--reps", str(reps), "--mode", mode], env=env,
                         cwd=tree, check=True, capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--base", help="the other commit's files")
    ap.add_argument("--only", default="synth-10k-256,synth-100k-256,synth-100k-800x600,garden-648x420")
    ap.add_argument("--reps", type=int, default=3, help="timed runs per process, after a warm-up")
    ap.add_argument("--rounds", type=int, default=3, help="processes per side, taking turns")
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--mode", default="off", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args.child, args.reps, args.mode)))
        return
    from splatcli.device import cpu_name

    base = Path(args.base).resolve()
    rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=base, capture_output=True, text=True).stdout.strip()
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True).stdout.strip()
    load0, rows = loadavg(), []
    print(f"{cpu_name()}; base {rev or base}, this checkout {head}", flush=True)
    for name in args.only.split(","):
        runs: dict[str, list[dict]] = {"base": [], "off": [], "on": []}
        for _ in range(args.rounds):  # the sides take turns, so a drifting machine slows each alike
            for mode in runs:
                runs[mode].append(run_side(base if mode == "base" else REPO, name, args.reps, mode))
        b, e, c = (_summary(runs[m]) for m in runs)
        rows.append((name, b, e, c))
        print(f"{name:20s} base {b['ms']:7.1f}  eager {e['ms']:7.1f} ({b['ms'] / e['ms']:.2f}x)  compiled {c['ms']:7.1f} "
              f"({b['ms'] / c['ms']:.2f}x; first call {c['first_s']:.1f} s)", flush=True)
    text = "\n".join([
        HEADING, "",
        f"Measured by `python bench/commits.py --base DIR` on {cpu_name()} (one torch thread; load average "
        f"{load0:.2f} at the start, {loadavg():.2f} at the end): this checkout ({head}) against {rev or 'the base'}, "
        f"forward and backward of `rasterize()`, medians (range) of {args.rounds} x {args.reps} runs: "
        f"{args.rounds} processes a side, taking turns, each timing {args.reps} after a warm-up. *First call*: "
        "the compiled side's first process, compiling or loading its kernels.", "",
        "| workload | base ms | eager ms | faster by | compiled planner ms | faster by | first call s |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
        *[f"| {n} | {b['ms']:.0f} ({b['lo']:.0f}-{b['hi']:.0f}) | {e['ms']:.0f} ({e['lo']:.0f}-{e['hi']:.0f}) | "
          f"{b['ms'] / e['ms']:.2f}x | {c['ms']:.0f} ({c['lo']:.0f}-{c['hi']:.0f}) | {b['ms'] / c['ms']:.2f}x | "
          f"{c['first_s']:.1f} |" for n, b, e, c in rows], ""])
    publish(HEADING, text, write=not args.no_write)


if __name__ == "__main__":
    main()
