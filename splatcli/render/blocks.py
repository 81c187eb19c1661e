"""The compositor's block size (4, 8 or 16 px): a speed knob only, the picture does not depend on it.

    ext = extents(cov2d, opacities)        the drawn Gaussians' bounding boxes, once per render
    choose_block(ext, W, H)                the cost model's pick (no state; any device)
    tuner = BlockTuner()                   the pick measured on this machine, call by call:
    rasterize(..., block=tuner)            (training passes one; CPU only, CUDA syncs would be needed)

Which block is fastest depends on the CPU as much as on the scene: the cost model below was
fitted on one machine, and on dense scenes another CPU runs 8 px blocks faster than the 4 px the
model picks. A tuner therefore corrects the model
per block size by what it measures: each render reports the seconds its planning, compositing
and compositing backward took, divided by the model's predicted cost for the block it used; the
tuner picks the block whose median ratio times its predicted cost is least. It first measures
each block the model does not rule out a few times, then keeps measuring the others now and
then, since the model's Gaussians change as training goes on.

The tuner measures the compositor's chunk size (dense elements per chunk: CHUNKS) the same way,
each block with each chunk size: small images and small models run faster in smaller chunks
(less to keep in cache), large ones in larger (fewer tensor operations), and where the turn
comes depends on the CPU's caches.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import NamedTuple

import torch
from torch import Tensor

from . import kernels
from .projection import TILE, Footprint

# 2 px blocks are not offered: they halve the slots below alpha 1/255 but make 2-3x the pairs; at best they
# tie 4 px in a step (lego at 200 px), and fox at 480 px took 1.5x with them (docs/benchmarks.md, "Slots that
# count").
BLOCKS = (4, 8, 16)
CHUNKS = (1 << 17, 1 << 18, 1 << 19)  # the compositor's chunk sizes a tuner tries, smallest first (the last: composite.CHUNK_ELEMS)

# Cost model (ns per (Gaussian, block) pair and per dense [pixel, pair] element, forward +
# backward, one CPU thread), fitted to the fastest block of 111 training views on one machine
# (lego at 200 and 800 px, fox at 480 and 960 px, models from step 50 to the end). 16 px blocks
# were never the fastest there: a block stops early only when all its pixels have saturated.
# A pair costs more once a plan holds millions (its lists and per-slot gradients leave the caches):
# dense views (garden, 100k Gaussians at 256 px) ran 8 px blocks 1.1-3.2x faster than the 4 px the
# linear model picked (Zen 4 EPYC; on a Xeon its default trailed the measured pick 1.27x on garden);
# the pair cost doubles at _PAIRS_CACHE pairs, which left the 8 fox and lego training views measured on their pick.
_COST_SLOT, _COST_ELEM, _PAIRS_CACHE = 50.0, 12.0, 2.5e6


@dataclass(frozen=True)
class Extents:
    """The alpha >= 1/255 bounding boxes of the Gaussians that are drawn, px, float64: all that
    choosing a block and estimating a plan's pairs need, computed once per render."""

    w: Tensor  # [D]
    h: Tensor  # [D]
    lo: Tensor | None = None  # [D, 2] (x, y) of each box's low corner, within its tiles; None: positions unknown
    hi: Tensor | None = None  # [D, 2] the high corner


@torch.no_grad()
def extents(
    cov2d: Tensor,  # [S, 3] px^2, of the Gaussians that may be drawn (a Footprint's)
    opacities: Tensor,  # [S]
    means2d: Tensor | None = None,  # [S, 2] px: with rect, each box is clipped to its tiles (as the planner clips)
    rect: Tensor | None = None,  # [S, 4] tile rect (tx0, ty0, tx1, ty1), exclusive ends
) -> Extents:
    o = opacities.detach().double()
    cv = cov2d.detach().double()
    t2 = 2.0 * torch.log(torch.clamp_min(o * 255.0, 1e-30))
    ok = t2 > 0
    # A footprint holds only rows with 2 ln(255 o) + 1e-3 > 0, so all are kept but in a sliver: the
    # boolean gathers are skipped then (they were most of this function's time: lego at 200 px, 2.3 -> 0.75 ms).
    if not bool(ok.all()):
        cv, t2 = cv[ok], t2[ok]
        means2d = None if means2d is None else means2d[ok]
        rect = None if rect is None else rect[ok]
    wh = 2 * torch.sqrt(t2[:, None] * cv[:, 0::2])  # [D, 2]: the box's width and height
    w, h = wh.unbind(1)
    if means2d is None or rect is None:
        return Extents(w, h)
    m, r = means2d.detach().double(), rect.double() * TILE
    half = wh / 2
    return Extents(w, h, torch.maximum(m - half, r[:, :2]), torch.minimum(m + half, r[:, 2:]))


def footprint_extents(fp: Footprint) -> Extents:
    """`extents` of a footprint's Gaussians, each box clipped to its tiles."""
    return extents(fp.cov2d, fp.opacities, fp.means2d, fp.rect)


def _boxes(ext: Extents, width: int, height: int) -> tuple[Tensor, Tensor]:  # -> w, h [D] px, 0 where off the image
    """Each box's width and height within the image (and its tiles, where the positions are known).
    A photo capture's background Gaussians reach far past the frame: fox's boxes, unclipped, held
    1.9x the pairs its 4 px plan made and 1.7x its 8 px plan's, which tipped the model to 8 px
    blocks that drew its training views 1.15x slower (docs/benchmarks.md, "Slots that count")."""
    if ext.lo is None or ext.hi is None:
        return ext.w.clamp_max(width), ext.h.clamp_max(height)
    size = torch.tensor([width, height], dtype=ext.hi.dtype, device=ext.hi.device)
    d = torch.minimum(ext.hi, size) - ext.lo.clamp_min(0)
    d = torch.where((d > 0).all(1, keepdim=True), d, torch.zeros_like(d))
    return d[:, 0], d[:, 1]


def _pairs(w: Tensor, h: Tensor) -> dict[int, float]:
    """About how many blocks boxes of w x h px touch, for each block size b (none for an empty box):
    the sum of (w / b + 1) (h / b + 1) = w h / b^2 + (w + h) / b + 1 over the boxes, from three
    sums taken once."""
    on = w > 0
    h = torch.where(on, h, torch.zeros_like(h))
    wh, sides, n = float((w * h).sum()), float((w + h).sum()), float(on.sum())
    return {b: wh / (b * b) + sides / b + n for b in BLOCKS}


def block_costs(ext: Extents, width: int, height: int) -> dict[int, float]:
    """The cost model's prediction for each block size (arbitrary units; empty when nothing is drawn)."""
    if ext.w.numel() == 0:
        return {}
    w, h = _boxes(ext, width, height)
    pairs = _pairs(w, h)
    return {b: m * (_COST_SLOT * (1 + m / _PAIRS_CACHE) + _COST_ELEM * b * b) for b, m in pairs.items()}


def choose_block(ext: Extents, width: int, height: int) -> int:
    """The block side (4, 8 or 16 px) that minimises the cost model: small blocks waste fewer
    pixels on small Gaussians, large blocks make fewer pairs."""
    cost = block_costs(ext, width, height)
    return min(cost, key=cost.get) if cost else 8


def estimate_pairs(ext: Extents, block: int) -> float:
    """About how many (Gaussian, block) pairs a plan will hold (from the bounding boxes, unclipped)."""
    return float(((ext.w / block + 1) * (ext.h / block + 1)).sum())


class Layout(NamedTuple):
    """How the compositor lays a render out: the block side (px) and the dense elements per chunk
    (None: the device's default)."""

    block: int
    chunk: int | None = None


class Meter:
    """One render's block-dependent seconds (planning, compositing, and its backward when the
    tuner waits for it), handed to the tuner when the render is complete."""

    def __init__(self, tuner: BlockTuner, layout: Layout, cost: float):
        self.tuner, self.layout, self.cost, self.seconds = tuner, layout, cost, 0.0
        self._compile_s = kernels.status().compile_s

    def add(self, seconds: float, last: bool) -> None:
        self.seconds += seconds
        if last and kernels.status().compile_s == self._compile_s:  # a call that compiled a kernel says nothing
            self.tuner.record(self.layout, self.seconds / self.cost)


@dataclass
class BlockTuner:
    """The block size and chunk size measured on this machine (module docstring). One per training
    run (or per process); not thread-safe. `backward`: whether each render is back-propagated
    (training): its time is then counted only once the backward has run."""

    backward: bool = True
    samples: int = 3  # measurements of each candidate layout before the ratios are trusted
    every: int = 25  # once settled, one render in `every` measures another candidate
    spread: float = 2.5  # blocks predicted this many times costlier than the model's pick are never tried
    warmup: int = 1  # first renders not measured (one-off allocations)
    chunks: tuple[int, ...] = CHUNKS  # chunk sizes tried with each block
    ratios: dict[Layout, deque] = field(default_factory=dict)
    used: dict[Layout, int] = field(default_factory=dict)

    @property
    def calls(self) -> int:
        """Renders chosen for so far (those with measure=False are not counted)."""
        return sum(self.used.values())

    def choose(self, ext: Extents, width: int, height: int, measure: bool = True) -> tuple[Layout, Meter | None]:
        """The layout for this render, and the meter its timed parts report to (None: not measured).
        measure=False (a render that will not be timed, such as an evaluation inside training): the
        best layout known so far, counted nowhere."""
        cost = block_costs(ext, width, height)
        if not cost:
            return Layout(8), None
        best = min(cost.values())
        blocks = [b for b in sorted(cost, key=cost.get) if cost[b] <= self.spread * best]
        cand = [Layout(b, c) for b in blocks for c in self.chunks]
        settled = all(len(self.ratios.get(x, ())) >= self.samples for x in cand)
        ranked = sorted(cand, key=lambda x: self.ratio(x) * cost[x.block]) if settled else cand
        if not measure:
            return ranked[0], None
        call = self.calls + 1
        if call <= self.warmup:
            layout, meter = cand[0], None
        elif not settled:
            layout = next(x for x in cand if len(self.ratios.get(x, ())) < self.samples)
            meter = Meter(self, layout, cost[layout.block])
        else:
            layout = ranked[0]
            if len(ranked) > 1 and call % self.every == 0:  # the others, in turn, now and then
                others = ranked[1:]
                layout = others[(call // self.every) % len(others)]
            meter = Meter(self, layout, cost[layout.block])
        self.used[layout] = self.used.get(layout, 0) + 1
        return layout, meter

    def ratio(self, layout: Layout) -> float:
        """Median measured seconds per unit of predicted cost for `layout`."""
        r = sorted(self.ratios[layout])
        return r[len(r) // 2]

    def record(self, layout: Layout, ratio: float) -> None:
        self.ratios.setdefault(layout, deque(maxlen=5)).append(ratio)

    def summary(self) -> dict:
        """What train.json keeps: renders per block, the measured ns per unit of predicted cost of
        each block at its best chunk size, and that chunk size."""
        used: dict[str, int] = {}
        for x, n in self.used.items():
            used[str(x.block)] = used.get(str(x.block), 0) + n
        best = {}
        for x in self.ratios:
            if self.ratios[x] and (x.block not in best or self.ratio(x) < self.ratio(best[x.block])):
                best[x.block] = x
        return {"used": {k: n for k, n in used.items() if n},
                "ns_per_cost": {str(b): round(1e9 * self.ratio(x), 4) for b, x in sorted(best.items())},
                "chunk": {str(b): x.chunk for b, x in sorted(best.items())}}
