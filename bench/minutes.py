"""Minutes, not hours (issue 35): `splatcli train` as a new user runs it, timed whole.

    .venv/bin/python bench/minutes.py [--runs lego-90,fox-300,fox-default,fox-photos-default] [--no-write]

Each run trains a fresh copy of a processed scene (bench/common.py) as a subprocess and
reports held-out PSNR (8-bit renders at the trained size), training seconds against the
budget, the whole command's wall time, the ETA line the command printed before its first
step, what it chose, and the load average before and after. One after the other, on this
machine. Results go to the "## minutes, not hours (issue 35)" section of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import re

import torch

from common import OUT, SPLATCLI, ensure_processed, fresh_copy, loadavg, publish, run, write_section
from splatcli.device import cpu_name

# label -> (scene, train arguments, target PSNR, budget seconds or None)
RUNS = {
    "lego-90": ("lego", ["--max-size", "200", "--time-budget", "90"], 30.0, 90.0),
    "fox-300": ("fox", ["--preset", "fast", "--max-size", "480", "--time-budget", "300"], 30.0, 300.0),
    "fox-default": ("fox", [], None, None),
    "fox-photos-default": ("fox-photos", [], 29.5, None),
}
SECTION = "## minutes, not hours (issue 35)"


def one(label: str) -> dict:
    scene, args, target, budget = RUNS[label]
    proj = fresh_copy(ensure_processed(scene), OUT / "minutes" / label)
    log = OUT / "minutes" / f"{label}.log"
    r = run(SPLATCLI + ["train", str(proj), *args, "--json"], log)
    if r.returncode != 0:
        raise SystemExit(f"{label}: train failed (exit {r.returncode}); see {log}")
    s = r.summary
    err = log.read_text()
    eta = re.search(r"note: (trains for [^;(]*)", err)
    size = json.loads((proj / "splatcli.json").read_text())["steps"]["train"]["config"]["max_size"]
    return {"label": label, "scene": scene, "args": " ".join(args) or "(none)", "psnr": s["psnr"], "ssim": s["ssim"],
            "target": target, "budget": budget, "train_s": s["train_seconds"], "wall_s": round(r.wall_s, 1),
            "steps": s["steps"], "gaussians": s["num_gaussians"], "nproc": s["nproc"], "max_size": size,
            "eta": eta.group(1).strip() if eta else None, "chosen": s.get("chosen"), "load": r.load,
            "plan": (s.get("plan") or {}).get("budget_s")}


def markdown(rows: list[dict]) -> str:
    out = [SECTION, "",
           f"Measured by `python bench/minutes.py` on {cpu_name()}, 2 CPU cores, "
           f"torch {torch.__version__}: each run is `splatcli train` on a fresh copy of the processed scene, one after "
           "the other, nothing else running. PSNR is held-out, on 8-bit renders at the trained size; *train s* are "
           "training seconds (the budget counts them), *wall s* the whole command (loading, processes starting, "
           "held-out evaluation included).", "",
           "| run | arguments | PSNR / SSIM | target | train s | budget | wall s | steps | Gaussians | processes "
           "| trained at | ETA printed | load before → after |",
           "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        out.append(f"| {r['label']} | `{r['args']}` | {r['psnr']:.2f} / {r['ssim']:.4f} | "
                   f"{r['target'] or '–'} | {r['train_s']:.0f} | {r['budget'] or r['plan'] or '–'} | {r['wall_s']:.0f} | "
                   f"{r['steps']} | {r['gaussians']:,} | {r['nproc']} | {r['max_size']} px | {r['eta'] or '–'} | "
                   f"{r['load'][0]} → {r['load'][1]} |")
    chosen = next((r["chosen"] for r in rows if r["args"] == "(none)" and r["chosen"]), None)
    if chosen:
        out += ["", "What a run with no options chose (`summary.chosen`):", ""]
        out += [f"- `{c['option']}` {c['value']}: {c['why']}" for c in chosen]
    return "\n".join(out) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", default=",".join(RUNS))
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--rewrite", action="store_true", help="only write the section again from the last results")
    args = ap.parse_args()
    if args.rewrite:
        write_section(SECTION, markdown(json.loads((OUT / "minutes" / "results.json").read_text())))
        return
    rows = []
    for label in args.runs.split(","):
        print(f"[{label}] load {loadavg()}", flush=True)
        rows.append(one(label))
        print(json.dumps(rows[-1]), flush=True)
    (OUT / "minutes").mkdir(parents=True, exist_ok=True)
    (OUT / "minutes" / "results.json").write_text(json.dumps(rows, indent=1))
    publish(SECTION, markdown(rows), write=not args.no_write)


if __name__ == "__main__":
    main()
