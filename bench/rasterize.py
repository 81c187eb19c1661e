"""Benchmark the rasterizer: forward, forward+backward, peak memory, ns per pair.

    python bench/rasterize.py [--threads 1,2] [--reps 5] [--only NAME ...] [--no-reference]

Workloads (seeded): synthetic N = 10k and 100k at 256x256 and 800x600 (camera
at the origin, f = 0.8 W; means x, y ~ U(-2, 2), z ~ U(3, 7); log scales ~ U(-4, -2);
normalised Gaussian-noise quats; opacity 0.5 + 0.1 N(0, 1) clamped to [0.05, 0.95];
colour U(0, 1) as SH degree 0), 100k at 800x600 with SH degree 3, and garden: the
real points of ../shared/data/garden/test_garden.npz cropped to [-2, 2]^3 at 648x420
with camera 0 (scales ~ U(1e-4, 0.02), random unit quats, opacity ~ U(0, 1), colours
from the file; skipped when the data is absent).

Per workload: median of --reps runs after one warm-up, of the forward (parameters
requiring grad, as in training) and of forward+backward (loss = sum of image times a
fixed random cotangent), wall and CPU (process) time; peak resident memory above
the pre-run level (CPU) or peak allocated (CUDA); and ns per pair, where pairs =
(Gaussian, pixel) with the pixel centre inside the Gaussian's 3-sigma ellipse
(2D covariance incl. the 0.3 px^2 blur), counted here in closed form per pixel row.
The dense reference runs on the smallest workload in the same run (forward, and
forward+backward in bands of rows), once, for the side-by-side ratio.

Results: bench/out/rasterize.json (common.report), the table printed.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import threading
import time

import torch

from common import report
from splatcli.render import rasterize
from splatcli.render.projection import project
from splatcli.render.reference import rasterize_reference
from workloads import Workload, workloads


def count_pairs(wl: Workload) -> tuple[int, int]:
    """(pairs, visible Gaussians): pixel centres inside each visible Gaussian's 3-sigma
    ellipse, counted per (Gaussian, pixel row) from the ellipse's x-interval on that row."""
    W, H = wl.width, wl.height
    with torch.no_grad():
        pr = project(*wl.args[:5], wl.args[5], wl.args[6], W, H, int(math.isqrt(wl.args[4].shape[1])) - 1)
        vis = pr.visible
        m = pr.means2d[vis].double()
        A, B, C = pr.conics[vis].double().unbind(1)  # the 2D covariance is the conic's inverse
        idet = A * C - B * B
        a, b, c = C / idet, -B / idet, A / idet
        det = a * c - b * b
        total = 0
        for s in range(0, m.shape[0], 20_000):
            sl = slice(s, s + 20_000)
            my, hy = m[sl, 1], 3 * c[sl].sqrt()
            y0 = torch.ceil(my - hy - 0.5).clamp(0, H - 1).long()
            y1 = torch.floor(my + hy - 0.5).clamp(-1, H - 1).long()
            n = (y1 - y0 + 1).clamp_min(0)
            gi = torch.repeat_interleave(torch.arange(n.numel()), n)
            row = y0[gi] + torch.arange(gi.numel()) - (torch.cumsum(n, 0) - n)[gi]
            dy = row.double() + 0.5 - my[gi]
            cc, bb = c[sl][gi], b[sl][gi]
            half = torch.sqrt((det[sl][gi] / cc * (9.0 - dy * dy / cc)).clamp_min(0))
            xc = m[sl, 0][gi] + bb / cc * dy
            x0 = torch.ceil(xc - half - 0.5).clamp_min(0)
            x1 = torch.floor(xc + half - 0.5).clamp_max(W - 1)
            total += int((x1 - x0 + 1).clamp_min(0).sum())
    return total, int(vis.sum())


class PeakRSS:
    """Peak resident set size above the level at entry, sampled every ~2 ms (CPU)."""

    def __enter__(self):
        self.base = self.peak = self._rss()
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()
        return self

    def _rss(self) -> int:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")

    def _run(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, self._rss())
            time.sleep(0.002)

    def __exit__(self, *exc):
        self._stop.set()
        self._t.join()
        self.peak = max(self.peak, self._rss())

    @property
    def mb(self) -> float:
        return (self.peak - self.base) / 2**20


def measure(wl: Workload, reps: int, device: torch.device, fn=rasterize, **kw) -> dict:
    params = [a.to(device).clone().requires_grad_(True) for a in wl.args[:5]]
    cam = [a.to(device) for a in wl.args[5:]]
    g = torch.Generator().manual_seed(1)
    cot = torch.randn(wl.height, wl.width, 3, generator=g).to(device)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    fwd, fwd_cpu, tot, tot_cpu, mem = [], [], [], [], []
    for i in range(reps + 1):  # the first is the warm-up
        for p in params:
            p.grad = None
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        with PeakRSS() as rss:
            sync()
            t0, c0 = time.perf_counter(), time.process_time()
            out = fn(*params, *cam, wl.width, wl.height, **kw)
            sync()
            t1, c1 = time.perf_counter(), time.process_time()
            (out.image * cot).sum().backward()
            sync()
            t2, c2 = time.perf_counter(), time.process_time()
        del out
        if i == 0:
            continue
        fwd.append(t1 - t0)
        fwd_cpu.append(c1 - c0)
        tot.append(t2 - t0)
        tot_cpu.append(c2 - c0)
        mem.append(torch.cuda.max_memory_allocated(device) / 2**20 if device.type == "cuda" else rss.mb)
    med = statistics.median
    return {"fwd": med(fwd), "fwd_cpu": med(fwd_cpu), "tot": med(tot), "tot_cpu": med(tot_cpu), "mem": max(mem)}


def reference_once(wl: Workload, band: int = 2) -> dict:
    """Dense reference on the whole image in bands of `band` rows: forward alone, then
    forward+backward (the loss is a sum over pixels, so band gradients add up)."""
    params = [a.clone().requires_grad_(True) for a in wl.args[:5]]
    g = torch.Generator().manual_seed(1)
    cot = torch.randn(wl.height, wl.width, 3, generator=g)
    t0 = time.perf_counter()
    with torch.no_grad():
        for y in range(0, wl.height, band):
            rasterize_reference(*params, *wl.args[5:], wl.width, wl.height, rows=(y, min(wl.height, y + band)))
    t1 = time.perf_counter()
    for y in range(0, wl.height, band):
        y1 = min(wl.height, y + band)
        out = rasterize_reference(*params, *wl.args[5:], wl.width, wl.height, rows=(y, y1))
        (out.image * cot[y:y1]).sum().backward()
    t2 = time.perf_counter()
    return {"fwd": t1 - t0, "tot": (t1 - t0) + (t2 - t1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--threads", default=str(torch.get_num_threads()), help="comma list of torch thread counts")
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--only", nargs="*", help="workload names (default: all)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--no-reference", action="store_true", help="skip the (slow) dense reference run")
    args = ap.parse_args()
    device = torch.device(args.device)
    threads = [int(t) for t in args.threads.split(",")]
    load0 = os.getloadavg()[0]
    rows = []
    wls = workloads(args.only)
    for wl in wls:
        pairs, nvis = count_pairs(wl)
        for nt in threads:
            torch.set_num_threads(nt)
            r = measure(wl, args.reps, device)
            rows.append({"workload": wl.name, "N": len(wl.args[0]), "visible": nvis, "pairs": pairs, "threads": nt,
                         "fwd_ms": r["fwd"] * 1e3, "fwd_cpu_ms": r["fwd_cpu"] * 1e3, "fwd_bwd_ms": r["tot"] * 1e3,
                         "fwd_bwd_cpu_ms": r["tot_cpu"] * 1e3, "fwd_ns_per_pair": r["fwd"] / pairs * 1e9,
                         "fwd_bwd_ns_per_pair": r["tot"] / pairs * 1e9, "peak_mb": r["mem"]})
            print(" ".join(f"{k} {v:.1f}" if isinstance(v, float) else f"{k} {v}" for k, v in rows[-1].items()),
                  flush=True)
    small = min(wls, key=lambda w: len(w.args[0]) * w.width * w.height) if wls else None
    fast = next((r for r in rows if small and r["workload"] == small.name and r["threads"] == threads[-1]), None)
    extra = {}
    if not args.no_reference and small:
        torch.set_num_threads(threads[-1])
        ref = reference_once(small)  # dense, float32, bands of 2 rows, one run
        extra["reference"] = {"workload": small.name, "threads": threads[-1], "fwd_s": ref["fwd"],
                              "fwd_bwd_s": ref["tot"],
                              "times_fast_fwd": ref["fwd"] * 1e3 / fast["fwd_ms"],
                              "times_fast_fwd_bwd": ref["tot"] * 1e3 / fast["fwd_bwd_ms"]}
        print(f"dense reference: {extra['reference']}", flush=True)
    report("rasterize", rows, device=str(device), reps=args.reps, load_start=round(load0, 2), **extra)


if __name__ == "__main__":
    main()
