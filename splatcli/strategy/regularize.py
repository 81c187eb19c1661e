"""Opacity and scale penalties (as MCMC uses them, Kheradmand et al. 2024): they keep Gaussians
small and let the unneeded ones fade, so that densification does not fill what the training
views leave unconstrained with floaters (docs/guide.md "Held-out quality over time").

Each step penalises the Gaussians its view draws, beside the photometric loss that judges the
same Gaussians. Adam turns a small but steady gradient into a step of the full learning rate:
penalised in every step, a Gaussian that the step's view does not show had the penalty as its
only gradient, and so faded at the learning rate, whatever the other views said of it. On a
capture of many views, where each view shows a small part of the model, that emptied the
background and churned the model (docs/benchmarks.md, "Training with no options").

The penalty is a loss term the strategy returns from `step_pre_backward`: the trainer adds it
to the photometric loss and calls backward once.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .base import Params, Splats, StepInfo, Strategy


def regularize(params: Params, opacity_reg: float, scale_reg: float, drawn: Tensor) -> Tensor:  # -> [] loss term
    """opacity_reg * mean(sigmoid(o)) + scale_reg * mean(exp(log s)), the means taken over the
    whole model but the terms only of the Gaussians in `drawn` ([N] bool: those the step's view draws)."""
    keep = drawn.to(params["opacity_logits"].dtype)  # [N]
    o = torch.sigmoid(params["opacity_logits"]) * keep  # [N]
    s = params["log_scales"].exp() * keep[:, None]  # [N, 3]
    return opacity_reg * o.mean() + scale_reg * s.mean()


class RegularizeStep(Strategy):
    name = "regularize"

    def __init__(self, opacity_reg: float, scale_reg: float) -> None:
        self.opacity_reg, self.scale_reg = opacity_reg, scale_reg

    def step_pre_backward(self, splats: Splats, state: object, step: int, info: StepInfo) -> Tensor:
        return regularize(splats.params, self.opacity_reg, self.scale_reg, info.render.visible)
