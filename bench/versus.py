"""Time to quality, side by side: this version against an earlier commit, in one run.

    .venv/bin/python bench/versus.py --against 333d7bf [--scenes lego,fox] [--train-args "--preset fast"]
                                     [--new-args ""] [--new-train-args "--time-budget 120"]
                                     [--eval-every 250] [--no-write]

For each scene (processed once, as bench/train.py does) it trains the earlier commit
(a git worktree under bench/out/versus/, run with PYTHONPATH pointing at it) and then
this version, one after the other on the same machine, with the same arguments
(`--new-args` go to this version only; `--new-train-args` replace them for this version,
e.g. to run its planned default against the earlier version's best fixed schedule). It plots held-out PSNR against training
seconds for both in one figure (docs/figures/versus_<scene>.png) and reports the
training seconds each takes to reach the earlier version's final PSNR (within 0.1 dB).
Results go to bench/out/versus/results.json and the "## time to quality" section of
docs/benchmarks.md, with the load average before and after each run.
"""

from __future__ import annotations

import os
import shlex
import subprocess
from pathlib import Path

from common import REPO, SCENES, TOL_DB, fmt, load_span, psnr_figure, scene_benchmark, scene_parser, train_fresh

OUT = REPO / "bench" / "out" / "versus"


def worktree(rev: str) -> Path:
    path = OUT / f"wt-{rev}"
    if not (path / "splatcli").is_dir():
        subprocess.run(["git", "worktree", "add", "--detach", "-f", str(path), rev], cwd=REPO, check=True,
                       capture_output=True)
    return path


def train_once(scene: str, label: str, code: Path, args: list[str]) -> dict:
    # Run from inside `code`: `python -m` puts the working directory first on sys.path,
    # ahead of the editable install of this checkout.
    env = {**os.environ, "PYTHONPATH": str(code), "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")}
    return train_fresh(scene, OUT / scene / label.replace(" ", "_"), args, cwd=code, env=env, label=label)


def plot(scene: str, runs: list[dict], path: Path) -> bool:
    return psnr_figure(path, scene, {r["label"]: r["curve"] for r in runs})


HEAD = ["## time to quality", "",
       "Measured by `python bench/versus.py`: the earlier commit and this version train the same processed "
       "scene one after the other in one run (same machine, 2 cores, one torch thread per process; a planned "
       "run of this version takes one process per free core). Seconds are training "
       "seconds (held-out evaluation excluded); *to base* is the first held-out evaluation within "
       f"{TOL_DB} dB of the earlier version's final PSNR.", "",
       "| scene | version | arguments | steps | train s | final PSNR | s to base | speed-up | Gaussians | "
       "peak RSS MB | load before → after |",
       "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]


def row(scene: str, run: dict, old: dict, t: float | None, sp: float | None) -> str:
    speedup = "1x" if run is old else "–" if sp is None else f"{sp:.2f}x"  # the earlier version is the base
    return (f"| {scene} | {run['label']} | `{' '.join(run['args'])}` | {run['steps']} | "
            f"{run['train_seconds']:.0f} | {run['final_psnr']:.2f} | {fmt(t, '.0f')} | {speedup} | "
            f"{run['num_gaussians']} | {run['peak_rss_mb']} | {load_span(run)} |")


def main() -> None:
    ap = scene_parser(__doc__, "lego", "--preset fast")
    ap.add_argument("--against", required=True, help="the earlier commit")
    ap.add_argument("--new-args", default="", help="extra arguments for this version only")
    ap.add_argument("--new-train-args", default=None,
                    help="this version's arguments instead of --train-args (e.g. its planned run: --time-budget 120)")
    args = ap.parse_args()
    old_code = worktree(args.against)

    def both(scene: str, common: list[str]) -> list[dict]:
        old = train_once(scene, args.against, old_code, common)
        mine = common if args.new_train_args is None else (
            shlex.split(args.new_train_args) + [*SCENES[scene][2], "--eval-every", str(args.eval_every)])
        mine += shlex.split(args.new_args)
        return [{**old, "args": common}, {**train_once(scene, "this version", REPO, mine), "args": mine}]

    scene_benchmark(args, OUT, "versus", both, plot, HEAD, row)


if __name__ == "__main__":
    main()
