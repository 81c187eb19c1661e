"""Everything a training run carries from step to step, and its checkpoint form.

`TrainState` = parameters (one `nn.Parameter` per attribute, rows = Gaussians),
one Adam per attribute, the density-control strategy and its state, the view
sampler and the loop's counters. `state_to_checkpoint` / `state_from_checkpoint`
convert it to and from plain tensors losslessly, which is what makes an
interrupted-and-resumed CPU run end bitwise equal to an uninterrupted one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from ..gaussians import Gaussians
from ..io.checkpoint import Checkpoint, save_checkpoint
from ..strategy import DefaultStrategy, DefaultStrategyConfig, DefaultStrategyState
from .config import TrainConfig

PARAM_ORDER = ("means", "quats", "log_scales", "opacity_logits", "sh0", "shN")


@dataclass
class TrainState:
    params: dict[str, nn.Parameter]
    optimizers: dict[str, torch.optim.Optimizer]
    strategy: DefaultStrategy
    sstate: DefaultStrategyState
    view_gen: torch.Generator  # view order only
    perm: Tensor  # [n_train] current epoch's view order
    pos: int  # next index into perm
    step: int = 0  # optimiser steps done
    sh_cap: int = 3  # highest SH degree in use (lowered by --sh-degree auto)
    elapsed_s: float = 0.0  # training seconds so far (evaluation excluded)
    bad_steps: int = 0  # non-finite steps skipped, total
    bad_run: int = 0  # ... consecutive
    extra: dict[str, Any] = field(default_factory=dict)  # compaction / sh-auto records
    loss_acc: Tensor = field(default_factory=lambda: torch.zeros(2, dtype=torch.float64))  # [sum, count] since the last log line

    @property
    def num_gaussians(self) -> int:
        return int(self.params["means"].shape[0])

    def active_sh_degree(self, step: int, interval: int) -> int:
        """3DGS raises the degree by one every `interval` steps."""
        return min(step // max(interval, 1), self.sh_cap)

    def sh(self) -> Tensor:  # [N, (d+1)^2, 3]
        if "shN" in self.params:
            return torch.cat([self.params["sh0"], self.params["shN"]], dim=1)
        return self.params["sh0"]

    def gaussians(self) -> Gaussians:
        p = self.params
        return Gaussians(p["means"], p["quats"], p["log_scales"], p["opacity_logits"], self.sh()).detach()

    def next_view(self, n: int) -> int:
        """Views in shuffled epochs, like 3DGS's refilled camera stack."""
        if self.pos >= self.perm.numel():
            self.perm = torch.randperm(n, generator=self.view_gen)
            self.pos = 0
        i = int(self.perm[self.pos])
        self.pos += 1
        return i


def strategy_config(cfg: TrainConfig) -> DefaultStrategyConfig:
    return DefaultStrategyConfig(
        refine_start=cfg.refine_start, refine_stop=cfg.refine_stop, refine_every=cfg.refine_every,
        reset_every=cfg.reset_every, grow_grad2d=cfg.grow_grad2d, max_gaussians=cfg.max_gaussians,
    )


def means_lr(cfg: TrainConfig, step: int, extent: float) -> float:
    """Exponential (log-linear) decay from lr_means to lr_means_final, times the
    scene extent, over `iterations`; held at the final value afterwards."""
    t = min(max(step / max(cfg.iterations, 1), 0.0), 1.0)
    return math.exp(math.log(cfg.lr_means) * (1 - t) + math.log(cfg.lr_means_final) * t) * extent


def _make_optimizers(params: dict[str, nn.Parameter], cfg: TrainConfig, extent: float,
                     device: torch.device) -> dict[str, torch.optim.Optimizer]:
    lrs = {
        "means": cfg.lr_means * extent,
        "quats": cfg.lr_quats,
        "log_scales": cfg.lr_scales,
        "opacity_logits": cfg.lr_opacity,
        "sh0": cfg.lr_sh0,
        "shN": cfg.lr_sh0 / cfg.lr_shN_div,
    }
    # fused: one kernel per tensor (CPU and CUDA), the fastest Adam torch has.
    return {k: torch.optim.Adam([p], lr=lrs[k], eps=cfg.adam_eps, fused=True) for k, p in params.items()}


def new_state(g: Gaussians, cfg: TrainConfig, extent: float, device: torch.device, n_train: int) -> TrainState:
    """A fresh run from initial Gaussians `g` (SH at the trained degree)."""
    g = g.with_sh_degree(cfg.max_sh_degree).to(device, torch.float32)
    raw = {"means": g.means, "quats": g.quats, "log_scales": g.log_scales, "opacity_logits": g.opacity_logits,
           "sh0": g.sh[:, :1]}
    if cfg.max_sh_degree > 0:
        raw["shN"] = g.sh[:, 1:]
    params = {k: nn.Parameter(v.detach().clone().contiguous()) for k, v in raw.items()}
    strategy = DefaultStrategy(strategy_config(cfg), extent)
    view_gen = torch.Generator().manual_seed(int(cfg.seed) + 1)
    return TrainState(
        params=params,
        optimizers=_make_optimizers(params, cfg, extent, device),
        strategy=strategy,
        sstate=strategy.initial_state(len(g), device, cfg.seed),
        view_gen=view_gen,
        perm=torch.randperm(n_train, generator=view_gen),
        pos=0,
        sh_cap=cfg.max_sh_degree,
        loss_acc=torch.zeros(2, dtype=torch.float64, device=device),
    )


def save_state(path: Path, state: TrainState, cfg: TrainConfig, interval: int) -> Path:
    """Write the state as a checkpoint (atomic). The active SH degree recorded is
    the one the model renders with now, so load_gaussians drops unused bands."""
    rng: dict[str, Any] = {"torch": torch.get_rng_state(), "view": state.view_gen.get_state()}
    if torch.cuda.is_available() and state.params["means"].is_cuda:
        rng["cuda"] = torch.cuda.get_rng_state_all()
    return save_checkpoint(
        path,
        step=state.step,
        gaussians=state.gaussians(),
        sh_degree=state.active_sh_degree(state.step, interval),
        optimizer={k: o.state_dict() for k, o in state.optimizers.items()},
        strategy=state.sstate.state_dict(),
        rng=rng,
        config=cfg.to_dict(),
        extra={
            "perm": state.perm, "pos": state.pos, "sh_cap": state.sh_cap, "elapsed_s": state.elapsed_s,
            "bad_steps": state.bad_steps, "bad_run": state.bad_run, "records": state.extra,
            "param_names": list(state.params), "loss_acc": state.loss_acc,
        },
    )


def state_from_checkpoint(ck: Checkpoint, cfg: TrainConfig, extent: float, device: torch.device) -> TrainState:
    """Rebuild the exact state a checkpoint was written from."""
    ex = ck.extra
    names = ex.get("param_names") or (["means", "quats", "log_scales", "opacity_logits", "sh0"]
                                      + (["shN"] if ck.gaussians.sh.shape[1] > 1 else []))
    g = ck.gaussians.to(device)
    raw = {"means": g.means, "quats": g.quats, "log_scales": g.log_scales, "opacity_logits": g.opacity_logits,
           "sh0": g.sh[:, :1], "shN": g.sh[:, 1:]}
    params = {k: nn.Parameter(raw[k].clone().contiguous()) for k in names}
    optimizers = _make_optimizers(params, cfg, extent, device)
    for k, o in optimizers.items():
        if k in ck.optimizer:
            o.load_state_dict(ck.optimizer[k])
    strategy = DefaultStrategy(strategy_config(cfg), extent)
    sstate = strategy.initial_state(len(g), device, cfg.seed)
    if ck.strategy:
        sstate.load_state_dict(ck.strategy)
    view_gen = torch.Generator()
    if "view" in ck.rng:
        view_gen.set_state(ck.rng["view"])
    if "torch" in ck.rng:
        torch.set_rng_state(ck.rng["torch"])
    if "cuda" in ck.rng and torch.cuda.is_available() and device.type == "cuda":
        torch.cuda.set_rng_state_all(ck.rng["cuda"])
    return TrainState(
        params=params,
        optimizers=optimizers,
        strategy=strategy,
        sstate=sstate,
        view_gen=view_gen,
        perm=ex.get("perm", torch.zeros(0, dtype=torch.long)),
        pos=int(ex.get("pos", 0)),
        step=ck.step,
        sh_cap=int(ex.get("sh_cap", ck.sh_degree)),
        elapsed_s=float(ex.get("elapsed_s", 0.0)),
        bad_steps=int(ex.get("bad_steps", 0)),
        bad_run=int(ex.get("bad_run", 0)),
        extra=dict(ex.get("records") or {}),
        loss_acc=ex.get("loss_acc", torch.zeros(2, dtype=torch.float64)).to(device),
    )


def sh_bases_stored(state: TrainState) -> int:
    return 1 + (int(state.params["shN"].shape[1]) if "shN" in state.params else 0)


