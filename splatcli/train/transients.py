"""`train --transients ignore`: pixels that disagree with the scene (people, cars, flags and
clouds that move between photos) are left out of a training photo's loss.

A photo collection shows passers-by in one photo and not in the next; fitted, they become
floaters in front of the scene. This is the robust mask of RobustNeRF (Sabour et al. 2023),
applied to the whole training image after the photo's colour transform (so a photo's exposure
is not an error). Per photo and step, with no gradient:

* a pixel's error is its mean absolute colour difference; the `quantile` of the errors over the
  photo's pixels is the bound above which a pixel is an outlier;
* a pixel is kept if it is an inlier, or if at least half of its 3x3 neighbourhood is, or if at
  least half of its patch is (patches of `patch` x the longer side): an outlier is left out only
  inside a region that is mostly outliers, so the fine detail that a good model misses here and
  there (edges, texture) stays in, and a person, a banner or a moving cloud goes;
* nothing is left out before `start` x the run's steps: early on, every textured region is far
  from its photo, and leaving it out would keep it so.

The mask only shapes the loss. Held-out scores, renders and exports are the scene's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from ..options import opt

TRANSIENTS = ("keep", "ignore")  # --transients


@dataclass(frozen=True)
class TransientsConfig:
    quantile: float = opt(0.8, "A pixel whose error is above this quantile of its photo's errors is an outlier.",
                          more_than=0, less_than=1)
    patch: float = opt(1 / 30, "Patch side, x the longer image side (16 px at 480): an outlier is left out only "
                       "where half of its patch and of its 3x3 neighbours are outliers too.", more_than=0, at_most=1)
    start: float = opt(0.25, "Leave pixels out from this fraction of the steps on (before it, every textured region "
                       "is still far from its photo).", at_least=0, less_than=1)


@torch.no_grad()
def kept_pixels(image: Tensor, target: Tensor, keep: Tensor | None,  # [H, W, 3] each, keep [H, W] bool
                cfg: TransientsConfig) -> Tensor:  # -> [H, W] bool
    """The pixels of a training photo that its loss keeps (module docstring); `keep`: the pixels
    a mask keeps already (None: all), which alone bound the errors' quantile and stay out."""
    err = (image - target).abs().mean(-1)  # [H, W] (no_grad: nothing is tracked)
    valid = err if keep is None else err[keep]
    if valid.numel() == 0:
        return torch.zeros_like(err, dtype=torch.bool) if keep is None else keep
    k = min(valid.numel(), max(1, math.ceil(cfg.quantile * valid.numel())))
    bound = valid.flatten().kthvalue(k).values
    inlier = (err <= bound).to(err.dtype)[None, None]  # [1, 1, H, W]
    near = F.avg_pool2d(inlier, 3, 1, 1, count_include_pad=False) >= 0.5
    h, w = err.shape
    p = max(2, round(cfg.patch * max(h, w)))
    share = F.avg_pool2d(inlier, p, p, ceil_mode=True)  # (a ragged last patch averages its own pixels)
    patch = F.interpolate(share, scale_factor=p, mode="nearest")[..., :h, :w] >= 0.5
    out = (inlier.bool() | near | patch)[0, 0]
    return out if keep is None else out & keep
