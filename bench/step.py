"""Where one training step goes: projection, planning, compositing, loss, backward.

    .venv/bin/python bench/step.py PROJECT [--max-size 200] [--scales 0.25,0.5,1] [--views 12]
                                           [--fractions 0.25,0.5,1]

PROJECT is a trained project (its latest checkpoint is the model; e.g. one that
bench/train.py left under bench/out/train/). For each share of the
Gaussians (a seeded random subset) and each resolution (a fraction of the trained
size, as coarse-to-fine renders), it times the stages of a training step on the
first training views, one torch thread, and prints medians in ms. The backward is
split by running it in three parts: the loss, the compositor and the projection.
Stages as rasterize() runs them: *project* is the fused projection (cull, screen
ellipses, SH colour, and the planner's per-Gaussian footprint: tile rects, depth
order); *plan* is the block choice, the pair estimate and make_plan (per block row and
per pair). With `--blocks 4,8,16` each block size is measured in turn (`model`: the cost model's pick).
Beside the times, the compositor's dense slots (render/timing.py): the shares below alpha 1/255,
behind a pixel whose transmittance had ended, and padding.
Results: bench/out/step.json (common.report), the table printed.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import time

import torch

from common import report
from splatcli.device import tune_allocator
from splatcli.files.checkpoint import load_checkpoint
from splatcli.project import Project
from splatcli.render import kernels, timing
from splatcli.render.blocks import choose_block, estimate_pairs, footprint_extents
from splatcli.render.composite import composite, make_plan
from splatcli.render.projection import project
from splatcli.train.data import load_train_data
from splatcli.train.loss import photometric_loss
from splatcli.train.profile import slot_shares

STAGES = ("project", "plan", "composite", "loss", "loss bwd", "composite bwd", "project bwd")


def step_times(p: dict, view, bg, block: str = "model") -> tuple[dict, int]:
    """One step's stages (seconds) and its (Gaussian, block) pair count."""
    t, out = time.perf_counter(), {}
    W, H = view.camera.width, view.camera.height

    def lap(name):
        nonlocal t
        now = time.perf_counter()
        out[name] = now - t
        t = now

    pr = project(*p.values(), view.viewmat, view.K, W, H, math.isqrt(p["sh"].shape[1]) - 1)
    lap("project")
    fp = pr.footprint
    ext = footprint_extents(fp)
    block = choose_block(ext, W, H) if block == "model" else int(block)
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
    ap.add_argument("--blocks", default="model", help="block sizes to measure: model (the cost model's), 4, 8, 16")
    ap.add_argument("--compile", choices=("on", "off"), default="off", help="the rasterizer's compiled kernels")
    ap.add_argument("--allocator", choices=("tuned", "glibc"), default="tuned", help="tuned: as every splatcli command")
    args = ap.parse_args()
    if args.allocator == "tuned":
        tune_allocator()
    kernels.set_mode(args.compile)
    torch.set_num_threads(1)
    proj, cpu = Project.open(args.project), torch.device("cpu")
    data = load_train_data(proj, 1.0, args.max_size, cpu, 0)  # the training views at --max-size
    ckpt = proj.latest_checkpoint()
    if ckpt is None:
        raise SystemExit(f"{args.project}: no checkpoint; train it first (splatcli train {args.project})")
    full = load_checkpoint(ckpt, cpu).gaussians.detach().as_dict()
    n_all = len(full["means"])
    load0 = os.getloadavg()[0]
    rows = []
    for frac in [float(x) for x in args.fractions.split(",")]:
        n = max(1, round(frac * n_all))
        idx = torch.randperm(n_all, generator=torch.Generator().manual_seed(0))[:n]
        p = {k: v[idx].clone().requires_grad_(True) for k, v in full.items()}
        for scale, block in [(float(x), b) for x in args.scales.split(",") for b in args.blocks.split(",")]:
            views = [v.at_scale(scale) for v in data.train[: args.views + 2]]
            runs, pairs, slots = [], [], {}
            for i, v in enumerate(views):
                timing.collect(slots if i >= 2 else None)
                st, m = step_times(p, v, data.background, block)
                if i >= 2:  # two warm-ups
                    runs.append(st)
                    pairs.append(m)
            timing.collect(None)
            med = {k: 1e3 * statistics.median(r[k] for r in runs) for k in STAGES}
            size = f"{views[0].camera.width}x{views[0].camera.height}"
            sl = slot_shares(slots, len(runs))
            rows.append({"gaussians": n, "image": size, "block": block, "pairs": statistics.median(pairs),
                         **{f"{k} ms": med[k] for k in STAGES}, "total ms": sum(med.values()),
                         "slots": sl["per_step"], **{f"{k} %": round(100 * sl[k], 1) for k in ("below", "ended", "padding")}})
            print(rows[-1], flush=True)
    st = kernels.status()
    report("step", rows, project=args.project, max_size=args.max_size, views=args.views, compile=args.compile,
           allocator=args.allocator,
           compile_s=st.compile_s if args.compile == "on" else None, load_start=round(load0, 2))


if __name__ == "__main__":
    main()
