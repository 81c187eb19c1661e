"""What fusing the per-Gaussian passes would buy: the projection's element-wise chain (forward
and backward) and the planner's make_plan, eager against torch.compile (inductor, CPU), one torch thread.

    .venv/bin/python bench/inductor.py PROJECT [--max-size 200] [--no-write]

PROJECT is a trained project (its latest checkpoint is the model), as for bench/step.py. The chain
is the projection's model on every Gaussian of the first training view, written once with
`render/projection.py`'s own helpers (camera transform, EWA covariance, conic, SH colour) and
differentiated by autograd: each side runs the same code, so the ratio is what fusion alone buys.
`make_plan` runs as it is on the footprints of the first 8 training views (block 8).
The compile is timed twice, in two fresh processes sharing one new cache folder: cold (an empty
cache, as on a user's first run) and warm (the second run on a machine).
Results go to the "## Fused kernels: torch.compile" section of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

from common import cpu_model, loadavg, publish

HEADING = "## Fused kernels: torch.compile"


def child(project: str, max_size: int) -> dict:
    import torch

    from splatcli.project import Project
    from splatcli.render.composite import make_plan
    from splatcli.render.projection import BLUR, NEAR, _Camera, _cov2d, _mean2d, project as project_view
    from splatcli.render.sh import sh_basis

    data, p = cpu_model(Project.open(project).latest_checkpoint(), max_size)
    view = data.train[0]
    cam = _Camera(view.viewmat, view.K, view.camera.width, view.camera.height, torch.float32)

    def chain(means, quats, log_scales, opacity_logits, sh):  # [N, 3], [N, 4], [N, 3], [N], [N, 16, 3]
        pc = torch.addmm(cam.t[:, None], cam.Rw, means.T)  # [3, N]
        zs = pc[2].clamp_min(NEAR)
        _, uv, tc = _mean2d(pc[:2], zs, cam)
        g = _cov2d(tc, zs, quats.T, torch.exp(log_scales.T), cam)
        a, b, c = g["a"], g["b"], g["c"]
        det = g["det0"] + BLUR * (a + c) + BLUR * BLUR
        lam = 0.5 * (a + c) + BLUR + torch.sqrt((0.5 * (a - c)) ** 2 + b * b)
        d = means.T - cam.campos[:, None]
        dirs = d / torch.sqrt((d * d).sum(0))
        colors = torch.clamp_min(torch.bmm(sh_basis(dirs.T, 3)[:, None, :], sh)[:, 0] + 0.5, 0.0)
        return uv, torch.stack([c + BLUR, -b, a + BLUR]) / det, torch.sigmoid(opacity_logits), colors, lam

    leaves = [p[k].clone().requires_grad_(True) for k in ("means", "quats", "log_scales", "opacity_logits", "sh")]
    gen = torch.Generator().manual_seed(0)
    cots = [torch.randn(o.shape, generator=gen) for o in chain(*leaves)]

    def step(fn):
        outs = fn(*leaves)
        torch.autograd.backward(outs, cots)
        return outs

    def median_ms(fn, reps=15):
        fn()
        fn()
        ts = []
        for _ in range(reps):
            t = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t)
        return 1e3 * statistics.median(ts)

    compiled = torch.compile(chain, dynamic=True)
    t = time.perf_counter()
    step(compiled)
    first = time.perf_counter() - t
    with torch.no_grad():
        diff = max(float((a - b).abs().max()) for a, b in zip(chain(*leaves), compiled(*leaves)))
    out = {"n": len(leaves[0]), "size": f"{view.camera.width}x{view.camera.height}", "first_s": first, "diff": diff,
           "eager_fwd": median_ms(lambda: chain(*leaves)), "eager": median_ms(lambda: step(chain)),
           "compiled": median_ms(lambda: step(compiled))}

    with torch.no_grad():
        fps = [(project_view(*p.values(), v.viewmat, v.K, v.camera.width, v.camera.height, 3).footprint, v.camera.width,
                v.camera.height) for v in data.train[:8]]
    plan_c = torch.compile(make_plan, dynamic=True)
    t = time.perf_counter()
    plan_c(*fps[0], 8)
    out["plan_first_s"] = time.perf_counter() - t
    out["plan_same"] = all(torch.equal(make_plan(*f, 8).pair_gid, plan_c(*f, 8).pair_gid) for f in fps)
    for name, fn in (("plan_eager", make_plan), ("plan_compiled", plan_c)):
        out[name] = statistics.median(median_ms(lambda f=f, fn=fn: fn(*f, 8), reps=3) for f in fps)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("project")
    ap.add_argument("--max-size", type=int, default=200)
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args.project, args.max_size)))
        return
    load0 = loadavg()
    runs = []
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, TORCHINDUCTOR_CACHE_DIR=cache, OMP_NUM_THREADS="1")
        for _ in ("cold", "warm"):
            out = subprocess.run([sys.executable, __file__, args.project, "--max-size", str(args.max_size), "--child"],
                                 env=env, check=True, capture_output=True, text=True).stdout
            runs.append(json.loads(out.strip().splitlines()[-1]))
    load1 = loadavg()
    cold, warm = runs
    rows = [f"| {name} | {r['first_s']:.1f} | {r['eager_fwd']:.1f} | {r['eager']:.1f} | {r['compiled']:.1f} | "
            f"{r['eager'] / r['compiled']:.1f}x | {r['diff']:.1e} |" for name, r in (("cold", cold), ("warm", warm))]
    plan_rows = [f"| {name} | {r['plan_first_s']:.1f} | {r['plan_eager']:.1f} | {r['plan_compiled']:.1f} | "
                 f"{r['plan_eager'] / r['plan_compiled']:.1f}x | {'yes' if r['plan_same'] else '**no**'} |"
                 for name, r in (("cold", cold), ("warm", warm))]
    text = "\n".join([
        HEADING, "",
        f"Measured by `python bench/inductor.py {args.project} --max-size {args.max_size}` (one torch thread; "
        f"{cold['n']:,} Gaussians, {cold['size']}; load average {load0:.2f} at the start, {load1:.2f} at the end). "
        "The projection's element-wise chain (camera transform, EWA covariance, conic, SH colour) on every Gaussian, "
        "forward and autograd backward, eager against `torch.compile(dynamic=True)`; milliseconds are medians of 15. "
        "*First call* is the compiled side's first forward and backward: cold in a fresh cache folder, warm from "
        "the cache the cold run left.", "",
        "| cache | first call s | eager forward ms | eager fwd+bwd ms | compiled fwd+bwd ms | faster by | max abs diff |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: |", *rows, "",
        "`make_plan` (no gradient), the median over the 8 views of each view's median of 3:", "",
        "| cache | first call s | eager ms | compiled ms | faster by | the same pairs |",
        "| --- | ---: | ---: | ---: | ---: | --- |", *plan_rows, ""])
    publish(HEADING, text, write=not args.no_write)


if __name__ == "__main__":
    main()
