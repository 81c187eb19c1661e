"""One training step, and nothing around it: render a view, let the strategies prepare,
shade through the image model, take the loss, backpropagate, exchange the gradients and
step the optimisers; `refine` then lets the strategies edit the model.

`Trainer` holds the run's state (parameters, optimisers, strategies, image model: state.py)
and the schedule in force (`cfg`, scaled for the ranks). It never prints or writes a file
(`prof`, train --profile, only times its stages): signals, out-of-memory handling,
checkpoints, the time plan, events, logs and held-out measurement are the run around it
(loop.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..render import RenderOutput
from ..strategy import Context, RefineStats, StepInfo
from .config import TrainConfig
from .data import TrainData, TrainView
from .distributed import Comm
from .loss import photometric_loss, sparse_depth_loss
from .profile import StepProfile
from .state import TrainState, learning_rates, make_strategies, means_lr
from .transients import kept_pixels


@dataclass
class Batch:
    """What one step trains on: a training view at the step's resolution and its photo."""

    index: int  # the view's place among the training views (its colour transform, with --appearance)
    view: TrainView  # at the step's resolution
    target: Tensor  # [H, W, 3] float32 in [0, 1]


@dataclass
class StepStats:
    """What one step did."""

    loss: Tensor  # [] the loss, averaged over the ranks, detached (read without a host sync)
    finite: bool  # the loss and every gradient were finite (else the update was skipped and counted)
    stopping: bool  # some rank was signalled (told with the gradients)
    info: StepInfo  # the render and view size, for the strategies' post-backward hooks


def render_view(state: TrainState, view: TrainView, bg: Tensor, sh_degree: int) -> RenderOutput:  # bg [3]
    """The current Gaussians seen from `view` at the training resolution."""
    g = state.drawn()
    return state.render.draw(g.means, g.quats, g.log_scales, g.opacity_logits, g.sh, view.viewmat, view.K,
                      view.camera.width, view.camera.height, bg, sh_degree=sh_degree, antialiased=state.antialiased,
                      block=state.render.block, check=False)  # the step checks every gradient for non-finite values


class Trainer:
    """The model in training and how one step changes it. `comm`: this process's rank of a
    data-parallel run (every rank holds the same state and draws the same view stream);
    `prof`: where the step's time goes (train --profile)."""

    def __init__(self, state: TrainState, cfg: TrainConfig, data: TrainData, ctx: Context,
                 comm: Comm | None = None, prof: StepProfile | None = None) -> None:
        self.state, self.cfg, self.data, self.ctx = state, cfg, data, ctx
        self.comm = comm or Comm()
        self.prof = prof or StepProfile(False)
        self.updating = False  # an optimiser update is under way: the state is not a whole step's

    def reschedule(self, cfg: TrainConfig) -> None:
        """Follow a new schedule (a --time-budget plan), from the next step on. The
        strategies are made again from it: they hold only their settings, and their
        running state (the rows in `state.splats.states`) is kept; the optimisers take its
        learning rates (their moments are kept)."""
        self.cfg = cfg
        self.state.strategies = make_strategies(cfg, self.data.extent, self.ctx)
        lrs = learning_rates(cfg, self.data.extent)
        for name, opt in self.state.optimizers.items():
            opt.param_groups[0]["lr"] = lrs[name]

    def catch_up(self) -> list[RefineStats | None]:
        """On resume: what each strategy does that an uninterrupted run would have done by now."""
        s = self.state
        return [strategy.catch_up(s.splats, st, s.counts.step) for strategy, st in zip(s.strategies, s.splats.states)]

    def next_batch(self, step: int) -> Batch:
        """The next views of the one-process stream, one per rank, dealt out; this rank's."""
        views = [self.state.views.next(len(self.data.train)) for _ in range(self.comm.world)]
        with self.prof.stage("data"):
            view = self.data.train[views[self.comm.rank]].at_scale(self.cfg.train_scale(step))
            return Batch(views[self.comm.rank], view, view.target())

    def step(self, step: int, batch: Batch, stop: bool = False) -> StepStats:
        """Train step `step` (1-based) on `batch`; `stop`: this process was signalled."""
        self.state.optimizers["means"].param_groups[0]["lr"] = means_lr(self.cfg, step, self.data.extent)
        info, loss = self._backward(step, batch)
        with self.prof.stage("optimiser"):
            loss, stopping = self.comm.reduce_step(self.state.trainable(), loss, stop)
            info.finite = _all_finite(loss, self.state)
            self.updating = True
            _optimise(self.state, info.finite)
        self.state.counts.step, self.updating = step, False
        return StepStats(loss.detach(), info.finite, stopping, info)

    def _backward(self, step: int, batch: Batch) -> tuple[StepInfo, Tensor]:  # -> (info, loss [])
        """Render, the strategies' pre-backward hooks, the image model and the loss (with the depth
        term at the view's SfM points, --depth-weight), its gradients."""
        s, cfg, prof = self.state, self.cfg, self.prof
        with prof.stage("render"):
            out = render_view(s, batch.view, self.data.background, s.active_sh_degree(step, cfg.sh_degree_interval))
        info = StepInfo(out, batch.view.camera.width, batch.view.camera.height, combine=self.comm.combine_rows)
        with prof.stage("densification"):
            terms = [strategy.step_pre_backward(s.splats, st, step, info)
                     for strategy, st in zip(s.strategies, s.splats.states)]
        with prof.stage("loss"):
            image, penalty = s.image_model.shade(out.image, batch.index, step, cfg.iterations)
            keep = mask = batch.view.keep
            if cfg.transients == "ignore" and step > cfg.robust.start * cfg.iterations:
                keep = kept_pixels(image, batch.target, keep, cfg.robust)
            loss = photometric_loss(image, batch.target, cfg.lambda_dssim, keep) + penalty
            if cfg.depth_weight > 0 and batch.view.sparse is not None:
                terms.append(cfg.depth_weight * sparse_depth_loss(out.depth, out.alpha, batch.view.sparse,
                                                                  batch.view.viewmat, batch.view.K, mask))
        with prof.stage("backward"):
            # one backward for the whole step: the photometric loss, the image model's penalty, the
            # SfM points' depth term and the strategies' terms; the loss reported is the first two
            sum((t for t in terms if t is not None), loss).backward()
        return info, loss

    def refine(self, step: int, info: StepInfo) -> list[RefineStats | None]:
        """The strategies' post-backward hooks after step `step`'s update (density control,
        model steps; `info.heldout` set when the run measured this step); what each changed."""
        s = self.state
        with self.prof.stage("densification"):
            return [strategy.step_post_backward(s.splats, st, step, info)
                    for strategy, st in zip(s.strategies, s.splats.states)]

    def finish(self) -> None:
        """The strategies' last word on the model, after the run's last step (parameter averaging)."""
        s = self.state
        with self.prof.stage("densification"):
            for strategy, st in zip(s.strategies, s.splats.states):
                strategy.finish(s.splats, st)


def _optimise(state: TrainState, finite: bool) -> None:
    """Adam's step on every parameter when the loss and gradients are finite (else the step is
    skipped and counted: NaN or Inf never reaches the parameters or the moments), then no gradients."""
    if finite:
        for opt in state.all_optimizers():
            opt.step()
        state.counts.bad_run = 0
    else:
        state.counts.bad_steps += 1
        state.counts.bad_run += 1
    for opt in state.all_optimizers():
        opt.zero_grad(set_to_none=True)


def _all_finite(loss: Tensor, state: TrainState) -> bool:  # loss: [] scalar
    """The loss and every gradient finite, in a single host sync. Each gradient is read once, by
    its smallest and largest value (NaN anywhere makes both NaN; an infinity is one of them):
    isfinite(grad).all() wrote a mask as large as the gradients first, several times the cost."""
    checks = [loss.detach().reshape(1)]
    checks += [torch.stack(torch.aminmax(p.grad)) for p in state.trainable().values() if p.grad is not None]
    return bool(torch.isfinite(torch.cat(checks)).all())
