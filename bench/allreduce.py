"""Would all-reducing only the rows some rank saw be cheaper than the dense all-reduce?

    .venv/bin/python bench/allreduce.py PROJECT [PROJECT ...] [--repeats 20] [--no-write]

From a trained project's latest checkpoint it measures, over pairs of training views
(what two ranks render in one step), the share of Gaussians that either view sees
(the rows a sparse exchange must carry). Then two gloo ranks on loopback time, for
that model's size, (a) the dense exchange `train --nproc` does (every gradient row
and the loss in one all-reduce) and (b) the sparse one: an all-reduce of the
visibility mask, then one of the seen rows only, with the gathers and scatters it
needs. Results go to the "## sparse all-reduce" section of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from common import write_section
from splatcli.io.checkpoint import load_checkpoint
from splatcli.project import Project
from splatcli.render.projection import project as project_view
from splatcli.train.data import load_train_data

ROW = 59  # floats per Gaussian at SH degree 3: 3 + 4 + 3 + 1 + 48


def union_shares(project: Path) -> tuple[int, list[float]]:
    proj = Project.open(project)
    ck = load_checkpoint(proj.latest_checkpoint())
    cfg = ck.config
    data = load_train_data(proj, cfg.get("downscale", 1.0), cfg.get("max_size", 1600), torch.device("cpu"))
    g = ck.gaussians
    seen = []
    with torch.no_grad():
        for v in data.train:
            p = project_view(g.means, g.quats, g.log_scales, g.opacity_logits, g.sh, v.viewmat, v.K, v.camera.width,
                        v.camera.height, sh_degree=0)
            seen.append(p.radii > 0)
    shares = [float((seen[i] | seen[i + 1]).float().mean()) for i in range(0, len(seen) - 1, 2)]
    return len(g), shares


def _rank(rank: int, n: int, share: float, repeats: int, store: str, out: str) -> None:
    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{store}", rank=rank, world_size=2)
    gen = torch.Generator().manual_seed(rank)
    grads = torch.randn(n, ROW, generator=gen)
    mine = torch.rand(n, generator=gen) < share / 1.5  # each rank sees part; the union is about `share`
    times = {"dense": [], "sparse": []}
    for _ in range(repeats):
        dist.barrier()
        t0 = time.perf_counter()
        flat = torch.cat([grads.reshape(-1), torch.zeros(2)])
        dist.all_reduce(flat)
        grads.copy_(flat[:-2].view(n, ROW))
        times["dense"].append(time.perf_counter() - t0)
        dist.barrier()
        t0 = time.perf_counter()
        mask = mine.to(torch.uint8)
        dist.all_reduce(mask, op=dist.ReduceOp.MAX)
        idx = mask.nonzero().squeeze(1)
        rows = torch.cat([grads.index_select(0, idx).reshape(-1), torch.zeros(2)])
        dist.all_reduce(rows)
        grads.index_copy_(0, idx, rows[:-2].view(-1, ROW))
        times["sparse"].append(time.perf_counter() - t0)
    if rank == 0:
        Path(out).write_text(json.dumps({k: sorted(v)[len(v) // 2] for k, v in times.items()}
                                        | {"union": float(mask.float().mean())}))
    dist.destroy_process_group()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("projects", nargs="+")
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    rows = []
    for project in args.projects:
        n, shares = union_shares(Path(project))
        share = sum(shares) / len(shares)
        load0 = os.getloadavg()
        with tempfile.TemporaryDirectory() as tmp:
            out = os.path.join(tmp, "r.json")
            mp.spawn(_rank, args=(n, share, args.repeats, os.path.join(tmp, "store"), out), nprocs=2, join=True)
            r = json.loads(Path(out).read_text())
        rows.append(f"| `{Path(project).parent.name}/{Path(project).name}` | {n} | {100 * share:.0f}% "
                    f"(min {100 * min(shares):.0f}%, max {100 * max(shares):.0f}%) | {1000 * r['dense']:.1f} | "
                    f"{1000 * r['sparse']:.1f} | {load0[0]:.2f} → {os.getloadavg()[0]:.2f} |")
    text = "\n".join([
        "## sparse all-reduce", "",
        "Measured by `python bench/allreduce.py PROJECT ...` on models `bench/distributed.py` trained "
        "(their latest checkpoints), two gloo ranks on loopback, one thread each, median of "
        f"{args.repeats}. The sparse exchange must first agree on the rows either rank saw (a mask "
        "all-reduce), then gather, exchange and scatter only those rows.", "",
        "| model | Gaussians | rows either of two views sees | dense all-reduce ms | sparse ms (mask + rows) | "
        "load before → after |",
        "| --- | --- | --- | --- | --- | --- |", *rows, ""])
    if not args.no_write:
        write_section("## sparse all-reduce", text)
    print(text)


if __name__ == "__main__":
    main()
