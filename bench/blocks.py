"""How close `rasterize(block="auto")` comes to the fastest block size.

    .venv/bin/python bench/blocks.py CHECKPOINT[@MAX_SIZE] ... [--views 6] [--no-write]

For each checkpoint (a `step-*.pt` under a project's checkpoints/; MAX_SIZE, the
longest image side, defaults to 480) it renders and backpropagates the first of every
few training views with 4, 8 and 16 px blocks, best of two each, one torch thread,
and with the block `choose_block` picks. Results go to the "## Block size" section of
docs/benchmarks.md: the total ms per block, the pick's total, and its excess over the
fastest block of each view.
"""

from __future__ import annotations

import argparse
import functools
import importlib
import os
import time
from pathlib import Path

from common import cpu_model, publish
from splatcli.render.rasterize import rasterize

R = importlib.import_module("splatcli.render.rasterize")  # the module (the package exports the function)
BLOCKS = (4, 8, 16)


def render_backward(p: list, view, background, block) -> None:
    """One view rendered with `block` px blocks, and back-propagated."""
    out = rasterize(*p, view.viewmat, view.K, view.camera.width, view.camera.height, background, block=block)
    out.image.sum().backward()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("checkpoints", nargs="+", help="CHECKPOINT[@MAX_SIZE]")
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    picked: list[int] = []
    real = R.choose_block

    def spy(*a):
        picked.append(real(*a))
        return picked[-1]

    rows, load0 = [], os.getloadavg()[0]
    for spec in args.checkpoints:
        path, _, size = spec.partition("@")
        ck = Path(path)
        data, params = cpu_model(ck, int(size or 480))
        p = [v.clone().requires_grad_(True) for v in params.values()]
        views = data.train[:: max(1, len(data.train) // args.views)][: args.views]
        tot = {b: 0.0 for b in (*BLOCKS, "auto", "best")}
        for i, v in enumerate(views):
            run = functools.partial(render_backward, p, v, data.background)
            if i == 0:
                run(8)  # warm-up
            t = {}
            for b in BLOCKS:
                t[b] = []
                for _ in range(2):
                    t0 = time.perf_counter()
                    run(b)
                    t[b].append(time.perf_counter() - t0)
                t[b] = 1e3 * min(t[b])
                tot[b] += t[b]
            R.choose_block, picked[:] = spy, []
            run("auto")
            R.choose_block = real
            tot["auto"] += t[picked[0]]
            tot["best"] += min(t.values())
        name = f"{ck.parents[1].name} step {int(ck.stem.split('-')[-1]):,}"
        size = f"{views[0].camera.width}x{views[0].camera.height}"
        rows.append((name, size, len(views), len(p[0]), tot))
        print(name, size, {k: round(v) for k, v in tot.items()}, flush=True)
    load1 = os.getloadavg()[0]
    out = ["## Block size", "",
           f"Measured by `python bench/blocks.py` (one torch thread, every view timed at each block size one after "
           f"the other, best of two; load average {load0:.2f} at the start, {load1:.2f} at the end). Render and "
           "backward, total ms over the views; *auto* is the sum over views of the time at the block "
           "`choose_block` picked; *excess* is auto over the fastest block of each view.", "",
           "| model | image | views | Gaussians | 4 px | 8 px | 16 px | auto | excess |",
           "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for name, size, nv, n, tot in rows:
        out.append(f"| {name} | {size} | {nv} | {n:,} | " + " | ".join(f"{tot[b]:,.0f}" for b in BLOCKS)
                   + f" | {tot['auto']:,.0f} | {100 * (tot['auto'] / tot['best'] - 1):.1f}% |")
    publish("## Block size", "\n".join(out) + "\n", write=not args.no_write)


if __name__ == "__main__":
    main()
