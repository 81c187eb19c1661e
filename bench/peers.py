"""The rasterizer against a peer, in one run: OpenSplat's CPU rasterizer and ours.

    .venv/bin/python bench/peers.py --source PATH/TO/OpenSplat [--threads 1,2] [--reps 5] [--block tuned,model]

OpenSplat is built from a checkout the user gives (recorded commit: 15b7e80; it is
AGPL-licensed and never vendored here) into bench/out/peers/build: its CPU
projection and rasterizer sources (`project_gaussians.cpp`, `rasterize_gaussians.cpp`,
`rasterizer/gsplat-cpu/gsplat_cpu.cpp`), the files its CMake compiles for
`-DGPU_RUNTIME=CPU`'s `gsplat_cpu` library, plus a 20-line binding written here,
compiled by torch's own extension builder against the libtorch inside the pip
torch wheel (g++ and ninja are needed; no OpenCV: the peer's image I/O is not timed).
Where the peer cannot be built, the script says why and exits 0.

Both sides render the workloads of bench/workloads.py forward and backward, in a process whose
allocator is set as every splatcli command sets it (`device.tune_allocator`):
the peer as its model.cpp does on CPU (project, SH degree 0 colours, rasterize);
ours through `splatcli.render.rasterize`, with the block `train` measures (tuned) and with
`rasterize()`'s default (model). They alternate, rep by rep, at each
thread count, so all see the same machine; medians are reported with the load
average. At the recorded commit the peer's CPU path blends in a wrong depth order
(its projection returns a strided depth view that the rasterizer reads as
contiguous), so its pictures differ from ours: it is timed as users build it.
Results: bench/out/peers.json (common.report), the table printed.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

from common import OUT as ALL_OUT, report
from splatcli.device import tune_allocator
from splatcli.gaussians import SH_C0
from splatcli.render import kernels, rasterize
from splatcli.render.blocks import BLOCKS, BlockTuner
from workloads import workloads

OUT = ALL_OUT / "peers"
SOURCES = ["project_gaussians.cpp", "rasterize_gaussians.cpp", "rasterizer/gsplat-cpu/gsplat_cpu.cpp"]
BINDING = r"""
#include <torch/extension.h>
#include "project_gaussians.hpp"
#include "rasterize_gaussians.hpp"

std::vector<torch::Tensor> project(torch::Tensor means, torch::Tensor scales, torch::Tensor quats,
                                   torch::Tensor viewmat, torch::Tensor fullmat, double fx, double fy,
                                   double cx, double cy, int64_t height, int64_t width) {
    return ProjectGaussiansCPU::apply(means, scales, 1, quats, viewmat, fullmat, fx, fy, cx, cy, height, width);
}

torch::Tensor rasterize(torch::Tensor xys, torch::Tensor radii, torch::Tensor conics, torch::Tensor colors,
                        torch::Tensor opacity, torch::Tensor cov2d, torch::Tensor depths, int64_t height,
                        int64_t width, torch::Tensor background) {
    return RasterizeGaussiansCPU::apply(xys, radii, conics, colors, opacity, cov2d, depths, height, width, background);
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
    m.def("project", &project);
    m.def("rasterize", &rasterize);
}
"""


def build(source: Path):
    """The peer as a torch extension module, or a reason it cannot be built."""
    missing = [s for s in SOURCES if not (source / s).is_file()]
    if missing:
        return None, f"{source}: not an OpenSplat checkout (missing {', '.join(missing)})"
    if shutil.which("g++") is None and shutil.which("c++") is None:
        return None, "no C++ compiler (g++)"
    try:
        import ninja  # noqa: F401
    except ImportError:
        if shutil.which("ninja") is None:
            return None, "ninja is missing (pip install ninja)"
    from torch.utils.cpp_extension import load

    build_dir = OUT / "build"
    build_dir.mkdir(parents=True, exist_ok=True)
    (build_dir / "binding.cpp").write_text(BINDING)
    rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=source, capture_output=True, text=True)
    try:
        mod = load(name="opensplat_cpu_peer", sources=[str(build_dir / "binding.cpp")] + [str(source / s) for s in SOURCES],
                   extra_include_paths=[str(source), str(source / "rasterizer")], extra_cflags=["-O3"],
                   build_directory=str(build_dir), verbose=False)
    except Exception as exc:  # a compiler error: say it and skip
        return None, f"building the peer failed: {' '.join(str(exc).split())[:300]}"
    inside = rev.returncode == 0 and (source / ".git").exists()  # not the repository around an exported tree
    return (mod, rev.stdout.strip() if inside else ""), None


def projection(K: torch.Tensor, width: int, height: int) -> torch.Tensor:  # [4, 4], as model.cpp builds it
    fx, fy = float(K[0, 0]), float(K[1, 1])
    near, far = 0.001, 1000.0
    t = near * (height / (2 * fy))
    r = near * (width / (2 * fx))
    return torch.tensor([[near / r, 0, 0, 0], [0, near / t, 0, 0],
                         [0, 0, (far + near) / (far - near), -far * near / (far - near)], [0, 0, 1, 0]])


def peer_step(mod, args, width: int, height: int) -> None:
    """One forward+backward through the peer, as its model.cpp runs on CPU (SH degree 0)."""
    means, quats, log_scales, logits, sh, viewmat, K = [a.detach().clone().requires_grad_(a.dim() > 1 and i < 5)
                                                        for i, a in enumerate(args)]
    logits.requires_grad_(True)
    p = mod.project(means, log_scales.exp(), quats / quats.norm(dim=-1, keepdim=True), viewmat,
                    projection(K, width, height) @ viewmat, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]),
                    float(K[1, 2]), height, width)
    xys, radii, conics, cov2d, depths = p
    rgb = (SH_C0 * sh[:, 0, :] + 0.5).clamp_min(0.0)
    img = mod.rasterize(xys, radii, conics, rgb, torch.sigmoid(logits)[:, None], cov2d, depths, height, width,
                         torch.zeros(3))  # the peer keeps opacities as [N, 1]
    img.sum().backward()


def ours_step(args, width: int, height: int, block) -> None:
    a = [t.detach().clone().requires_grad_(i < 5) for i, t in enumerate(args)]
    rasterize(*a, width, height, block=block).image.sum().backward()


def time_pair(mod, wl, reps: int, blocks: list[str]) -> dict:
    """Medians of `reps` forward+backward passes of the peer and of ours with each of `blocks`,
    alternating, after a warm-up. Ours draws as `train` does ("tuned": a BlockTuner, warmed up until
    it has measured every candidate block and chunk size) or with the cost model's block ("model")."""
    ours = {b: BlockTuner() if b == "tuned" else "auto" for b in blocks}
    peer_step(mod, wl.args, wl.width, wl.height)
    for o in ours.values():
        for _ in range(1 + o.samples * len(BLOCKS) * len(o.chunks) if isinstance(o, BlockTuner) else 1):
            ours_step(wl.args, wl.width, wl.height, o)
    times: dict[str, list[float]] = {"peer": [], **{b: [] for b in blocks}}
    for _ in range(reps):
        for name in times:
            t = time.perf_counter()
            if name == "peer":
                peer_step(mod, wl.args, wl.width, wl.height)
            else:
                ours_step(wl.args, wl.width, wl.height, ours[name])
            times[name].append(time.perf_counter() - t)
    tuned = ours["tuned"].summary() if "tuned" in ours else {}
    return {**{k: statistics.median(v) for k, v in times.items()}, "used": tuned.get("used", {}),
            "chunk": tuned.get("chunk", {})}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--source", default=os.environ.get("OPENSPLAT_SOURCE") or "",
                    help="an OpenSplat checkout (or $OPENSPLAT_SOURCE)")
    ap.add_argument("--rev", default="", help="the peer's commit, when the source is not a git checkout")
    ap.add_argument("--threads", default="1,2")
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--only", default="", help="comma-separated workload names")
    ap.add_argument("--compile", choices=("on", "off"), default="off", help="our rasterizer's compiled kernels")
    ap.add_argument("--block", default="tuned,model",
                    help="our block sizes, each timed: measured as train does (tuned), the cost model's pick (model)")
    ap.add_argument("--one", default="", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if not set(args.block.split(",")) <= {"tuned", "model"}:
        ap.error(f"--block {args.block!r}: a comma-separated list of tuned and model")
    if not args.source:
        print("peers: skipped: no OpenSplat source (--source or $OPENSPLAT_SOURCE)")
        return
    built, why = build(Path(args.source))
    if built is None:
        print(f"peers: skipped: {why}")
        return
    mod, rev = built
    rev = rev or args.rev or "unknown"
    if args.one:  # a child: one workload at one thread count, one JSON line
        tune_allocator()  # as every splatcli command does (the peer allocates through the same C library)
        wl = next(w for w in workloads([args.one]))
        torch.set_num_threads(int(args.threads))
        kernels.set_mode(args.compile)
        if args.compile == "on":  # compiled (or loaded from the cache) before the clock starts
            ours_step(wl.args, wl.width, wl.height, "auto")
        print(json.dumps(time_pair(mod, wl, args.reps, args.block.split(","))), flush=True)
        return
    rows = []
    print(f"OpenSplat {rev}; ours {'compiled' if args.compile == 'on' else 'eager'}, block {args.block}", flush=True)
    load0 = os.getloadavg()[0]
    for wl in workloads([x for x in args.only.split(",") if x] or None):
        if wl.args[4].shape[1] != 1:  # the peer's path here is SH degree 0
            continue
        for nt in [int(x) for x in args.threads.split(",")]:
            # Each pair in its own process: the peer crashes on some inputs, and a crash
            # must cost one row, not the run.
            r = subprocess.run([sys.executable, __file__, "--source", str(args.source), "--one", wl.name,
                                "--threads", str(nt), "--reps", str(args.reps), "--compile", args.compile,
                                "--block", args.block], capture_output=True, text=True)
            row = {"workload": wl.name, "threads": nt, "opensplat_ms": None}
            if r.returncode != 0:
                row["peer"] = f"crashed (exit {r.returncode})" if r.returncode < 0 or r.returncode > 128 else "failed"
            else:
                t = json.loads(r.stdout.strip().splitlines()[-1])
                row.update(opensplat_ms=t["peer"] * 1e3, peer="ran", blocks=t.get("used"), chunk=t.get("chunk"))
                for b in args.block.split(","):
                    row.update({f"{b}_ms": t[b] * 1e3, f"speedup_{b}": t["peer"] / t[b]})
                if "tuned" in t and "model" in t:
                    row["model_over_tuned"] = t["model"] / t["tuned"]
            rows.append(row)
            print(row, flush=True)
    if rows:
        report("peers", rows, opensplat_commit=rev, compile=args.compile, block=args.block, reps=args.reps,
               load_start=round(load0, 2))


if __name__ == "__main__":
    main()
