"""Density and model control: when to clone, split, prune, reset and compact Gaussians,
and the one set of ops that edits parameters, Adam moments and strategy state together."""

from .average import AverageState, AverageStep
from .base import Context, Evaluator, RefineConfig, RefineStats, RowState, Splats, StepInfo, Strategy, TrainViews
from .compact import CompactConfig, CompactReport, CompactStep, ShAutoConfig, ShAutoStep, cut_steps, sh_degree_of
from .default import DefaultStrategy, DefaultStrategyConfig, DefaultStrategyState
from .mcmc import MCMCStrategy, MCMCStrategyConfig, MCMCStrategyState
from .mip import MipFilter, MipFilterState
from .regularize import RegularizeStep
from .support import SupportConfig, SupportPrune

__all__ = ["AverageState", "AverageStep", "CompactConfig", "CompactReport", "CompactStep", "Context",
           "DefaultStrategy", "DefaultStrategyConfig", "DefaultStrategyState", "Evaluator", "MCMCStrategy",
           "MCMCStrategyConfig", "MCMCStrategyState", "MipFilter", "MipFilterState", "RefineConfig", "RefineStats",
           "RegularizeStep", "RowState", "ShAutoConfig", "ShAutoStep", "Splats", "StepInfo", "Strategy",
           "SupportConfig", "SupportPrune", "TrainViews", "cut_steps", "sh_degree_of"]
