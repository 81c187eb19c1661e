"""Parameter averaging (Polyak averaging; an exponential moving average, as "EMA weights" in image
models): the run ends with each Gaussian's parameters averaged over its last steps rather than
with the last step's values.

Each step fits one view (one per rank) and moves the Gaussians towards it; at the end of a run
the last few views still pull the model about, and MCMC's noise still jitters the faint ones.
An average over the last few percent of the steps keeps what the views agree on. Scored on the
held-out views of the same runs (lego and fox, planned runs of 2 processes on an Intel Xeon of
family 6 model 207), averages with time constants of 1-4% of the steps ended 0.07-0.21 dB above
the last step's model; 17% reached back to models still learning and ended 0.17 dB below
(docs/benchmarks.md, "Time budgets"). The default is 2%.

Each row is averaged since its Gaussian last appeared: a Gaussian that density control adds or
moves (MCMC's relocation) gets zeroed strategy rows from `ops`, and its average starts again
from its new values. The averages exist only in the last `WINDOW` time constants of the run
(before that the rows are [N, 0]: no memory, no work); after the run's last step they become
the parameters (Adam's moments kept: the run ends there, and a resumed one goes on from the
average), before the final measurement and checkpoint.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor

from . import ops
from .base import RefineStats, RowState, Splats, StepInfo, Strategy

# The averages start this many time constants before the end: by then the weight left on their
# first values is e^-4, under 2%.
WINDOW = 4.0


@dataclass
class AverageState(RowState):
    ROWS: ClassVar[tuple[str, ...]] = ("values", "count")

    values: Tensor  # [N, D] every parameter of a row, flattened in `params` order; [N, 0] outside the window
    count: Tensor  # [N] steps averaged into the row (0: new or moved; ops adds and moves rows at 0)
    layout: tuple[tuple[str, int], ...] = ()  # (parameter, its share of D), in `params` order


class AverageStep(Strategy):
    """Averages the parameters with a time constant of `share` x `total` steps (`total`: the
    run's, as planned now) and makes the averages the parameters when the run ends (`finish`)."""

    name = "average"

    def __init__(self, share: float, total: int) -> None:
        self.tau = max(1.0, share * total)  # steps
        self.start = total - WINDOW * self.tau

    def initial_state(self, n: int, device: torch.device, seed: int = 0) -> AverageState:
        return AverageState(torch.zeros(n, 0, device=device), torch.zeros(n, device=device))

    @torch.no_grad()
    def step_post_backward(self, splats: Splats, state: AverageState, step: int, info: StepInfo) -> RefineStats | None:
        if step < self.start:
            return None
        params = splats.params
        n = len(splats)
        layout = tuple((k, p[0].numel()) for k, p in params.items())
        widths = [w for _, w in layout]
        if state.layout != layout:  # the window opens (or bands were cut): start again
            state.values, state.layout = params["means"].new_zeros(n, sum(widths)), layout
            state.count.zero_()
        state.count += 1
        w = (1.0 / state.count.clamp(max=self.tau))[:, None]  # [N, 1]: 1 at a row's first step
        for p, part in zip(params.values(), state.values.split(widths, 1)):
            part.lerp_(p.reshape(n, -1), w)
        return None

    @torch.no_grad()
    def finish(self, splats: Splats, state: AverageState) -> None:
        if state.values.shape[1] == 0:  # the window never opened
            return
        # Each parameter's leading values: --sh-degree auto may have cut SH bands since the last average
        # (the first bands lead each row, and a degree of 0 drops shN); one that grew keeps its own.
        parts = dict(zip([k for k, _ in state.layout], state.values.split([w for _, w in state.layout], 1)))
        ops.assign(splats, {k: parts[k][:, :p[0].numel()].reshape(p.shape) for k, p in splats.params.items()
                            if k in parts and p[0].numel() <= parts[k].shape[1]})
        state.values, state.layout = state.values.new_zeros(len(splats), 0), ()  # (not kept in the last checkpoint)
