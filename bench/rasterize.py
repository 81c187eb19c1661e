"""Benchmark the rasterizer: forward, forward+backward, peak memory, ns per pair.

    python bench/rasterize.py [--threads 1,2] [--reps 5] [--only NAME ...] [--no-reference] [--no-write]

Workloads (seeded, issue 7): synthetic N = 10k and 100k at 256x256 and 800x600 (camera
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

Writes the "## Rasterizer" section of docs/benchmarks.md (other sections kept).
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from common import publish
from scenes import Workload, workloads
from splatcli.device import cpu_name
from splatcli.render import rasterize
from splatcli.render.projection import project
from splatcli.render.reference import rasterize_reference

SECTION = "## Rasterizer"
# A peer's time counts only when it ran in the same run, on the same machine: figures from
# another day are not divided by here (issue 12). The same-run peer comparison is pending.


ALTERNATIVES = """### Alternatives tried (chosen by measuring)

Single thread, CPU (process) time unless marked wall, same-run A/B comparisons where noted
(the 2 cores were shared with other jobs throughout, so absolute numbers drift by up to 50%
between runs; ratios within one run are the reliable part). fwd / fwd+bwd in ms.

| # | variant | workload | result | kept? |
|---|---|---|---|---|
| 1 | first version: dense [blocks, K, pixels] tensors, `exp`, `torch.where` masks, 2^21-element chunks, whole lists (no early termination), bounding-box pairing | 10k, 256^2, block 4 / 8 / 16 | 345/741, 380/1051, 578/1228 (wall) | replaced |
| 2 | [blocks, pixels, K] layout: scans run along the contiguous K axis (cumprod 0.46 vs 1.76 ns/element), every GEMM in its fast orientation (colour 0.25 vs 2.1 ns/element); `exp2` with log2(e) folded into the coefficients (0.23 vs 1.7 ns/element); `threshold_`/`clamp_` instead of `where`/`masked_fill` (0.1 vs 2.8 / 10 ns/element); K segments with early termination | 10k, 256^2, block 8 | 52/140 | yes |
| 3 | chunk size 2^16 / 2^18 / 2^20 / 2^21 elements | same | 70/224, 52/140, 54/184, 71/228 | 2^18 (fits L2/L3) |
| 4 | segment length 32 / 64 / 128 | same | 49/128, 52/140, 45/129 (noise) | 64 |
| 5 | exact ellipse-vs-block pairing per block row (closed-form x-extent of the alpha ellipse over a row band) instead of bounding boxes | 10k, 256^2 / 800x600 | 19% / 32% fewer pairs (block 8) | yes |
| 6 | exponent coefficients per pair, gathered per chunk, vs built per padded slot | 10k, 256^2, same run | 191 -> 138 fwd+bwd | yes, then 7 |
| 7 | lazy slots: coefficients gathered and gradients scattered per segment, for active blocks only (pairs behind saturated pixels cost nothing but planning) | 100k, 800x600, block 8 / 16 | 4219 -> 2340, 2257 -> 1532 (total) | yes |
| 8 | planning with `index_select`/`repeat_interleave` instead of `x[idx]` gathers (1.6x faster per element) | 100k, 800x600, block 8 | plan 700 -> 283 | yes |
| 9 | block side 4 / 8 / 16 (total fwd+bwd) | 10k 256^2; 10k 800x600; 100k 800x600; garden; 100k 200^2 | 110/133/169; 1000/433/460; -/1623/1247; 1146/899/936; 351/310/356 | `block="auto"`: cost model picks 8, 8, 16, 8, 8 |
| 10 | keep alpha and T from the forward for the backward (budget 2^26 elements) instead of recomputing | 10k 256^2 / 800x600, same run | 120 -> 131, 424 -> 399 fwd+bwd (noise), more memory | no |
| 11 | `torch.compile` (inductor, CPU) of the per-chunk forward kernel | [64, 64, 64] chunk | 7.8 vs 30 ns/element for the same naive eager code, but 45 s to compile and 5.5 s per new shape (dynamic=True); the tuned eager kernel runs at about 2 ns/element in isolation | no |
| 12 | textbook flattened formulation (see the line above the table) | 10k, 256^2 | see above | no (baseline) |
| 13 | 2 torch threads while the cores are oversubscribed | 10k, 256^2 | 6x more CPU time than 1 thread (OpenMP workers spin) | measure 1 thread; use 2 on idle cores |
| 14 | a block also leaves the segment loop when its list has ended, not only when its pixels saturate (before, a chunk padded every block to its longest list, and short lists ran to the end on padding: at 50 px one chunk held 169 blocks padded to K = 4,365 for 89k pairs) | lego checkpoint, 36.6k Gaussians, 12 training views at 50 / 100 / 200 px, block 4, before -> after, consecutive runs | composite fwd 84 -> 34, 61 -> 28, 61 -> 43; backward (loss included) 224 -> 115, 187 -> 102, 192 -> 148; whole fwd+bwd step at 9.1k Gaussians 119 -> 62 (50 px), 122 -> 94 (200 px) | yes (issue 12) |
| 15 | glibc keeps freed memory (`mallopt`: mmap threshold 32 MB, trim threshold 1 GB) instead of page-faulting each segment's fresh tensors in again | compositor alone, fresh process / whole `train` runs | 1.4x faster compositor in a short microbenchmark; `train --preset fast --iterations 400` on lego: 71.8 and 68.8 s default, 70.2 and 73.5 s tuned (alternating): no gain, since a long run's dynamic mmap threshold already adapts | no |
"""


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


def flattened(means, quats, log_scales, opacity_logits, sh, viewmat, K, width, height):
    """The textbook flattened formulation (the alternative we measured against): one row
    per (Gaussian, pixel) pair inside the alpha bounding box, alpha per pair, a global
    sort by (pixel, depth), a segmented cumsum of log(1 - alpha) for transmittance, and
    index_add into pixels; backward by autograd. Same model and picture as rasterize()."""
    W, H = width, height
    pr = project(means, quats, log_scales, opacity_logits, sh, viewmat, K, W, H, int(math.isqrt(sh.shape[1])) - 1)
    with torch.no_grad():
        fp = pr.footprint  # the drawable Gaussians in depth order
        idx, m, cv, rc = fp.gid, fp.means2d, fp.cov2d, fp.rect
        t2 = 2 * torch.log((fp.opacities * 255).clamp_min(1e-30)) + 1e-3
        hx, hy = (t2 * cv[:, 0]).sqrt(), (t2 * cv[:, 2]).sqrt()
        x0 = torch.maximum(torch.ceil(m[:, 0] - hx - 0.5), rc[:, 0] * 16.0).clamp_min(0).long()
        x1 = torch.minimum(torch.floor(m[:, 0] + hx - 0.5), rc[:, 2] * 16.0 - 1).clamp_max(W - 1).long()
        y0 = torch.maximum(torch.ceil(m[:, 1] - hy - 0.5), rc[:, 1] * 16.0).clamp_min(0).long()
        y1 = torch.minimum(torch.floor(m[:, 1] + hy - 0.5), rc[:, 3] * 16.0 - 1).clamp_max(H - 1).long()
        nx, ny = (x1 - x0 + 1).clamp_min(0), (y1 - y0 + 1).clamp_min(0)
        n = nx * ny
        rank = torch.repeat_interleave(torch.arange(idx.numel()), n)
        loc = torch.arange(rank.numel()) - (torch.cumsum(n, 0) - n)[rank]
        px = x0[rank] + loc % nx[rank]
        py = y0[rank] + loc // nx[rank]
        key, order = torch.sort((py * W + px) * max(idx.numel(), 1) + rank)
        pix = torch.div(key, max(idx.numel(), 1), rounding_mode="floor")
        rank, px, py = rank[order], px[order], py[order]
        gid = idx[rank]
    d = torch.stack([px + 0.5, py + 0.5], 1).to(means.dtype) - pr.means2d[gid]
    A, B, C = pr.conics[gid].unbind(1)
    alpha = pr.opacities[gid] * torch.exp(-0.5 * (A * d[:, 0] ** 2 + C * d[:, 1] ** 2) - B * d[:, 0] * d[:, 1])
    alpha = torch.where(alpha >= 1 / 255, alpha.clamp(max=0.99), torch.zeros_like(alpha))
    lg = torch.log1p(-alpha).double()  # a global float32 cumsum would lose the segments' digits
    cs = torch.cumsum(lg, 0)
    first = torch.searchsorted(pix, pix)  # start of each pixel's segment
    excl = cs - lg - torch.where(first > 0, cs[(first - 1).clamp_min(0)], torch.zeros_like(cs))
    T_before = torch.exp(excl).to(alpha.dtype)
    inc = (T_before * (1 - alpha) >= 1e-4).detach()
    w = torch.where(inc, alpha * T_before, torch.zeros_like(alpha))
    img = torch.zeros(H * W, 3, dtype=means.dtype).index_add(0, pix, w[:, None] * pr.colors[gid])
    acc = torch.zeros(H * W, dtype=means.dtype).index_add(0, pix, w)
    return img.reshape(H, W, 3), (1 - acc).reshape(H, W)


@dataclass
class _Out:
    image: torch.Tensor


def flattened_measure(wl: Workload, reps: int) -> dict:
    fn = lambda *a: _Out(flattened(*a)[0])  # noqa: E731
    return measure(wl, reps, torch.device("cpu"), fn=fn)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--threads", default=str(torch.get_num_threads()), help="comma list of torch thread counts")
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--only", nargs="*", help="workload names (default: all)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--no-reference", action="store_true", help="skip the (slow) dense reference run")
    ap.add_argument("--no-write", action="store_true", help="print only; leave docs/benchmarks.md alone")
    ap.add_argument("--flattened", action="store_true", help="also time the textbook flattened formulation")
    ap.add_argument("--extra", default="", help="markdown appended to the section (e.g. the alternatives table)")
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
            ns = r["tot"] / pairs * 1e9
            rows.append((wl.name, len(wl.args[0]), nvis, pairs, nt, r))
            print(f"{wl.name:22s} threads {nt}: fwd {r['fwd'] * 1e3:8.1f} ms (cpu {r['fwd_cpu'] * 1e3:8.1f})  "
                  f"fwd+bwd {r['tot'] * 1e3:8.1f} ms (cpu {r['tot_cpu'] * 1e3:8.1f})  peak {r['mem']:7.1f} MB  "
                  f"pairs {pairs:>11,d}  fwd {r['fwd'] / pairs * 1e9:5.1f} / fwd+bwd {ns:5.1f} ns/pair", flush=True)
    ref_line = ""
    if not args.no_reference and wls:
        small = min(wls, key=lambda w: len(w.args[0]) * w.width * w.height)
        torch.set_num_threads(threads[-1])
        fast = next(r for r in rows if r[0] == small.name and r[4] == threads[-1])[5]
        ref = reference_once(small)
        ref_line = (f"Dense reference (`splatcli/render/reference.py`, float32, bands of 2 rows) on {small.name}, "
                    f"{threads[-1]} thread(s), one run: forward {ref['fwd']:.1f} s, forward+backward {ref['tot']:.1f} s, "
                    f"i.e. {ref['fwd'] / fast['fwd']:.0f}x and {ref['tot'] / fast['tot']:.0f}x the fast path's time.")
        print(ref_line, flush=True)
    flat_line = ""
    if args.flattened and wls:
        small = min(wls, key=lambda w: len(w.args[0]) * w.width * w.height)
        torch.set_num_threads(threads[-1])
        pairs = next(r for r in rows if r[0] == small.name)[3]
        fast = next(r for r in rows if r[0] == small.name and r[4] == threads[-1])[5]
        with torch.no_grad():
            diff = (flattened(*small.args, small.width, small.height)[0]
                    - rasterize(*small.args, small.width, small.height).image).abs().max().item()
        fl = flattened_measure(small, args.reps)
        flat_line = (f"Textbook flattened formulation (per-pair alpha, global sort by (pixel, depth), segmented "
                     f"cumsum of log(1 - alpha), index_add; autograd backward) on {small.name}, {threads[-1]} "
                     f"thread(s): forward {fl['fwd'] * 1e3:.0f} ms ({fl['fwd'] / pairs * 1e9:.0f} ns/pair, CPU "
                     f"{fl['fwd_cpu'] * 1e3:.0f} ms), fwd+bwd {fl['tot'] * 1e3:.0f} ms ({fl['tot'] / pairs * 1e9:.0f} "
                     f"ns/pair, CPU {fl['tot_cpu'] * 1e3:.0f} ms), peak {fl['mem']:.0f} MB; the block compositor "
                     f"is {fl['tot_cpu'] / fast['tot_cpu']:.1f}x faster (CPU time). Max |difference| of the images "
                     f"{diff:.1e}.")
        print(flat_line, flush=True)
    load1 = os.getloadavg()[0]
    cpu = cpu_name()
    out = [
        SECTION,
        "",
        f"Measured by `python bench/rasterize.py --threads {args.threads} --reps {args.reps}` on {cpu}, "
        f"{os.cpu_count()} cores, torch {torch.__version__}, device {device}. "
        + (f"The cores were shared with other jobs (load average {load0:.1f} at start, {load1:.1f} at end), so "
           "wall times are inflated; " if load0 >= 1.0 else
           f"Nothing else ran (load average {load0:.1f} at the start; {load1:.1f} at the end is the benchmark's "
           "own threads); ")
        + "the CPU column is this process's CPU time. Medians of the runs after one warm-up. Pairs: (Gaussian, pixel) "
        "with the pixel centre in the Gaussian's 3-sigma ellipse; ns/pair = fwd+bwd wall time / pairs.",
        "",
        "| workload | N | visible | pairs | threads | fwd ms | fwd ms (CPU) | fwd+bwd ms | fwd+bwd ms (CPU) "
        "| fwd ns/pair | fwd+bwd ns/pair | peak MB |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name, n, nvis, pairs, nt, r in rows:
        out.append(
            f"| {name} | {n:,} | {nvis:,} | {pairs:,} | {nt} | {r['fwd'] * 1e3:.0f} | {r['fwd_cpu'] * 1e3:.0f} | "
            f"{r['tot'] * 1e3:.0f} | {r['tot_cpu'] * 1e3:.0f} | {r['fwd'] / pairs * 1e9:.1f} | "
            f"{r['tot'] / pairs * 1e9:.1f} | {r['mem']:.0f} |"
        )
    out += ["", "Goal: fwd+bwd <= 40 ns/pair (issue 7), <= 25 (issue 12). No peer column: a ratio counts only "
            "when both sides ran in the same run.", ""]
    for nt in sorted({row[4] for row in rows}):
        mine = [row for row in rows if row[4] == nt]
        ns, worst = max((row[5]["tot"] / row[3] * 1e9, row[0]) for row in mine)
        line = (f"Goals with {nt} thread(s): worst fwd+bwd {ns:.1f} ns/pair "
                f"({worst}; goal <= 40: {'met' if ns <= 40 else 'NOT met'})")
        fw = max(row[5]["fwd"] / row[3] for row in mine) * 1e9
        out += [line + f"; worst forward alone {fw:.1f} ns/pair.", ""]
    if ref_line:
        out += [ref_line, ""]
    if flat_line:
        out += [flat_line, ""]
    out += [ALTERNATIVES]
    if args.extra:
        out += [Path(args.extra).read_text(encoding="utf-8").rstrip("\n"), ""]
    publish(SECTION, "\n".join(out), write=not args.no_write)


if __name__ == "__main__":
    main()
