"""Model only what the scene needs: the first Gaussians (within the budget), and
what happens when the main schedule ends: `--sh-degree auto` and `--compact`.

--sh-degree auto: render a validation subset of the *training* views with the
  SH truncated to each degree and keep the lowest degree whose PSNR is within
  `sh_auto_tol_db` of the full degree; the unused bands are dropped from the
  parameters (so they are neither stored nor exported).
--compact: rank Gaussians by their total blending weight sum_pixels alpha_i T_i
  over the training views and keep the top `compact_keep` fraction, in
  `compact_rounds` cuts spread over the first half of a `compact_finetune`-step
  fine-tune (no densification; the loop runs the steps, `at_step` the cuts).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ..train.data import TrainData, View
from ..events import EventSink, Note, emit
from ..gaussians import Gaussians
from ..train.init import gaussians_from_ply, gaussians_from_points, random_points, subsample, subsample_index
from ..io.ply import ply_bytes
from ..project import Project
from ..render.weights import blending_weights as render_weights
from . import ops
from ..train.config import TrainConfig
from ..train.state import TrainState


def initial_gaussians(cfg: TrainConfig, data: TrainData, device: torch.device) -> Gaussians:
    """From --init-ply, else the SfM points, else random points in the scene box
    (seeded); then a seeded subset if there are more than --max-gaussians."""
    budget = cfg.max_gaussians
    if cfg.init_ply:
        g = gaussians_from_ply(cfg.init_ply, cfg.max_sh_degree, device)
        return subsample(g, budget, cfg.seed) if budget is not None else g
    if len(data.points):
        pts = torch.as_tensor(data.points, dtype=torch.float32, device=device)
        cols = torch.as_tensor(data.colors, dtype=torch.float32, device=device) / 255.0
    else:
        n = cfg.init_random_points if budget is None else min(cfg.init_random_points, budget)
        pts, cols = random_points(n, data.bounds_min, data.bounds_max, cfg.seed, device)
    if budget is not None and pts.shape[0] > budget:  # subset first: kNN scales then match the kept density
        idx = subsample_index(pts.shape[0], budget, cfg.seed).to(device)
        pts, cols = pts[idx], cols[idx]
    return gaussians_from_points(pts, cols, cfg.max_sh_degree, cfg.init_opacity, cfg.init_knn)


def after_training(project: Project, cfg: TrainConfig, data: TrainData, state: TrainState,
                   on_event: EventSink | None, before: tuple[float, float] | None = None) -> None:
    """Run once, at step == iterations, before that step's checkpoint. `before` is
    the held-out (PSNR, SSIM) just measured for this model, if any."""
    from ..train.loop import evaluate_views

    if cfg.sh_degree == "auto" and "sh_auto_psnr" not in state.extra:
        val = subset(data.train, cfg.val_max_views)
        scores = {d: evaluate_views(state, val, data.background, d)[0] for d in range(state.sh_cap + 1)}
        best = scores[state.sh_cap]
        chosen = min(d for d, p in scores.items() if p >= best - cfg.sh_auto_tol_db)
        state.extra["sh_auto_psnr"] = {str(d): round(p, 4) for d, p in scores.items()}
        state.extra["sh_auto_degree"] = chosen
        if chosen < state.sh_cap:
            ops.truncate_bands(state.params, state.optimizers, "shN", (chosen + 1) ** 2 - 1)
            state.sh_cap = chosen
        emit(on_event, Note(f"--sh-degree auto: degree {chosen} (validation PSNR "
                            + ", ".join(f"{d}: {p:.2f}" for d, p in scores.items()) + " dB)"))
    if cfg.compact and "compact_before" not in state.extra:
        deg = state.sh_cap
        n = state.num_gaussians
        if before is None and data.test:
            before = evaluate_views(state, data.test, data.background, deg)
        state.extra["compact_before"] = {"count": n, "bytes": ply_bytes(n, deg),
                                         "psnr": before[0] if before is not None else None}
        _prune_round(cfg, data, state, 1, on_event)


def prune_steps(cfg: TrainConfig) -> list[int]:
    """Steps ending with a --compact prune round: the first at `iterations`, the
    others spread over the first half of the fine-tune, so the final set still
    gets at least half of it. Pruning in rounds lets the survivors take over the
    pruned Gaussians' work before the next cut (one cut loses more)."""
    spacing = cfg.compact_finetune // (2 * cfg.compact_rounds)
    if spacing == 0:  # too short a fine-tune for rounds: one cut
        return [cfg.iterations]
    return [cfg.iterations + r * spacing for r in range(cfg.compact_rounds)]


def at_step(project: Project, cfg: TrainConfig, data: TrainData, state: TrainState, step: int,
            on_event: EventSink | None, before: tuple[float, float] | None = None) -> None:
    """The loop's one hook: post-processing at `iterations`, later prune rounds."""
    if step == cfg.iterations:
        after_training(project, cfg, data, state, on_event, before)
    elif cfg.compact and step > cfg.iterations:
        sched = prune_steps(cfg)
        if step in sched[1:] and state.extra.get("compact_round", 0) < sched.index(step) + 1:
            _prune_round(cfg, data, state, sched.index(step) + 1, on_event)


def _prune_round(cfg: TrainConfig, data: TrainData, state: TrainState, r: int, on_event: EventSink | None) -> None:
    """Round r of R: keep the n0 * keep^(r/R) Gaussians with the most blending weight."""
    n0 = state.extra["compact_before"]["count"]
    rounds = len(prune_steps(cfg))
    k = max(1, int(n0 * cfg.compact_keep ** (r / rounds)))  # the last round keeps exactly int(keep * n0)
    n = state.num_gaussians
    if k < n:
        weight = blending_weights(state, data.train, data.background)
        keep = torch.zeros(n, dtype=torch.bool, device=weight.device)
        keep[torch.argsort(weight, descending=True, stable=True)[:k]] = True
        ops.keep(state.params, state.optimizers, keep)
        z = state.sstate.grad2d.new_zeros(state.num_gaussians)
        state.sstate.grad2d, state.sstate.count, state.sstate.radii = z, z.clone(), z.clone()
        state.extra["compact_before"][f"kept_weight_{r}"] = float(weight[keep].sum() / weight.sum().clamp_min(1e-12))
    state.extra["compact_round"] = r
    emit(on_event, Note(f"--compact round {r}/{rounds}: kept {state.num_gaussians} of {n0} Gaussians "
                        f"by blending weight"))


def subset(views: list[View], k: int) -> list[View]:
    """`k` evenly spaced views (all when k <= 0 or there are fewer)."""
    if k <= 0 or len(views) <= k:
        return list(views)
    idx = np.linspace(0, len(views) - 1, k).round().astype(int)
    return [views[i] for i in idx]


def blending_weights(state: TrainState, views: list[View], bg: Tensor) -> Tensor:  # -> [N]
    """sum over views and pixels of alpha_i T_i per Gaussian (render.weights)."""
    p = state.params
    return render_weights(p["means"], p["quats"], p["log_scales"], p["opacity_logits"],
                          ((v.viewmat, v.K, v.camera.width, v.camera.height) for v in views))
