"""Adaptive density control: when to clone, split, prune and reset Gaussians."""

from .default import DefaultStrategy, DefaultStrategyConfig, DefaultStrategyState, RefineStats, StepInfo

__all__ = ["DefaultStrategy", "DefaultStrategyConfig", "DefaultStrategyState", "RefineStats", "StepInfo"]
