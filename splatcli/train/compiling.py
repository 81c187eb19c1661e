"""`--compile auto` resolved for a run: compile the rasterizer's planner where the run is long
enough to repay it (render/kernels.py compiles; the loop asks here first)."""

from __future__ import annotations

import torch

from ..render import kernels
from .config import TrainConfig

# --compile auto: compile when the run is at least this long (seconds of training). The compiled
# planner saves a few per cent of a step at most, and on some CPUs nothing, while an empty cache
# costs tens of seconds of compiling and a warm one a few seconds of loading, all taken from the
# budget (docs/benchmarks.md, "Time budgets": a 300 s run trained fewer steps compiled than eager).
COMPILE_COLD_S = 1800.0
COMPILE_WARM_S = 900.0
COMPILE_STEPS = 10_000  # a step schedule without a time budget: compile from this many steps


def compile_mode(cfg: TrainConfig, device: torch.device) -> tuple[str, str]:
    """--compile resolved to "on" or "off", and why (train.json)."""
    if device.type != "cpu":
        return "off", "the CPU path only (CUDA draws with gsplat's kernels or eagerly)"
    if cfg.compile != "auto":
        return cfg.compile, "--compile " + cfg.compile
    if kernels.compiler() is None:
        return "off", "no C++ compiler found"
    warm = kernels.warm_cache()
    need = COMPILE_WARM_S if warm else COMPILE_COLD_S
    cache = "the kernels are cached" if warm else "the first run on this machine compiles"
    if cfg.time_budget is not None:
        if cfg.time_budget >= need:
            return "on", f"a {cfg.time_budget:.0f} s run repays compiling ({cache})"
        return "off", f"a {cfg.time_budget:.0f} s run is too short to repay compiling ({cache}; from {need:.0f} s)"
    if cfg.total_steps >= COMPILE_STEPS:
        return "on", f"{cfg.total_steps} steps repay compiling ({cache})"
    return "off", f"{cfg.total_steps} steps are too few to repay compiling (from {COMPILE_STEPS})"
