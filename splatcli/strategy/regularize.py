"""Opacity and scale penalties on the whole model (as MCMC uses them, Kheradmand et al. 2024):
they keep Gaussians small and let the unneeded ones fade, so that densification does not
fill what the training views leave unconstrained with floaters (issue 15's overfitting
study, docs/benchmarks.md "overfitting").

Their gradients are accumulated into `.grad` before the photometric loss's backward (the
two add up), so the loop does not change.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .base import Params, Splats, StepInfo, Strategy


@dataclass(frozen=True)
class RegularizeConfig:
    opacity_reg: float = 0.0  # x mean opacity, added to the loss (0: off)
    scale_reg: float = 0.0  # x mean scale in world units (0: off)

    @property
    def enabled(self) -> bool:
        return self.opacity_reg > 0 or self.scale_reg > 0


def regularize(params: Params, opacity_reg: float, scale_reg: float) -> None:
    """Backward of opacity_reg * mean(sigmoid(o)) + scale_reg * mean(exp(log s)) into the
    parameters' `.grad`."""
    reg = (opacity_reg * torch.sigmoid(params["opacity_logits"]).mean()
           + scale_reg * params["log_scales"].exp().mean())
    reg.backward()


class RegularizeStep(Strategy):
    name = "regularize"

    def __init__(self, config: RegularizeConfig) -> None:
        self.config = config

    def step_pre_backward(self, splats: Splats, state: object, step: int, info: StepInfo) -> None:
        regularize(splats.params, self.config.opacity_reg, self.config.scale_reg)
