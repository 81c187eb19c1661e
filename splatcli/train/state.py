"""Everything a training run carries from step to step, and its checkpoint form.

`TrainState` = the model (`Splats`: parameters, one Adam per attribute, every strategy's
per-Gaussian state; the strategies; the image model), the view order (`ViewOrder`), the loop's
`Counters`, the time plan and the `RenderSettings`. `save_state` / `state_from_checkpoint` convert
it to and from plain tensors losslessly, which is what makes an interrupted-and-resumed CPU run
end bitwise equal to an uninterrupted one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from ..files.checkpoint import Checkpoint, save_checkpoint
from ..gaussians import Gaussians
from ..render import rasterize
from ..render.backends import Rasterizer
from ..render.blocks import BlockTuner
from ..strategy import (
    AverageStep,
    CompactStep,
    Context,
    DefaultStrategy,
    MCMCStrategy,
    MipFilter,
    RegularizeStep,
    ShAutoStep,
    Splats,
    Strategy,
    SupportPrune,
    sh_degree_of,
)
from ..strategy.mip import GROW_GRAD2D as MIP_GROW_GRAD2D
from .appearance import ImageModel, make_image_model
from .config import TrainConfig
from .plan import TimePlan


@dataclass(frozen=True)
class RenderSettings:
    """How a run draws its training views, fixed when the run starts."""

    draw: Rasterizer = rasterize  # the renderer (render/backends.py): rasterize's signature and result
    block: int | str | BlockTuner = "auto"  # --block: rasterize's block= (a size, "auto": the cost model's, or a tuner)
    compiled: dict[str, Any] | None = None  # --compile: what was resolved, and the compile's figures (train.json)


@dataclass
class Counters:
    """The loop's counts, carried from step to step and through a checkpoint."""

    step: int = 0  # optimiser steps done
    world: int = 1  # data-parallel ranks: each step sees this many views
    elapsed_s: float = 0.0  # training seconds so far (evaluation excluded)
    bad_steps: int = 0  # non-finite steps skipped, total
    bad_run: int = 0  # ... consecutive
    loss_acc: Tensor = field(default_factory=lambda: torch.zeros(2, dtype=torch.float64))  # [sum, count] since the last log line
    refine_acc: dict[str, int] = field(default_factory=dict)  # cloned / split / pruned since the last log line

    @property
    def images(self) -> int:
        """Views seen so far: the step a one-process run would be at (what checkpoints,
        logs and reports count, whatever the number of ranks)."""
        return self.step * self.world

    def record(self) -> dict[str, Any]:
        return {"world": self.world, "elapsed_s": self.elapsed_s, "bad_steps": self.bad_steps, "bad_run": self.bad_run,
                "loss_acc": self.loss_acc, "refine_acc": dict(self.refine_acc)}

    @classmethod
    def from_record(cls, ex: dict[str, Any], images: int, world: int, device: torch.device) -> Counters:
        return cls(step=images // world, world=world, elapsed_s=float(ex.get("elapsed_s", 0.0)),
                   bad_steps=int(ex.get("bad_steps", 0)), bad_run=int(ex.get("bad_run", 0)),
                   loss_acc=ex.get("loss_acc", torch.zeros(2, dtype=torch.float64)).to(device),
                   refine_acc={k: int(v) for k, v in (ex.get("refine_acc") or {}).items()})


@dataclass
class ViewOrder:
    """Training views in shuffled epochs, like 3DGS's refilled camera stack."""

    gen: torch.Generator  # view order only
    perm: Tensor  # [n_train] current epoch's view order
    pos: int = 0  # next index into perm

    def next(self, n: int) -> int:
        if self.pos >= self.perm.numel():
            self.perm = torch.randperm(n, generator=self.gen)
            self.pos = 0
        i = int(self.perm[self.pos])
        self.pos += 1
        return i


@dataclass
class TrainState:
    """The model (`splats`, `strategies`, `image_model`), the view order, the counters,
    the time plan and the render settings: each complete when built."""

    splats: Splats  # parameters, Adam, and the strategies' rows (states[i] belongs to strategies[i])
    strategies: list[Strategy]
    image_model: ImageModel  # --appearance: between a render and its photo
    views: ViewOrder
    counts: Counters
    plan: TimePlan | None = None  # --time-budget
    render: RenderSettings = field(default_factory=RenderSettings)

    @property
    def params(self) -> dict[str, nn.Parameter]:
        return self.splats.params

    @property
    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return self.splats.optimizers

    def trainable(self) -> dict[str, nn.Parameter]:
        """Every tensor a step's backward reaches: the Gaussians' parameters and the image
        model's (what the ranks all-reduce)."""
        return {**self.params, **{f"{self.image_model.name}.{k}": p for k, p in self.image_model.parameters().items()}}

    def all_optimizers(self) -> list[torch.optim.Optimizer]:
        return list(self.optimizers.values()) + self.image_model.optimizers()

    @property
    def num_gaussians(self) -> int:
        return len(self.splats)

    def active_sh_degree(self, step: int, interval: int) -> int:
        """3DGS raises the degree by one every `interval` steps, up to what the parameters hold."""
        return min(step // max(interval, 1), sh_degree_of(self.splats))

    def sh(self) -> Tensor:  # [N, (d+1)^2, 3]
        if "shN" in self.params:
            return torch.cat([self.params["sh0"], self.params["shN"]], dim=1)
        return self.params["sh0"]

    def gaussians(self) -> Gaussians:
        p = self.params
        return Gaussians(p["means"], p["quats"], p["log_scales"], p["opacity_logits"], self.sh()).detach()

    def drawn(self) -> Gaussians:
        """The model as it is drawn, differentiable in the parameters: the scales and
        opacities through every strategy's `shade` (--mip-filter's 3D filter)."""
        p = self.params
        ls, op = p["log_scales"], p["opacity_logits"]
        for s, st in zip(self.strategies, self.splats.states):
            ls, op = s.shade(self.splats, st, ls, op)
        return Gaussians(p["means"], p["quats"], ls, op, self.sh())

    def model(self) -> Gaussians:
        """The model as drawn, without gradients (what a checkpoint's `model()` gives back)."""
        with torch.no_grad():
            return self.drawn().detach()

    @property
    def antialiased(self) -> bool:
        """Whether the model is drawn with the 2D filter (rasterize(antialiased=True))."""
        return any(s.antialiased for s in self.strategies)


def make_strategies(cfg: TrainConfig, extent: float, ctx: Context) -> list[Strategy]:
    """The run's strategies, in the order the loop calls them. Density control never
    acts on the last step of the main schedule (a reset there would be the final
    model) nor during a compaction fine-tune."""
    r = cfg.refine
    stop = min(r.refine_stop, cfg.iterations)
    if cfg.strategy == "mcmc":
        density: Strategy = MCMCStrategy(replace(cfg.mcmc, refine_stop=stop),
                                         min(cfg.iterations, round(cfg.mcmc.relocate_until * cfg.iterations)),
                                         round(cfg.mcmc.reg_until * cfg.iterations), views=len(ctx.views.cameras))
    else:
        # With far points (--init-far) the size limit is an angle: far Gaussians may be large.
        grow = cfg.default.grow_grad2d * (MIP_GROW_GRAD2D if cfg.mip_filter else 1.0)
        density = DefaultStrategy(replace(cfg.default, refine_stop=stop, grow_grad2d=grow), extent,
                                  ctx.views.center if cfg.init_far else None)
    out: list[Strategy] = [density]
    if cfg.strategy == "default" and (cfg.default.opacity_reg > 0 or cfg.default.scale_reg > 0):
        out.append(RegularizeStep(cfg.default.opacity_reg, cfg.default.scale_reg))  # mcmc applies its own
    if cfg.support.prune_views:
        out.append(SupportPrune(cfg.support, r.refine_start, stop, r.refine_every, ctx))
    if cfg.average > 0:  # (its `finish` keeps the averages of the bands --sh-degree auto leaves)
        out.append(AverageStep(cfg.average, cfg.total_steps))
    if cfg.sh_degree == "auto":
        out.append(ShAutoStep(cfg.sh_auto, cfg.iterations, ctx))
    if cfg.compact.enabled:
        cap = cfg.mcmc.max_gaussians if cfg.strategy == "mcmc" else None  # (the default strategy's is only a ceiling)
        out.append(CompactStep(cfg.compact, cfg.iterations, ctx, cap))
    if cfg.mip_filter:  # last: it filters the Gaussians the others left
        out.append(MipFilter(ctx.views.cameras))
    return out


def means_lr(cfg: TrainConfig, step: int, extent: float) -> float:
    """lr_means for the first `lr_hold` of `iterations`, then an exponential (log-linear)
    decay to lr_means_final at the end; held there afterwards. Times the scene extent."""
    t = min(max(step / max(cfg.iterations, 1), 0.0), 1.0)
    t = max(0.0, t - cfg.lr_hold) / (1.0 - cfg.lr_hold)
    lr = math.exp(math.log(cfg.lr_means) * (1 - t) + math.log(cfg.lr_means_final) * t)
    return lr * extent * cfg.lr_scale * cfg.lr_means_scale


def learning_rates(cfg: TrainConfig, extent: float) -> dict[str, float]:
    """Each parameter's learning rate (the means' at step 0: `means_lr` sets it every step)."""
    lrs = {
        "quats": cfg.lr_quats,
        "log_scales": cfg.lr_scales,
        "opacity_logits": cfg.lr_opacity,
        "sh0": cfg.lr_sh0,
        "shN": cfg.lr_sh0 / cfg.lr_shN_div,
    }
    return {"means": means_lr(cfg, 0, extent)} | {k: v * cfg.lr_scale for k, v in lrs.items()}


def _make_optimizers(params: dict[str, nn.Parameter], cfg: TrainConfig, extent: float) -> dict[str, torch.optim.Optimizer]:
    lrs = learning_rates(cfg, extent)
    # fused: one kernel per tensor (CPU and CUDA), the fastest Adam torch has.
    return {k: torch.optim.Adam([p], lr=lrs[k], eps=cfg.adam_eps,
                                betas=(cfg.adam_beta1, cfg.adam_beta2), fused=True) for k, p in params.items()}


def _params(g: Gaussians, names: list[str]) -> dict[str, nn.Parameter]:
    raw = {"means": g.means, "quats": g.quats, "log_scales": g.log_scales, "opacity_logits": g.opacity_logits,
           "sh0": g.sh[:, :1], "shN": g.sh[:, 1:]}
    return {k: nn.Parameter(raw[k].detach().clone().contiguous()) for k in names}


def new_state(g: Gaussians, cfg: TrainConfig, extent: float, device: torch.device, n_train: int,
              ctx: Context, world: int = 1, plan: TimePlan | None = None,
              render: RenderSettings = RenderSettings()) -> TrainState:
    """A fresh run from initial Gaussians `g` (SH at the trained degree)."""
    g = g.with_sh_degree(cfg.max_sh_degree).to(device, torch.float32)
    names = ["means", "quats", "log_scales", "opacity_logits", "sh0"] + (["shN"] if cfg.max_sh_degree > 0 else [])
    params = _params(g, names)
    strategies = make_strategies(cfg, extent, ctx)
    splats = Splats(params, _make_optimizers(params, cfg, extent),
                    [s.initial_state(len(g), device, cfg.seed) for s in strategies])
    gen = torch.Generator().manual_seed(int(cfg.seed) + 1)
    return TrainState(splats, strategies, make_image_model(cfg, n_train, device, ctx.views.centres),
                      ViewOrder(gen, torch.randperm(n_train, generator=gen)),
                      Counters(world=world, loss_acc=torch.zeros(2, dtype=torch.float64, device=device)), plan, render)


def save_state(path: Path, state: TrainState, cfg: TrainConfig) -> Path:
    """Write the state as a checkpoint (atomic), counting steps in views seen, with `cfg`
    the run's config as given (for one process). The active SH degree recorded is
    the one the model renders with now, so `Checkpoint.model()` drops unused bands."""
    rng: dict[str, Any] = {"torch": torch.get_rng_state(), "view": state.views.gen.get_state()}
    if torch.cuda.is_available() and state.params["means"].is_cuda:
        rng["cuda"] = torch.cuda.get_rng_state_all()
    return save_checkpoint(
        path,
        step=state.counts.images,
        gaussians=state.gaussians(),
        sh_degree=state.active_sh_degree(state.counts.images, cfg.sh_degree_interval),
        optimizer={k: o.state_dict() for k, o in state.optimizers.items()},
        strategy={s.name: st.state_dict() for s, st in zip(state.strategies, state.splats.states)},
        rng=rng,
        config=cfg.to_dict(),
        appearance=state.image_model.state_dict() or None,
        extra={"perm": state.views.perm, "pos": state.views.pos, **state.counts.record(),
               "param_names": list(state.params), "plan": state.plan.record() if state.plan is not None else None},
    )


def state_from_checkpoint(ck: Checkpoint, cfg: TrainConfig, extent: float, device: torch.device, n_train: int,
                          ctx: Context, world: int = 1, plan: TimePlan | None = None,
                          render: RenderSettings = RenderSettings()) -> TrainState:
    """Rebuild the exact state a checkpoint was written from (strategies the
    checkpoint has no state for, such as --compact or --appearance added on resume,
    start fresh; `n_train` training views),
    for `world` ranks running `cfg` (already scaled for them): the step resumes at the
    views seen divided by the ranks, whatever the number of ranks that wrote it."""
    ex = ck.extra
    names = ex.get("param_names") or (["means", "quats", "log_scales", "opacity_logits", "sh0"]
                                      + (["shN"] if ck.gaussians.sh.shape[1] > 1 else []))
    g = ck.gaussians.to(device)
    params = _params(g, names)
    optimizers = _make_optimizers(params, cfg, extent)
    for k, o in optimizers.items():
        if k in ck.optimizer:
            o.load_state_dict(ck.optimizer[k])
    strategies = make_strategies(cfg, extent, ctx)
    states = [s.initial_state(len(g), device, cfg.seed) for s in strategies]
    for s, st in zip(strategies, states):
        if isinstance(ck.strategy.get(s.name), dict):
            st.load_state_dict(ck.strategy[s.name])
    gen = torch.Generator()
    if "view" in ck.rng:
        gen.set_state(ck.rng["view"])
    if "torch" in ck.rng:
        torch.set_rng_state(ck.rng["torch"])
    if "cuda" in ck.rng and torch.cuda.is_available() and device.type == "cuda":
        torch.cuda.set_rng_state_all(ck.rng["cuda"])
    image_model = make_image_model(cfg, n_train, device, ctx.views.centres)
    if ck.appearance.get("kind") == image_model.name:  # (a model added on resume starts fresh)
        image_model.load_state_dict(ck.appearance, str(ck.path))
    return TrainState(Splats(params, optimizers, states), strategies, image_model,
                      ViewOrder(gen, ex.get("perm", torch.zeros(0, dtype=torch.long)), int(ex.get("pos", 0))),
                      Counters.from_record(ex, ck.step, world, device), plan, render)


def time_plan(cfg: TrainConfig, record: Any = None, n_train: int = 0, world: int = 1) -> TimePlan | None:
    """The --time-budget plan of `cfg` (one process's config): a new one, or the one a
    checkpoint recorded, with the budget now given. It prices a --compact cut at the largest share
    of the `n_train` training views one of `world` processes scores (the others wait for it), so
    that every rank plans alike (a rank that planned its own share ran other steps: a collective
    mismatch)."""
    if cfg.time_budget is None:
        return None
    scored = -(-n_train // world)
    if isinstance(record, dict):
        plan = TimePlan.from_record(record)
        plan.budget_s, plan.scored = float(cfg.time_budget), scored
        return plan
    return TimePlan.start(cfg, scored)
