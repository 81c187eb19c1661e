"""Where one training step goes: projection, planning, compositing, loss, backward.

    .venv/bin/python bench/step.py PROJECT [--max-size 200] [--scales 0.25,0.5,1] [--views 12]
                                           [--fractions 0.25,0.5,1] [--no-write]

PROJECT is a trained project (its latest checkpoint is the model; e.g. one that
bench/versus.py or bench/train.py left under bench/out/). For each share of the
Gaussians (a seeded random subset) and each resolution (a fraction of the trained
size, as coarse-to-fine renders), it times the stages of a training step on the
first training views, one torch thread, and prints medians in ms. The backward is
split by running it in three parts: the loss, the compositor and the projection.
Stages as rasterize() runs them: *project* is the fused projection (cull, screen
ellipses, SH colour, and the planner's per-Gaussian footprint: tile rects, depth
order); *plan* is the block choice, the pair estimate and make_plan (per block row and
per pair).
Results go to the "## Where a training step goes" section of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import torch

from common import cpu_model, publish
from splatcli.device import cpu_name
from splatcli.project import Project
from splatcli.render import kernels
from splatcli.render.blocks import choose_block, estimate_pairs, extents
from splatcli.render.composite import composite, make_plan
from splatcli.render.projection import project
from splatcli.train.loss import photometric_loss

STAGES = ("project", "plan", "composite", "loss", "loss bwd", "composite bwd", "project bwd")


def step_times(p: dict, view, bg) -> tuple[dict, int]:
    """One step's stages (seconds) and its (Gaussian, block) pair count."""
    t, out = time.perf_counter(), {}
    W, H = view.camera.width, view.camera.height

    def lap(name):
        nonlocal t
        now = time.perf_counter()
        out[name] = now - t
        t = now

    pr = project(*p.values(), view.viewmat, view.K, W, H, 3)
    lap("project")
    fp = pr.footprint
    ext = extents(fp.cov2d, fp.opacities)
    block = choose_block(ext, W, H)
    estimate_pairs(ext, block)  # rasterize's check for banding
    plan = make_plan(fp, W, H, block)
    lap("plan")
    mid = [x.detach().requires_grad_(True) for x in (pr.means2d, pr.conics, pr.opacities, pr.colors, pr.depths)]
    img = composite(plan, *mid, bg)[0]
    lap("composite")
    leaf = img.detach().requires_grad_(True)
    loss = photometric_loss(leaf, view.target(), 0.2)
    lap("loss")
    loss.backward()
    lap("loss bwd")
    grads = torch.autograd.grad(img, mid, leaf.grad)
    lap("composite bwd")
    torch.autograd.backward([pr.means2d, pr.conics, pr.opacities, pr.colors, pr.depths], list(grads))
    lap("project bwd")
    return out, plan.n_pairs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("project")
    ap.add_argument("--max-size", type=int, default=200)
    ap.add_argument("--scales", default="0.25,0.5,1")
    ap.add_argument("--fractions", default="0.25,0.5,1", help="shares of the model's Gaussians")
    ap.add_argument("--views", type=int, default=12)
    ap.add_argument("--compile", choices=("on", "off"), default="off", help="the rasterizer's compiled kernels")
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    kernels.set_mode(args.compile)
    data, full = cpu_model(Project.open(args.project).latest_checkpoint(), args.max_size)
    n_all = len(full["means"])
    load0 = os.getloadavg()[0]
    rows = []
    for frac in [float(x) for x in args.fractions.split(",")]:
        n = max(1, round(frac * n_all))
        idx = torch.randperm(n_all, generator=torch.Generator().manual_seed(0))[:n]
        p = {k: v[idx].clone().requires_grad_(True) for k, v in full.items()}
        for scale in [float(x) for x in args.scales.split(",")]:
            views = [v.at_scale(scale) for v in data.train[: args.views + 2]]
            runs, pairs = [], []
            for i, v in enumerate(views):
                st, m = step_times(p, v, data.background)
                if i >= 2:  # two warm-ups
                    runs.append(st)
                    pairs.append(m)
            med = {k: 1e3 * statistics.median(r[k] for r in runs) for k in STAGES}
            rows.append((n, f"{views[0].camera.width}x{views[0].camera.height}", statistics.median(pairs), med))
            print(f"N {n:7d}  {rows[-1][1]:>9s}  " + "  ".join(f"{k} {med[k]:.1f}" for k in STAGES)
                  + f"  total {sum(med.values()):.1f} ms", flush=True)
    load1 = os.getloadavg()[0]
    st = kernels.status()
    compiled = (f"compiled planner (first calls {st.compile_s:.1f} s, not in the medians)" if args.compile == "on"
                else "eager")
    print(f"{cpu_name()}; {compiled}; load {load0:.2f} -> {load1:.2f}", flush=True)
    out = ["## Where a training step goes", "",
           f"Measured by `python bench/step.py {args.project} --max-size {args.max_size} --compile {args.compile}` "
           f"on {cpu_name()}, {compiled} (one torch thread; medians "
           f"over {args.views} training views after 2 warm-ups; load average {load0:.2f} at the start, {load1:.2f} at "
           "the end). Milliseconds per stage of one training step; *pairs* are (Gaussian, block) pairs planned.", "",
           "| Gaussians | image | pairs | " + " | ".join(STAGES) + " | total |",
           "| ---: | --- | ---: | " + " | ".join("---:" for _ in STAGES) + " | ---: |"]
    for n, size, m, med in rows:
        out.append(f"| {n:,} | {size} | {m:,.0f} | " + " | ".join(f"{med[k]:.1f}" for k in STAGES)
                   + f" | {sum(med.values()):.1f} |")
    publish("## Where a training step goes", "\n".join(out) + "\n", write=not args.no_write)


if __name__ == "__main__":
    main()
