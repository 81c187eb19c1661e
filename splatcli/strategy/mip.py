"""`train --mip-filter`: Mip-Splatting's 3D smoothing filter (Yu et al., CVPR 2024, sec. 5.1).

No Gaussian may hold detail finer than the training views could sample. Per Gaussian,
nu = max focal / depth (pixels per world unit) over the training cameras that see its
centre (in front of the near plane, inside the image widened by 15% per side, as the
authors' code does); the filter is an isotropic Gaussian of standard deviation
sqrt(0.2) / nu world units, convolved into the Gaussian when it is drawn
(`gaussians.smooth_3d`: scales s' = sqrt(s^2 + f^2), opacity times prod s / s').

The filter is a row per Gaussian (`MipFilterState.filter3d`): `ops` keeps, appends and
replaces it with the parameters, and it is checkpointed with the strategy state, where
`Checkpoint.model()` folds it into the model every other command loads. It is recomputed
for every Gaussian every `EVERY` steps and, for Gaussians that `ops` added or replaced
since (their `known` row is 0), before the next render and after each step.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor

from ..gaussians import smooth_3d
from ..render.projection import in_frustum
from .base import RowState, Splats, StepInfo, Strategy

VARIANCE = 0.2  # filter variance in squared sampling intervals (the paper's s; their code's 0.2)
MARGIN = 0.15  # a centre this fraction of the image size outside it still counts as seen (their code)
EVERY = 100  # steps between full recomputations (their code)
# The default strategy's growth threshold is this fraction of grow_grad2d under the filters:
# they lower small Gaussians' view-space gradients (the 2D filter's opacity compensation,
# the 3D filter's smoothing), so fewer crossed it: at 1x lego grew fewer Gaussians than plain
# training and scored lower at the size trained; at 0.8x it matched it there and gained zoomed
# in (docs/guide.md, "Rendering at other resolutions").
GROW_GRAD2D = 0.8

CameraList = Iterable[tuple[Tensor, Tensor, int, int]]  # (viewmat [4, 4], K [3, 3], width, height)


@torch.no_grad()
def sampling_rate(
    means: Tensor,  # [N, 3] world
    cameras: CameraList,  # at the training resolution
    margin: float = MARGIN,
) -> Tensor:  # [N] pixels per world unit; 0 where no camera sees the centre
    """The highest rate at which any camera samples each centre: focal / depth."""
    nu = torch.zeros(means.shape[0], dtype=means.dtype, device=means.device)
    for viewmat, K, width, height in cameras:
        _, z, inside = in_frustum(means, viewmat, K, width, height, margin)
        rate = K[:2, :2].diagonal().max().to(means) / torch.where(inside, z, torch.ones_like(z))
        nu = torch.maximum(nu, torch.where(inside, rate, torch.zeros_like(rate)))
    return nu


def filter_from_rate(
    nu: Tensor,  # [N] pixels per world unit, 0 where unseen
    fallback: float | None = None,  # for unseen centres; None: the largest filter of the seen ones
) -> Tensor:  # [N] world units
    """Standard deviation sqrt(VARIANCE) / nu. A centre no camera sees gets `fallback`
    (the authors give it the largest filter of the seen ones), 0 when nothing is seen."""
    seen = nu > 0
    f = math.sqrt(VARIANCE) / torch.where(seen, nu, torch.ones_like(nu))
    if fallback is None:
        fallback = float(f[seen].max()) if bool(seen.any()) else 0.0
    return torch.where(seen, f, torch.full_like(f, fallback))


@dataclass
class MipFilterState(RowState):
    # `filter3d` is the name Checkpoint.model() folds (files/checkpoint.py).
    ROWS: ClassVar[tuple[str, ...]] = ("filter3d", "known")

    filter3d: Tensor  # [N] world units
    known: Tensor  # [N] 1 where filter3d was computed for the Gaussian in that row (ops adds rows at 0)


class MipFilter(Strategy):
    """Keeps `filter3d` current and draws the model through it, with the 2D filter
    (`rasterize(antialiased=True)`) as Mip-Splatting does."""

    name = "mip"
    antialiased = True

    def __init__(self, cameras: CameraList) -> None:
        self.cameras = cameras  # the training views at the training resolution

    def initial_state(self, n: int, device: torch.device, seed: int = 0) -> MipFilterState:
        z = torch.zeros(n, device=device)
        return MipFilterState(z, z.clone())

    def shade(self, splats: Splats, state: MipFilterState, log_scales: Tensor,
              opacity_logits: Tensor) -> tuple[Tensor, Tensor]:
        self._fill(splats, state)
        return smooth_3d(log_scales, opacity_logits, state.filter3d)

    def step_post_backward(self, splats: Splats, state: MipFilterState, step: int, info: StepInfo) -> None:
        if step % EVERY == 0:
            state.known.zero_()
        self._fill(splats, state)

    @torch.no_grad()
    def _fill(self, splats: Splats, state: MipFilterState) -> None:
        """Compute the filter of every row not `known`."""
        todo = state.known <= 0
        if not bool(todo.any()):
            return
        means = splats.params["means"].detach()
        if bool(todo.all()):
            f = filter_from_rate(sampling_rate(means, self.cameras))
        else:
            idx = todo.nonzero().squeeze(1)
            old = state.filter3d[~todo]
            f = filter_from_rate(sampling_rate(means[idx], self.cameras), float(old.max()) if old.numel() else None)
            f = state.filter3d.index_put((idx,), f.to(state.filter3d))
        state.filter3d = f.to(state.filter3d)
        state.known = torch.ones_like(state.known)
