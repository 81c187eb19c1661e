"""Opacity and scale penalties on the whole model (as MCMC uses them, Kheradmand et al. 2024):
they keep Gaussians small and let the unneeded ones fade, so that densification does not
fill what the training views leave unconstrained with floaters (issue 15's overfitting
study, docs/guide.md "Held-out quality over time").

Their gradients are accumulated into `.grad` before the photometric loss's backward (the
two add up), so the loop does not change.
"""

from __future__ import annotations

import torch

from .base import Params, Splats, StepInfo, Strategy


def regularize(params: Params, opacity_reg: float, scale_reg: float) -> None:
    """Backward of opacity_reg * mean(sigmoid(o)) + scale_reg * mean(exp(log s)) into the
    parameters' `.grad`."""
    reg = (opacity_reg * torch.sigmoid(params["opacity_logits"]).mean()
           + scale_reg * params["log_scales"].exp().mean())
    reg.backward()


class RegularizeStep(Strategy):
    name = "regularize"

    def __init__(self, opacity_reg: float, scale_reg: float) -> None:
        self.opacity_reg, self.scale_reg = opacity_reg, scale_reg

    def step_pre_backward(self, splats: Splats, state: object, step: int, info: StepInfo) -> None:
        regularize(splats.params, self.opacity_reg, self.scale_reg)
