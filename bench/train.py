"""Training benchmark: speed against held-out error on real scenes, and what
--compact and --max-gaussians cost.

    .venv/bin/python bench/train.py [--scenes lego,fox,fox-photos,sample] [--variants default,compact,budget]
                                    [--preset fast] [--iterations N] [--no-write]

For each scene it processes the data once (bench/out/train/<scene>/base), then
runs `splatcli train` as a subprocess per variant on a copy of that project:

  default   the preset as is
  compact   + --compact
  budget    + --max-gaussians (a third of the default run's final count)
  time      + --time-budget (lego 75 s, fox 240 s, sample 60 s: the issue-12 targets)

and records steps/s, held-out PSNR/SSIM at 1k, 3k and 7k steps, the training
seconds to reach 30 dB, wall time, peak RSS (sampled every 0.5 s from /proc),
the RSS the run logged at each log line (memory must stay flat once densification
stops), and the final Gaussian count and .ply size. Results go to
bench/out/train/results.json and the "## train" section of docs/benchmarks.md.

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
import platform
import shutil
from pathlib import Path

from common import PROCESSED, SCENES, ensure_processed, fmt, fresh_copy, splatcli, write_section
from splatcli.device import cpu_name
from splatcli.eval.curve import read_log
from splatcli.project import Project

OUT = PROCESSED  # bench/out/train: <scene>/base (processed) beside <scene>/<variant> (trained)
MILESTONES = (1000, 3000, 7000)
TARGET_DB = 30.0
TIME_BUDGETS = {"lego": 75, "fox": 240, "fox-photos": 240, "sample": 60}  # seconds, for the `time` variant


def train_variant(scene: str, variant: str, extra: list[str], preset: str, iterations: int | None,
                  threads: int | None, resume: bool = False) -> dict:
    """One `splatcli train` run. The compact variant resumes a copy of the finished
    default run with --compact (bitwise what a --compact run from scratch gives,
    see tests/test_train.py), so it costs only the prune and the fine-tune."""
    base = ensure_processed(scene)
    proj = OUT / scene / variant
    _, _, targs, scene_preset = SCENES[scene]
    preset = scene_preset or preset
    resuming = resume and Project(proj).latest_checkpoint() is not None
    if resuming:
        # An interrupted benchmark run continues from its last checkpoint (bitwise what an
        # uninterrupted run gives); its training seconds still count from step 0, but its
        # wall time and peak RSS cover only the resumed part.
        args = ["train", str(proj), "--resume", "--device", "cpu"]
    elif variant == "compact":
        src = OUT / scene / "default"
        if not Project(src).checkpoints_dir.is_dir():
            raise SystemExit(f"[{scene}/compact] needs the default run first ({src})")
        if proj.exists():
            shutil.rmtree(proj)
        shutil.copytree(src, proj)
        args = ["train", str(proj), "--resume", "--compact", "--device", "cpu"]
    else:
        fresh_copy(base, proj)
        args = ["train", str(proj), "--preset", preset, "--device", "cpu", "--eval-every", "1000", *targs, *extra]
        if iterations:
            args += ["--iterations", str(iterations)]
    if threads:
        os.environ["OMP_NUM_THREADS"] = str(threads)
    print(f"[{scene}/{variant}] splatcli {' '.join(args)}", flush=True)
    r = splatcli(args, OUT / scene / f"{variant}.log")
    s, peak_mb, samples = r.summary, r.peak_mb, r.rss
    log = read_log(Project(proj).train_log_path)
    evals = {r["step"]: r for r in log if "psnr" in r}
    at = {str(m): {"psnr": evals[m]["psnr"], "ssim": evals[m]["ssim"], "seconds": evals[m]["elapsed_s"]}
          for m in MILESTONES if m in evals}
    hit = next((r for r in log if r.get("psnr", 0) >= TARGET_DB), None)
    rss = [(r["step"], r["rss_mb"]) for r in log if "rss_mb" in r]
    res = {
        "scene": scene, "variant": variant, "preset": preset, "args": extra, "steps": s["steps"],
        "train_seconds": s["train_seconds"], "steps_per_s": s["steps"] / max(s["train_seconds"], 1e-9),
        "wall_seconds": round(r.wall_s, 1), "peak_rss_mb": peak_mb, "num_gaussians": s["num_gaussians"],
        "ply_bytes": s["ply_bytes"], "sh_degree": s["sh_degree"], "final_psnr": s["psnr"], "final_ssim": s["ssim"],
        "at": at, "seconds_to_30db": hit["elapsed_s"] if hit else None, "rss_by_step": rss,
        "rss_samples": samples[:: max(1, len(samples) // 200)], "compact": s.get("compact"),
        "threads": os.environ.get("OMP_NUM_THREADS"), "resumed_from": s.get("resumed_from"),
    }
    print(f"[{scene}/{variant}] {res['steps']} steps, {res['steps_per_s']:.2f} steps/s, PSNR {res['final_psnr']}, "
          f"{res['num_gaussians']} Gaussians, peak RSS {peak_mb} MB", flush=True)
    return res


def save_result(path: Path, r: dict) -> None:
    """Merge one result into results.json (re-read first: runs may go in parallel)."""
    old = json.loads(path.read_text()) if path.exists() else {"results": []}
    old["results"] = [o for o in old["results"] if (o["scene"], o["variant"]) != (r["scene"], r["variant"])] + [r]
    tmp = path.with_suffix(f".{os.getpid()}.tmp")
    tmp.write_text(json.dumps(old, indent=1))
    os.replace(tmp, path)


def markdown(results: list[dict], meta: dict) -> str:
    lines = ["## train", "",
             f"Measured by `python bench/train.py` on {meta['machine']}, {meta['cores']} CPU cores "
             f"{'shared with other jobs (noisy wall times)' if meta['shared'] else ''}; torch {meta['torch']}, "
             f"CPU only. Every run is `splatcli train` as a subprocess on its own copy of the processed project; "
             "PSNR/SSIM are held-out (every 8th image), measured every 1000 steps; seconds are training seconds "
             "(evaluation excluded) from `reports/train_log.jsonl`. A row marked *resumed* continued an "
             "earlier run from its checkpoint: its steps/s and train s count from step 0, its wall s and peak RSS "
             "cover the resumed part only.", ""]
    lines += ["| scene | variant | steps | steps/s | PSNR / SSIM 1k | PSNR / SSIM 3k | PSNR / SSIM 7k | "
              "final PSNR / SSIM | s to 30 dB | train s | wall s | peak RSS MB | Gaussians | .ply MB |",
              "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in results:
        a = r["at"]
        p = lambda m, k="psnr", a=a: a.get(str(m), {}).get(k)  # noqa: E731
        lines.append(
            f"| {r['scene']} | {r['variant']}{' ' + ' '.join(r['args']) if r['args'] else ''}"
            f"{' (resumed at ' + str(r['resumed_from']) + ')' if r.get('resumed_from') else ''} | {r['steps']} | "
            f"{r['steps_per_s']:.2f} | "
            + " | ".join(f"{fmt(p(m))} / {fmt(p(m, 'ssim'), '.4f')}" if p(m) is not None else "–" for m in MILESTONES)
            + " | "
            f"{fmt(r['final_psnr'])} / {fmt(r['final_ssim'], '.4f')} | "
            f"{fmt(r['seconds_to_30db'], '.0f')} | {r['train_seconds']:.0f} | {r['wall_seconds']:.0f} | "
            f"{r['peak_rss_mb']} | {r['num_gaussians']} | {r['ply_bytes'] / 1e6:.2f} |")
    comp = [r for r in results if r.get("compact")]
    if comp:
        lines += ["", "`--compact` (prune by total blending weight over the training views, then fine-tune):", "",
                  "| scene | before: Gaussians | PSNR | after: Gaussians | PSNR | .ply MB before → after | "
                  "fine-tune steps | extra train s |",
                  "| --- | --- | --- | --- | --- | --- | --- | --- |"]
        for r in comp:
            c = r["compact"]
            m = max((int(k) for k in r["at"]), default=0)  # the schedule's end, where compaction starts
            last = r["at"].get(str(m))
            extra = r["train_seconds"] - last["seconds"] if last else None
            lines.append(f"| {r['scene']} | {c['before_count']} | {fmt(c['before_psnr'])} | {c['after_count']} | "
                         f"{fmt(c['after_psnr'])} | {c['before_bytes'] / 1e6:.2f} → {c['after_bytes'] / 1e6:.2f} | "
                         f"{r['steps'] - m} | {fmt(extra, '.0f')} |")
    lines += ["", "Memory over the run (RSS logged by the training process at each log line; it follows the "
              "Gaussian count while densifying and must stay flat afterwards):", "",
              "| scene | variant | RSS MB at steps → |", "| --- | --- | --- |"]
    for r in results:
        pts = r["rss_by_step"]
        if pts:
            pick = pts[:: max(1, len(pts) // 8)] + ([pts[-1]] if pts[-1] not in pts[:: max(1, len(pts) // 8)] else [])
            lines.append(f"| {r['scene']} | {r['variant']} | " + ", ".join(f"{s}: {m}" for s, m in pick) + " |")
    lines += ["", "Goals, as measured:", ""] + goals(results)
    lines += ["", PRESET_NOTES.strip(), "", meta.get("notes", "").strip(), ""]
    return "\n".join(lines) + "\n"


PRESET_NOTES = """
Presets (`splatcli train --preset`): `default` is the paper's schedule (30k steps, densify every 100
steps from 500 to 15k, opacity reset every 3k, 100k random points for scenes without SfM points).
`fast` keeps every rule but compresses the schedule to 7k steps (densify until 4k, so the last 3k
steps refine a fixed set; one opacity reset at 3k; 10k random initial points, since early steps on
random points are the most expensive ones on a CPU and the first densification prunes most of them).
`demo` is `make demo` on sample_data: 1.5k steps at 256 px with a 20k-Gaussian budget. Every run is
`OMP_NUM_THREADS=1`: the two cores were shared with other jobs, and OpenMP's spin-waiting makes a
2-thread torch process 10-20x slower per step under oversubscription (measured on this machine);
one thread is also the CLI's default (docs/guide.md, "Threads"): 2 threads are 1.2x faster only on idle cores.
"""


def goals(results: list[dict]) -> list[str]:
    by = {(r["scene"], r["variant"]): r for r in results}
    out = []
    lego = by.get(("lego", "default"))
    if lego:
        t = lego["seconds_to_30db"]
        out.append(f"- lego at 200 px reaches 30 dB held-out PSNR after {fmt(t, '.0f')} training seconds "
                   f"(goal: within 900 s on 2 cores): {'met' if t is not None and t <= 900 else 'NOT met'}.")
    for scene in ("lego", "fox"):
        d, c, b = by.get((scene, "default")), by.get((scene, "compact")), by.get((scene, "budget"))
        if d and c and c.get("compact"):
            k = c["compact"]
            ratio = k["after_count"] / max(d["num_gaussians"], 1)
            dp = (k["after_psnr"] or 0) - (d["final_psnr"] or 0)
            ok = ratio <= 1 / 3 + 1e-9 and dp >= -0.1
            out.append(f"- {scene} --compact keeps {k['after_count']} of {d['num_gaussians']} Gaussians "
                       f"({ratio:.1%}) at {dp:+.2f} dB held-out PSNR vs the default run "
                       f"(goal: at most a third within 0.1 dB): {'met' if ok else 'NOT met'}.")
        if d and b:
            out.append(f"- {scene} --max-gaussians {b['args'][-1]} (a third of the default's final count): "
                       f"{b['num_gaussians']} Gaussians, {(b['final_psnr'] or 0) - (d['final_psnr'] or 0):+.2f} dB, "
                       f"{b['steps_per_s'] / max(d['steps_per_s'], 1e-9):.2f}x the steps/s.")
        t = by.get((scene, "time"))
        if t:
            budget = TIME_BUDGETS[scene]
            within = abs(t["train_seconds"] - budget) <= 0.1 * budget
            out.append(f"- {scene} --time-budget {budget}: {t['steps']} steps in {t['train_seconds']:.0f} training s "
                       f"({'within' if within else 'NOT within'} 10% of the budget), held-out PSNR "
                       f"{fmt(t['final_psnr'])} dB (goal: at least 30 dB): "
                       f"{'met' if within and (t['final_psnr'] or 0) >= 30 else 'NOT met'}.")
    return out


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
    ap.add_argument("--notes", default="", help="a paragraph appended to the section")
    ap.add_argument("--no-write", action="store_true", help="do not edit docs/benchmarks.md")
    args = ap.parse_args()
    import torch

    OUT.mkdir(parents=True, exist_ok=True)
    results_path = OUT / "results.json"
    for scene in [x for x in args.scenes.split(",") if x]:
        for variant in [x for x in args.variants.split(",") if x]:
            if scene == "sample" and variant not in ("default", "time"):
                continue
            extra = {"default": [], "compact": ["--compact"],
                     "time": ["--time-budget", str(TIME_BUDGETS[scene])]}.get(variant)
            if variant == "budget":
                old = json.loads(results_path.read_text())["results"] if results_path.exists() else []
                prev = [r for r in old if r["scene"] == scene and r["variant"] == "default"]
                if not prev:
                    print(f"[{scene}/budget] skipped: needs the default run's count", flush=True)
                    continue
                extra = ["--max-gaussians", str(max(1, prev[-1]["num_gaussians"] // 3))]
            save_result(results_path, train_variant(scene, variant, extra, args.preset, args.iterations, args.threads,
                                                          args.resume))
    old = json.loads(results_path.read_text()) if results_path.exists() else {"results": []}
    meta = {"machine": f"{platform.machine()} ({cpu_name()})",
            "cores": os.cpu_count(), "shared": True, "torch": torch.__version__, "notes": args.notes}
    order = {s: i for i, s in enumerate(SCENES)}
    allres = sorted(old["results"], key=lambda r: (order.get(r["scene"], 9),
                                                   ["default", "compact", "budget", "time"].index(r["variant"])))
    if not args.no_write:
        write_section("## train", markdown(allres, meta))
    print(markdown(allres, meta))


if __name__ == "__main__":
    main()
