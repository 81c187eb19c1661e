"""3D Gaussian Splatting as Markov Chain Monte Carlo (Kheradmand et al., NeurIPS 2024).

A fixed budget instead of heuristics: the model grows by a fixed fraction every
`refine_every` steps until it reaches `cap` Gaussians, and Gaussians that have died
(opacity below `min_opacity`) are moved onto live ones, drawn in proportion to their
opacity. A Gaussian drawn k times becomes k + 1 Gaussians whose opacity and scale are
set so that their sum renders like the one did (the paper's relocation, eq. 9); the
copies are then placed at draws from their source Gaussian, as 3DGS places a split's
halves (the paper leaves them on its centre, where identical copies get nearly the same
gradients and separate slowly, which cost held-out PSNR on lego), and, like those halves,
they and their source shrink by 1.6: at full size the spread copies cover more than
their source did, and the larger Gaussians cost render time. Growth ends with the
refinement window, relocation goes on to `relocate_until` of the run, so that
Gaussians that die late are reused instead of wasting the budget. A Gaussian that no
training view drew over a sweep of `SWEEP_EPOCHS` epochs of the views is lost, and moved
like a dead one: the noise below walks the nearly transparent ones away, and off every
view nothing (no photo, no penalty) brings one back or lets it die (on 40 photos of a
landmark, 23-46% of the budget had left every view by the end, some 90,000 camera
extents away, where positions quantised to the model's range lost the rest of it).
After every optimiser step, positions get noise shaped by each Gaussian's own covariance and
gated to the nearly transparent ones (so the sampler explores where the scene is
empty). L1 penalties on opacity and scale are added to the gradients before the
loss's backward (they accumulate into the same `.grad`), which keeps Gaussians small
and lets the unneeded ones die and be reused. They stop at `reg_until` of the run: after
growth they only hold opacities down (on lego at the end, far fewer nearly opaque
Gaussians than the default strategy's), and the fixed set then fits the photos
alone. Every edit goes through `ops`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor

from ..options import opt, override
from ..render.projection import quat_rotate, unit_quat
from . import ops
from .base import RefineConfig, RefineStats, RowState, Splats, StepInfo, Strategy
from .regularize import regularize


@dataclass(frozen=True)
class MCMCStrategyConfig(RefineConfig):
    # its schedule and cap are the RefineConfig fields (the cap: max_gaussians, which it needs)
    opacity_reg: float = override(RefineConfig, "opacity_reg", 0.01)  # the paper's
    scale_reg: float = override(RefineConfig, "scale_reg", 0.01)
    init_opacity: float = opt(0.5, "Opacity of SfM points at the start (random ones: init_opacity), as gsplat's MCMC "
                              "example; +0.38 dB on the demo scene.", more_than=0, less_than=1)
    min_opacity: float = opt(0.02, "Below this a Gaussian is dead and relocated (lego at 2k steps: the paper's 0.005 "
                             "29.65 dB, 0.01 29.99, 0.02 30.22).", more_than=0, less_than=1)
    growth: float = opt(0.05, "The count grows by at least this fraction per refinement, up to the cap ...", at_least=0)
    grow_until: float = opt(0.4, "... and fast enough to reach it by this fraction of the refinement window, or of "
                            "what is left of it for a cap raised later (0.6 before: lego +0.10 dB at the fast preset; "
                            "fox 31.94 against 31.84 dB, not in one run).",
                            at_least=0, at_most=1)
    noise_lr: float = opt(5e5, "Position noise = this x the means' learning rate x covariance x gate.", at_least=0)
    noise_gate_k: float = opt(100.0, "Gate = sigmoid(k (1 - opacity - (1 - min_opacity))).", at_least=0)
    max_ratio: int = opt(51, "One relocation splits a Gaussian into at most this many.", at_least=1)
    relocate_until: float = opt(0.95, "Relocation goes on to this fraction of the run (growth stops with the "
                                "refinement window; lego +0.42 dB).", at_least=0, at_most=1)
    reg_until: float = opt(0.6, "The penalties act until this fraction of the run (1: all of it, the paper's; fast "
                           "preset: lego +0.27 dB, fox +0.12).", at_least=0, at_most=1)
    spread: float = opt(1.0, "Copies go to a draw from their source Gaussian x this (0: on top of it, the paper's; "
                        "lego +1.46 dB).", at_least=0)
    shrink: float = opt(1.6, "... then they and their source get the scale / this, as 3DGS's split halves (1: the "
                        "paper's; lego, fast preset: 34.73 dB against 34.00, in 0.91x the default strategy's time "
                        "beside it).", at_least=1)


# A sweep for lost Gaussians spans this many epochs of the training views (the views come in
# shuffled epochs: any window of two holds every view once at least).
SWEEP_EPOCHS = 2


@dataclass
class MCMCStrategyState(RowState):
    generator: torch.Generator  # relocation and noise sampling
    drawn: Tensor  # [N] float: the views that drew each Gaussian in this sweep (summed over ranks)
    tracked: Tensor  # [N] float: 1 for the Gaussians that were there when the sweep began (new rows 0)
    sweep_from: int = 0  # the step the sweep began at

    ROWS: ClassVar[tuple[str, ...]] = ("drawn", "tracked")
    REDUCE: ClassVar[dict[str, str]] = {"drawn": "sum"}


def relocation(opacity: Tensor, scales: Tensor, ratio: Tensor, max_ratio: int) -> tuple[Tensor, Tensor]:
    """New opacity [M] and scales [M, 3] for Gaussians each replaced by `ratio` [M] copies,
    so that the copies, drawn one over another, match the original at its centre
    (Kheradmand et al. eq. 9): o' = 1 - (1 - o)^(1/n) and
    s' = s * o / sum_{i=1..n} sum_{k=0..i-1} C(i-1, k) (-1)^k o'^(k+1) / sqrt(k+1)."""
    n = ratio.clamp(1, max_ratio).to(opacity.dtype)
    new_o = 1.0 - (1.0 - opacity).clamp_min(0.0) ** (1.0 / n)
    denom = torch.zeros_like(opacity)
    top = int(n.max()) if n.numel() else 1
    for i in range(1, top + 1):
        inner = torch.zeros_like(opacity)
        for k in range(i):
            inner = inner + math.comb(i - 1, k) * (-1) ** k * new_o ** (k + 1) / math.sqrt(k + 1)
        denom = denom + torch.where(n >= i, inner, torch.zeros_like(inner))
    coef = opacity / denom.clamp_min(1e-12)
    return new_o, scales * coef[:, None]


class MCMCStrategy(Strategy):
    name = "mcmc"

    def __init__(self, config: MCMCStrategyConfig, relocate_stop: int | None = None,
                 reg_stop: int | None = None, views: int | None = None) -> None:
        """Growth in (refine_start, refine_stop) to `config.max_gaussians`; relocation until
        `relocate_stop` (default: refine_stop); the penalties before step `reg_stop` (default:
        every step); lost Gaussians found over sweeps of SWEEP_EPOCHS x `views` steps (None:
        not looked for)."""
        if config.max_gaussians is None:
            raise ValueError("MCMCStrategy needs config.max_gaussians")
        self.config = config
        self.cap = config.max_gaussians
        self.refine_start, self.refine_stop, self.refine_every = config.refine_start, config.refine_stop, config.refine_every
        self.relocate_stop = max(self.refine_stop, relocate_stop or 0)
        self.reg_stop = reg_stop
        self.sweep = None if views is None else SWEEP_EPOCHS * max(1, views)

    def initial_state(self, n: int, device: torch.device, seed: int = 0) -> MCMCStrategyState:
        gen = torch.Generator(device=device)
        gen.manual_seed(int(seed) + 0x3C3C)  # its own stream: never shifts view sampling
        return MCMCStrategyState(gen, torch.zeros(n, device=device), torch.ones(n, device=device))

    def step_pre_backward(self, splats: Splats, state: MCMCStrategyState, step: int,
                          info: StepInfo) -> Tensor | None:
        """The penalties on the Gaussians the view draws (regularize.py says why those alone), a
        term of the step's loss; none from `reg_stop` on."""
        if self.reg_stop is None or step < self.reg_stop:
            return regularize(splats.params, self.config.opacity_reg, self.config.scale_reg, info.render.visible)
        return None

    def step_post_backward(self, splats: Splats, state: MCMCStrategyState, step: int, info: StepInfo) -> RefineStats:
        n = len(splats)
        stats = RefineStats(step=step, before=n, after=n)
        state.drawn += info.render.visible.to(state.drawn.dtype)
        if self.refine_start < step < self.relocate_stop and step % self.refine_every == 0:
            lost = self._lost(state, step, info)
            stats.pruned = self._relocate(splats, state, lost)  # moved, not removed: logged as pruned-and-cloned
            stats.cloned = self._grow(splats, state, step) if step < self.refine_stop else 0
            stats.cloned += stats.pruned
        if info.finite:
            self._noise(splats, state)
        stats.after = len(splats)
        return stats

    def _lost(self, state: MCMCStrategyState, step: int, info: StepInfo) -> Tensor | None:  # -> [N] bool
        """At the end of a sweep, the Gaussians that were there all through it and that no
        view drew (every rank's views: `combine`); a new sweep begins. None mid-sweep."""
        if self.sweep is None or step - state.sweep_from < self.sweep:
            return None
        info.combine(state)
        lost = (state.tracked > 0) & (state.drawn == 0)
        state.drawn.zero_()
        state.tracked.fill_(1.0)
        state.sweep_from = step
        return lost

    @torch.no_grad()
    def _relocate(self, splats: Splats, state: MCMCStrategyState, lost: Tensor | None = None) -> int:
        opacity = torch.sigmoid(splats.params["opacity_logits"])
        dead = opacity <= self.config.min_opacity
        if lost is not None:
            dead |= lost
        n_dead = int(dead.sum())
        if n_dead == 0 or n_dead == len(opacity):
            return 0
        alive = (~dead).nonzero().squeeze(1)
        src = alive[torch.multinomial(opacity[alive], n_dead, replacement=True, generator=state.generator)]
        rows = self._split_into(splats, src)
        dst = dead.nonzero().squeeze(1)
        ops.replace_rows(splats, dst, self._copies(rows, src, state))
        return n_dead

    @torch.no_grad()
    def _grow(self, splats: Splats, state: MCMCStrategyState, step: int) -> int:
        n = len(splats)
        add = min(self.cap, int(math.floor(n * (1.0 + self.growth_rate(n, step))))) - n
        if add <= 0:
            return 0
        opacity = torch.sigmoid(splats.params["opacity_logits"])
        src = torch.multinomial(opacity, add, replacement=True, generator=state.generator)
        rows = self._split_into(splats, src)
        ops.append(splats, self._copies(rows, src, state))
        return add

    def growth_rate(self, n: int, step: int) -> float:
        """The fraction to grow by at refinement `step`: at least `growth`, and enough to
        reach the cap by `grow_until` of the refinement window at a constant rate (the
        paper's 5% per 100 steps fills 30k-step budgets; short CPU schedules need more). A cap
        raised after that (--time-budget's curve and its raise) is reached by `grow_until` of what
        is left of the window, not by its end, which a plan that shrinks the run brings forward (lego
        raised to 72,000 in 200 s grew to 63,028: the window planned to end at step 1,115 ended at 951)."""
        until = self.config.grow_until
        target = self.refine_start + until * (self.refine_stop - self.refine_start)
        left = math.floor((target - step) / self.refine_every) + 1  # refinements until the target, this one included
        if left <= 0:
            left = math.floor(until * (self.refine_stop - 1 - step) / self.refine_every) + 1
        if n <= 0 or n >= self.cap or left <= 0:
            return self.config.growth
        return max(self.config.growth, (self.cap / n) ** (1.0 / left) - 1.0)

    def _split_into(self, splats: Splats, src: Tensor) -> dict[str, Tensor]:
        """Each drawn Gaussian (index in `src`, repeats allowed) becomes its count + 1
        copies: its own row is rewritten (moments zeroed) and the returned rows
        (indexed like the parameters) are the copies' values."""
        p = splats.params
        n = len(splats)
        count = torch.bincount(src, minlength=n)  # [N]
        idx = count.nonzero().squeeze(1)
        new_o, new_s = relocation(torch.sigmoid(p["opacity_logits"][idx]), p["log_scales"][idx].exp(),
                                  count[idx] + 1, self.config.max_ratio)
        eps = torch.finfo(new_o.dtype).eps
        logits = torch.logit(new_o.clamp(eps, 1 - eps))
        rows = {k: v.detach().clone() for k, v in p.items()}
        rows["opacity_logits"][idx] = logits
        rows["log_scales"][idx] = new_s.clamp_min(1e-12).log()  # the copies are drawn from this Gaussian
        own = {k: v[idx] for k, v in rows.items()}
        own["log_scales"] = own["log_scales"] - math.log(self.config.shrink)
        ops.replace_rows(splats, idx, own)
        return rows

    def _copies(self, rows: dict[str, Tensor], src: Tensor, state: MCMCStrategyState) -> dict[str, Tensor]:
        """The copies' rows ([M] drawn sources), each moved by `spread` x a draw from its
        Gaussian, then shrunk by `shrink`."""
        out = {k: v[src] for k, v in rows.items()}
        if self.config.spread > 0:
            z = torch.randn(out["means"].shape, generator=state.generator, device=src.device, dtype=out["means"].dtype)
            out["means"] = out["means"] + self.config.spread * ops.draws(out["quats"], out["log_scales"], z)
        out["log_scales"] = out["log_scales"] - math.log(self.config.shrink)
        return out

    @torch.no_grad()
    def _noise(self, splats: Splats, state: MCMCStrategyState) -> None:
        cfg = self.config
        p = splats.params
        lr = float(splats.optimizers["means"].param_groups[0]["lr"])
        opacity = torch.sigmoid(p["opacity_logits"])
        gate = torch.sigmoid(cfg.noise_gate_k * ((1.0 - opacity) - (1.0 - cfg.min_opacity)))  # [N]
        z = torch.randn(p["means"].shape, generator=state.generator, device=p["means"].device,
                        dtype=p["means"].dtype)  # drawn for every row: the stream does not depend on opacities
        idx = (gate > 1e-6).nonzero().squeeze(1)  # the nearly transparent: elsewhere the noise is below 1e-6 of it
        q = unit_quat(p["quats"].index_select(0, idx))  # 4 x [M]
        var = p["log_scales"].index_select(0, idx).exp_().square_()  # [M, 3]
        # covariance x z = R diag(var) R^T z, a component at a time, without forming the covariance or R
        zg = z.index_select(0, idx) * (gate.index_select(0, idx) * (cfg.noise_lr * lr))[:, None]  # [M, 3]
        w = quat_rotate(q, zg.unbind(1), inverse=True)
        delta = torch.zeros_like(p["means"])
        delta.index_copy_(0, idx, torch.stack(quat_rotate(q, [vi * wi for vi, wi in zip(var.unbind(1), w)]), 1))
        ops.nudge(splats, "means", delta)
