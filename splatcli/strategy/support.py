"""Prune what too few training views see: a Gaussian whose centre lies in the frustum of
fewer than `prune_views` training cameras can only explain those few photos, and shows
up as a floater in every other view (issue 15's overfitting study, docs/guide.md
"Held-out quality over time"). Runs on the density strategy's refinement schedule."""

from __future__ import annotations

from dataclasses import dataclass

from ..options import MODEL, opt
from . import ops
from .base import Context, RefineStats, Splats, StepInfo, Strategy


@dataclass(frozen=True)
class SupportConfig:
    prune_views: int = opt(0, "While densifying, prune Gaussians that fewer than this many training views see (they "
                           "can only explain those photos: floaters elsewhere; 0: off).", group=MODEL, at_least=0)


class SupportPrune(Strategy):
    name = "support"

    def __init__(self, config: SupportConfig, refine_start: int, refine_stop: int, refine_every: int,
                 ctx: Context) -> None:
        self.config = config
        self.refine_start, self.refine_stop, self.refine_every = refine_start, refine_stop, refine_every
        self.ctx = ctx

    def step_post_backward(self, splats: Splats, state: object, step: int, info: StepInfo) -> RefineStats | None:
        if not (self.refine_start < step <= self.refine_stop and step % self.refine_every == 0):
            return None
        n = len(splats)
        seen = self.ctx.views.seeing(splats.params["means"].detach())
        drop = seen < self.config.prune_views
        stats = RefineStats(step=step, before=n, pruned=int(drop.sum()), after=n)
        if stats.pruned and stats.pruned < n:
            ops.keep(splats, ~drop)
            stats.after = len(splats)
        else:
            stats.pruned = 0
        return stats
