"""A strategy Context for tests that build strategies without a run."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from splatcli.strategy import Context, TrainViews


class FixedEvaluator:
    """A strategy.Evaluator with no views to score, whose weights are the ones it was given."""

    def __init__(self, weights: Tensor | None = None) -> None:
        self._weights = weights

    def score(self, views: str, sh_degree: int) -> tuple[float, float] | None:
        return None

    def weights(self) -> Tensor:
        return self._weights if self._weights is not None else torch.zeros(0)


def context(weights: Tensor | None = None, **views: Any) -> Context:
    """A Context whose evaluator returns `weights`, with the TrainViews fields given."""
    return Context(FixedEvaluator(weights), TrainViews(**views))
