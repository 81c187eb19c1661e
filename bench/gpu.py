"""splatcli on a GPU: the PyTorch path against gsplat's kernels, and both against gsplat bare.

    .venv/bin/python bench/gpu.py [--steps 30] [--iterations 7000] [--compare 500] [--no-train]

Three measurements, one after the other in one run:

- **Host syncs per step**, anywhere (the CPU too): one fwd+bwd of the PyTorch rasterizer as
  training calls it (50k Gaussians, 480x270, SH 3: bench/workloads.py), counting the calls
  that make the host wait for a CUDA device (`HostSyncs`), with the compositor's CPU settings
  (what CUDA ran before issue 36) and its CUDA ones (`composite.device_settings`). On the CPU
  this counts what CUDA would do; on a GPU, torch's own sync counter is read beside it.
- **Step time** (CUDA): the same Gaussians and camera, fwd+bwd: `--renderer torch`,
  `--renderer gsplat` (splatcli's adapter), and gsplat's `rasterization()` in a bare loop;
  wall ms, GPU kernel ms and kernel launches per step from torch.profiler.
- **Training** (CUDA): fox at 480 px, `--preset fast`: gsplat at the full schedule, then
  `--renderer gsplat` and `torch` at `--compare` steps: train seconds and held-out PSNR.

Results: bench/out/gpu.json (common.report), the tables printed. Without a GPU the CUDA
measurements are left out. Issue 36's targets: fox at 480 px, fast preset, in at most 120 s with
gsplat and within 0.3 dB of the PyTorch path; a step at most 1.3x gsplat's bare loop; 3x fewer
host syncs per step.
"""

from __future__ import annotations

import argparse
import time
from collections import Counter

import torch
from torch.overrides import TorchFunctionMode

from common import OUT, ensure_processed, fresh_copy, report, splatcli
from splatcli.device import describe_device
from splatcli.render import composite as comp
from splatcli.render.backends import gsplat_inputs, gsplat_problem, rasterize_gsplat
from splatcli.render.rasterize import rasterize
from workloads import benchmark_scene

# calls after which the host waits for a CUDA device: a value read back, or an output whose
# size depends on the data
SYNCING = {"__bool__", "item", "tolist", "__int__", "__float__", "__index__", "nonzero", "unique", "masked_select",
           "bincount", "numpy", "cpu"}


class HostSyncs(TorchFunctionMode):
    """Counts, by name, the torch calls that synchronise with a CUDA device (also run on the
    CPU, where they cost nothing, so the count is the same code path's)."""

    def __init__(self) -> None:
        super().__init__()
        self.calls: Counter[str] = Counter()

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = getattr(func, "__name__", "")
        index = args[1] if name == "__getitem__" and len(args) > 1 else None
        masks = index if isinstance(index, tuple) else (index,)
        if (name in SYNCING
                or any(isinstance(m, torch.Tensor) and m.dtype == torch.bool for m in masks)
                or (name == "repeat_interleave" and kwargs.get("output_size") is None)):
            self.calls[name] += 1
        return func(*args, **kwargs)

    @property
    def total(self) -> int:
        return sum(self.calls.values())


def scene(device: torch.device, n: int = 50_000, width: int = 480, height: int = 270) -> tuple[list, int, int]:
    args = [a.to(device) for a in benchmark_scene(n, width, height, sh_degree=3, seed=1)]
    return args, width, height


def fwd_bwd(draw, args, W, H) -> None:
    xs = [a.detach().requires_grad_(i < 5) for i, a in enumerate(args)]
    out = draw(*xs, W, H, check=False)
    out.means2d.retain_grad()
    (out.image.square().mean() + out.alpha.mean()).backward()


def syncs(device: torch.device) -> list[dict]:
    """Host syncs per fwd+bwd with the compositor's CPU settings (what CUDA ran before issue 36) and
    its CUDA ones: counted (`HostSyncs`), and on a GPU the profiler's count beside them."""
    args, W, H = scene(device)
    rows = []
    for name, settings in (("before (CPU settings)", comp.device_settings(torch.device("cpu"))),
                           ("CUDA settings", comp.device_settings(torch.device("cuda")))):
        old = comp.device_settings
        comp.device_settings = lambda dev, block=8, s=settings: s
        try:
            fwd_bwd(rasterize, args, W, H)  # warm-up
            with HostSyncs() as h:
                fwd_bwd(rasterize, args, W, H)
            cuda = None
            if device.type == "cuda":
                torch.cuda.synchronize()
                with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA,
                                                        torch.profiler.ProfilerActivity.CPU]) as prof:
                    fwd_bwd(rasterize, args, W, H)
                    torch.cuda.synchronize()
                cuda = int(sum(e.count for e in prof.key_averages() if "Synchronize" in e.key or "DtoH" in e.key))
        finally:
            comp.device_settings = old
        rows.append({"table": "host syncs", "run": name, "counted": h.total, "cuda_syncs": cuda,
                     "most_frequent": ", ".join(f"{k} {v}" for k, v in h.calls.most_common(4))})
    return rows


def step_rows(device: torch.device, steps: int) -> list[dict]:
    """Fwd+bwd of the same Gaussians and camera through each renderer, mean of `steps` (CUDA)."""
    if device.type != "cuda" or gsplat_problem() is not None:
        print(f"step times: not measured ({'no GPU' if device.type != 'cuda' else gsplat_problem()})", flush=True)
        return []
    from gsplat import rasterization

    args, W, H = scene(device)

    def bare(means, quats, log_scales, logits, sh, viewmat, K, W, H, check=False):
        kw = gsplat_inputs(means, quats, log_scales, logits, sh, viewmat, K, W, H, torch.zeros(3, device=device),
                           sh_degree=3, near=0.2, antialiased=False)
        colors, alphas, meta = rasterization(**kw)
        meta["means2d"].retain_grad()
        return types_out(colors, alphas, meta)

    rows = []
    for name, draw in (("torch", rasterize), ("gsplat (splatcli)", rasterize_gsplat), ("gsplat bare", bare)):
        for _ in range(3):
            fwd_bwd(draw, args, W, H)
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA]) as prof:
            for _ in range(steps):
                fwd_bwd(draw, args, W, H)
            torch.cuda.synchronize()
        wall = (time.perf_counter() - t0) / steps * 1e3
        kernels = [e for e in prof.events() if e.device_type == torch.autograd.DeviceType.CUDA]
        gpu_ms = sum(e.device_time for e in kernels) / 1e3 / steps
        rows.append({"table": "step", "run": name, "wall_ms": wall, "gpu_kernel_ms": gpu_ms,
                     "launches": len(kernels) / steps})
        print(rows[-1], flush=True)
    return rows


class types_out:  # gsplat's raw results with what fwd_bwd reads (the bare loop has no RenderOutput)
    def __init__(self, colors, alphas, meta):
        self.image, self.alpha, self.means2d = colors[0, ..., :3], alphas[0, ..., 0], meta["means2d"]


def train_rows(device: torch.device, iterations: int, compare: int) -> list[dict]:
    """gsplat at the full schedule (issue 36's time target), then both renderers at a short one
    (`compare` steps; the PyTorch path is host-bound on a GPU, too slow for the full schedule in
    a lease): the same settings, so the PSNRs compare the renderers."""
    if device.type != "cuda":
        return []
    rows = []
    for renderer, steps in (("gsplat", iterations), ("gsplat", compare), ("torch", compare)):
        name = f"{renderer}-{steps}"
        dest = fresh_copy(ensure_processed("fox"), OUT / "gpu" / name)
        r = splatcli(["train", str(dest), "--device", "cuda", "--renderer", renderer, "--max-size", "480",
                      "--preset", "fast", "--iterations", str(steps)], OUT / "gpu" / f"{name}.log")
        s = r.summary
        rows.append({"table": "training, fox 480 px, --preset fast", "run": f"{renderer} ({s['renderer']})",
                     "steps": steps, "train_s": s["train_seconds"], "wall_s": r.wall_s, "psnr": s["psnr"],
                     "gaussians": s["num_gaussians"], "load_before": r.load[0], "load_after": r.load[1]})
        print(rows[-1], flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=30, help="fwd+bwd steps timed per renderer")
    ap.add_argument("--iterations", type=int, default=7000, help="gsplat's training steps (the fast preset's 7,000)")
    ap.add_argument("--compare", type=int, default=500, help="steps of the run of each renderer at equal settings")
    ap.add_argument("--no-train", action="store_true", help="skip the training runs")
    a = ap.parse_args()
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    torch.manual_seed(0)
    rows = syncs(device) + step_rows(device, a.steps) + ([] if a.no_train else train_rows(device, a.iterations,
                                                                                          a.compare))
    report("gpu", rows, columns=["table", "run", "counted", "cuda_syncs", "most_frequent", "wall_ms", "gpu_kernel_ms",
                                 "launches", "steps", "train_s", "wall_s", "psnr", "gaussians"],
           device=describe_device(device))


if __name__ == "__main__":
    main()
