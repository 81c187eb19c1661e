"""What every strategy shares: the trainable set that `ops` edits, what the loop tells
a strategy at each step, and what a refinement did.

A strategy keeps its hyperparameters in a frozen dataclass and its running state in
a `RowState`. The loop calls every strategy of the run at the same fixed points:

    term = strategy.step_pre_backward(splats, state, step, info)  # a loss term, or None
    stats = strategy.step_post_backward(splats, state, step, info)

and, once when a run resumes, `strategy.catch_up(splats, state, step)`. Whenever the
model is drawn, `strategy.shade(splats, state, log_scales, opacity_logits)` gives the
scales and opacities it is drawn with (TrainState.drawn).
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol

import torch
from torch import Tensor, nn

from ..options import MODEL, opt
from ..render.output import RenderOutput

Params = dict[str, nn.Parameter]
Optimizers = dict[str, torch.optim.Optimizer]


@dataclass(frozen=True)
class RefineConfig:
    """What every density strategy has, each with its own values: when it refines, the
    most Gaussians it may hold, and the penalties on opacity and scale. The options are
    shared: `--max-gaussians` sets the chosen strategy's (options.py)."""

    refine_start: int = opt(500, "First step that may refine (exclusive).", shared=True, at_least=0,
                            steps="schedule")
    refine_stop: int = opt(15_000, "No refinement from this step on.", shared=True, at_least=0, steps="schedule")
    refine_every: int = opt(100, "Steps between refinements.", shared=True, at_least=1, steps="schedule")
    max_gaussians: int | None = opt(
        None, "The most Gaussians the model may hold: the default strategy's growth goes to the highest "
        "gradients first and stops there; mcmc grows to exactly this many (and needs it).",
        shared=True, group=MODEL, at_least=1)
    opacity_reg: float = opt(0.0, "Add this x the mean opacity to the loss: unneeded Gaussians fade and are "
                             "pruned or reused.", shared=True, group=MODEL, at_least=0)
    scale_reg: float = opt(0.0, "Add this x the mean scale (world units) to the loss: Gaussians stay small.",
                           shared=True, group=MODEL, at_least=0)


@dataclass
class RowState:
    """Base of a strategy's running state (a dataclass). `ROWS` names its tensor fields
    that hold one row per Gaussian: `ops` slices and grows them together with the
    parameters, so no strategy resets another's accumulators by hand. Fields are
    checkpointed as they are (tensors, plain values; a generator as its state)."""

    ROWS: ClassVar[tuple[str, ...]] = ()
    # Accumulators each data-parallel rank fills from its own views, and how the ranks'
    # rows merge ("sum" or "max") before a decision: see StepInfo.combine.
    REDUCE: ClassVar[dict[str, str]] = {}

    def state_dict(self) -> dict[str, Any]:
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            out[f.name] = v.get_state() if isinstance(v, torch.Generator) else v
        return out

    def load_state_dict(self, d: dict[str, Any]) -> None:
        for f in dataclasses.fields(self):
            if f.name not in d:
                continue
            v = getattr(self, f.name)
            if isinstance(v, torch.Generator):
                _set_generator(v, d[f.name])
            elif isinstance(v, Tensor):
                setattr(self, f.name, d[f.name].to(v.device))
            else:
                setattr(self, f.name, d[f.name])


@dataclass
class Splats:
    """The trainable set: one `nn.Parameter` per attribute (rows = Gaussians), one Adam
    per parameter, and every strategy's per-Gaussian state. `ops` edits all three in
    one call, and nothing else edits any of them."""

    params: Params
    optimizers: Optimizers
    states: list[RowState] = field(default_factory=list)

    def __len__(self) -> int:
        return int(self.params["means"].shape[0])


@dataclass
class StepInfo:
    """What the loop tells the strategies about one step."""

    render: RenderOutput  # means2d [N, 2] (grad retained), radii [N], visible [N]
    width: int
    height: int
    finite: bool = True  # False on a skipped (non-finite) step: accumulate nothing
    heldout: tuple[float, float] | None = None  # (PSNR, SSIM) measured after this step's update, if any
    # A strategy calls combine(state) before deciding from accumulated rows: in a
    # data-parallel run it merges every rank's `REDUCE` rows (the same on every rank).
    combine: Callable[[RowState], None] = lambda state: None


@dataclass
class RefineStats:
    """What one call changed; the loop logs it (train_log.jsonl, progress bar)."""

    step: int
    before: int
    cloned: int = 0
    split: int = 0
    pruned: int = 0
    after: int = 0
    reset_opacity: bool = False
    held_by_budget: int = 0  # growth candidates refused because of max_gaussians

    @property
    def changed(self) -> bool:
        return self.cloned + self.split + self.pruned > 0 or self.reset_opacity


class Evaluator(Protocol):
    """Scores and weighs the model a run is training (the loop gives one; strategies never
    import the trainer). Every rank gets the same answers."""

    def score(self, views: str, sh_degree: int) -> tuple[float, float] | None:
        """Mean (PSNR, SSIM) on `views`: "test", or "val:K" (K evenly spaced training views); None
        when there are no such views."""

    def weights(self) -> Tensor:
        """[N] each Gaussian's blending weight summed over the training views (pixels)."""


@dataclass(frozen=True)
class TrainViews:
    """The training views, as a strategy sees them."""

    cameras: list[tuple[Tensor, Tensor, int, int]] = field(default_factory=list)  # (viewmat, K, width, height) each
    centres: Tensor | None = None  # [n_train, 3] the cameras' centres (Camera.center), in training-view order
    center: Tensor | None = None  # [3] their centre (far content is judged by distance from it)
    # means [N, 3] -> [N] how many training views hold each point in their frustum
    seeing: Callable[[Tensor], Tensor] = lambda means: torch.zeros(len(means))


@dataclass(frozen=True)
class Context:
    """What a step acting on the whole model is given: the run's evaluator, the training views,
    and a way to tell the user a line."""

    evaluator: Evaluator
    views: TrainViews = field(default_factory=TrainViews)
    note: Callable[[str], None] = lambda line: None


class Strategy:
    """A step of density or model control. Defaults do nothing."""

    name: ClassVar[str] = "strategy"
    antialiased: ClassVar[bool] = False  # the model must be drawn with the 2D filter (rasterize(antialiased=True))

    def initial_state(self, n: int, device: torch.device, seed: int) -> RowState:
        return RowState()

    def step_pre_backward(self, splats: Splats, state: Any, step: int, info: StepInfo) -> Tensor | None:
        """Before backward: e.g. ask autograd to keep a gradient. Returns a term ([] scalar) the
        trainer adds to the step's loss before its one backward, or None."""
        return None

    def step_post_backward(self, splats: Splats, state: Any, step: int, info: StepInfo) -> RefineStats | None:
        """After the optimiser step of `step`."""
        return None

    def shade(self, splats: Splats, state: Any, log_scales: Tensor,  # [N, 3]
              opacity_logits: Tensor) -> tuple[Tensor, Tensor]:  # [N] -> ([N, 3], [N])
        """The scales and opacities the model is drawn with (differentiably): the
        parameters, unless the strategy filters the model (--mip-filter)."""
        return log_scales, opacity_logits

    def finish(self, splats: Splats, state: Any) -> None:
        """After the run's last step, before its final measurement and checkpoint."""
        return None

    def catch_up(self, splats: Splats, state: Any, step: int) -> RefineStats | None:
        """On resume at `step`: do what an uninterrupted run would already have done
        by now but this checkpoint has not (a finished run resumed with --compact)."""
        return None

    def summary(self, state: Any, num_gaussians: int, sh_degree: int, psnr: float | None) -> dict[str, Any]:
        """Entries of the train summary this strategy owns."""
        return {}


class ModelStep(Strategy):
    """A step on the whole model from step `at` on (--sh-degree auto, --compact): its
    state is a fresh `state_type` and it asks the run through `ctx`."""

    state_type: ClassVar[type[RowState]] = RowState

    def __init__(self, config: Any, at: int, ctx: Context) -> None:
        self.config, self.at, self.ctx = config, at, ctx

    def initial_state(self, n: int, device: torch.device, seed: int) -> RowState:
        return self.state_type()


def _set_generator(gen: torch.Generator, state: Tensor) -> None:
    """Restore `gen`, or, for a state written on another kind of device (a CUDA run
    resumed on the CPU, or the reverse), seed it from that state: the same stream
    cannot continue there, but the resumed run stays deterministic."""
    if state.numel() == gen.get_state().numel():
        gen.set_state(state)
    else:
        gen.manual_seed(int.from_bytes(hashlib.sha256(state.cpu().numpy().tobytes()).digest()[:8], "little") >> 1)
