"""The 3DGS adaptive density control (Kerbl et al. 2023, sec. 5.2), with a budget.

`step_post_backward` runs after the optimiser step; it accumulates the view-space
gradient and, on refinement steps, clones, splits, prunes and resets through `ops`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor

from ..options import MODEL, opt
from . import ops
from .base import RefineConfig, RefineStats, RowState, Splats, StepInfo, Strategy


@dataclass(frozen=True)
class DefaultStrategyConfig(RefineConfig):
    opacity_reset: int = opt(
        3000, "While densifying, lower every opacity to reset_opacity every this many steps, as 3DGS does against "
        "floaters near the cameras; Gaussians that are too large are pruned only after the first (0: never, and no "
        "size pruning).", group=MODEL, at_least=0, steps="schedule")
    grow_grad2d: float = opt(2e-4, "Average |d loss / d mean2d| in NDC units that triggers growth.", more_than=0)
    grow_scale3d: float = opt(0.01, "x extent: larger Gaussians split, smaller ones clone (3DGS's percent_dense).",
                              more_than=0)
    split_samples: int = opt(2, "Gaussians a split makes.", at_least=1)
    prune_opacity: float = opt(0.005, "Gaussians below this opacity are pruned.", at_least=0, less_than=1)
    prune_scale3d: float = opt(0.1, "x extent: a world-space size that is too large (after the first reset).",
                               more_than=0)
    # 3DGS's fixed 20 px assumes ~1-1.6k px images; a fraction keeps its meaning at 200 px
    prune_scale2d: float = opt(0.15, "Screen radius / max(W, H) that is too large (after the first reset).",
                               more_than=0)
    reset_opacity: float = opt(0.01, "Opacities are clamped to at most this at a reset.", more_than=0, less_than=1)


@dataclass
class DefaultStrategyState(RowState):
    ROWS: ClassVar[tuple[str, ...]] = ("grad2d", "count", "radii")
    REDUCE: ClassVar[dict[str, str]] = {"grad2d": "sum", "count": "sum", "radii": "max"}

    grad2d: Tensor  # [N] accumulated view-space gradient norms
    count: Tensor  # [N] number of views each Gaussian was visible in
    radii: Tensor  # [N] largest screen radius seen, as a fraction of max(W, H)
    generator: torch.Generator  # split sampling

    def reset(self) -> None:
        for name in self.ROWS:
            getattr(self, name).zero_()


class DefaultStrategy(Strategy):
    name = "default"

    def __init__(self, config: DefaultStrategyConfig, scene_extent: float,
                 scene_center: Tensor | None = None) -> None:  # scene_center [3]
        """`scene_center` given: a Gaussian farther than the extent from it may be as much
        larger than `prune_scale3d` x extent as it is farther (an angular limit, for far
        content such as --init-far's sphere); None: 3DGS's world-space limit."""
        self.config = config
        self.scene_extent = float(scene_extent)
        self.scene_center = scene_center

    def initial_state(self, n: int, device: torch.device, seed: int = 0) -> DefaultStrategyState:
        gen = torch.Generator(device=device)
        gen.manual_seed(int(seed) + 0x5EED)  # its own stream: densification never shifts view sampling
        z = torch.zeros(n, device=device)
        return DefaultStrategyState(z, z.clone(), z.clone(), gen)

    def active(self, step: int) -> bool:
        return step < self.config.refine_stop

    def step_pre_backward(self, splats: Splats, state: DefaultStrategyState, step: int, info: StepInfo) -> None:
        """Ask autograd to keep the screen-space mean gradient we accumulate (no loss term)."""
        if self.active(step) and info.render.means2d.requires_grad:
            info.render.means2d.retain_grad()

    def step_post_backward(
        self, splats: Splats, state: DefaultStrategyState, step: int, info: StepInfo
    ) -> RefineStats:
        cfg = self.config
        n = len(splats)
        stats = RefineStats(step=step, before=n, after=n)
        if not self.active(step):
            return stats
        if info.finite:
            self._accumulate(state, info)
        if step > cfg.refine_start and step % cfg.refine_every == 0:
            info.combine(state)  # every rank decides from every rank's views
            self._refine(splats, state, step, stats)
        if cfg.opacity_reset and step % cfg.opacity_reset == 0:
            # Clamp every opacity low so that the following densification has to
            # re-earn each Gaussian's opacity: floaters near cameras fade and get pruned.
            lim = math.log(cfg.reset_opacity / (1 - cfg.reset_opacity))
            ops.set_rows(splats, "opacity_logits", lambda v: v.clamp_max(lim))
            stats.reset_opacity = True
        stats.after = len(splats)
        return stats

    @torch.no_grad()
    def _accumulate(self, state: DefaultStrategyState, info: StepInfo) -> None:
        r = info.render
        g = r.screen_grad()
        if g is None:
            return
        # Pixels -> NDC (x_ndc spans 2 over W pixels): the 2e-4 threshold is in NDC.
        scale = torch.tensor([info.width / 2.0, info.height / 2.0], device=g.device, dtype=g.dtype)
        norm = (g * scale).norm(dim=-1)  # [N]
        vis = r.visible
        state.grad2d += torch.where(vis, norm, torch.zeros_like(norm))
        state.count += vis.to(state.count.dtype)
        rel = r.radii.to(state.radii.dtype) / float(max(info.width, info.height))
        torch.maximum(state.radii, torch.where(vis, rel, torch.zeros_like(rel)), out=state.radii)

    @torch.no_grad()
    def _refine(self, splats: Splats, state: DefaultStrategyState, step: int, stats: RefineStats) -> None:
        cfg = self.config
        params = splats.params
        n = stats.before
        opacity = torch.sigmoid(params["opacity_logits"])  # [N]
        max_scale = params["log_scales"].exp().amax(dim=-1)  # [N] world units
        prune = opacity < cfg.prune_opacity
        if cfg.opacity_reset and step > cfg.opacity_reset:  # 3DGS checks size only once a reset has happened
            limit = torch.full_like(max_scale, cfg.prune_scale3d * self.scene_extent)
            if self.scene_center is not None:
                far = (params["means"].detach() - self.scene_center).norm(dim=-1) / self.scene_extent
                limit = limit * far.clamp_min(1.0)
            prune |= max_scale > limit
            prune |= state.radii > cfg.prune_scale2d
        avg = state.grad2d / state.count.clamp_min(1)  # [N]
        grow = (avg > cfg.grow_grad2d) & ~prune
        small = max_scale <= cfg.grow_scale3d * self.scene_extent
        if cfg.max_gaussians is not None:
            # Every candidate adds one Gaussian (a clone, or a split's net extra one
            # when split_samples == 2); keep the highest-gradient ones that fit.
            per = torch.where(small, 1, cfg.split_samples - 1)
            room = cfg.max_gaussians - (n - int(prune.sum()))
            cand = grow.nonzero().squeeze(1)
            if int(per[cand].sum()) > room:
                order = cand[torch.argsort(avg[cand], descending=True, stable=True)]
                fits = torch.cumsum(per[order], 0) <= max(room, 0)
                grow = torch.zeros_like(grow)
                grow[order[fits]] = True
                stats.held_by_budget = int((~fits).sum())
        clone = grow & small
        split = grow & ~small
        stats.cloned, stats.split, stats.pruned = int(clone.sum()), int(split.sum()), int(prune.sum())
        if stats.cloned + stats.split + stats.pruned:
            rows = ops.cat_rows([ops.clone_rows(params, clone),
                                 ops.split_rows(params, split, state.generator, cfg.split_samples)])
            ops.keep(splats, ~(prune | split))
            ops.append(splats, rows)
        state.reset()  # 3DGS restarts the statistics after every refinement
