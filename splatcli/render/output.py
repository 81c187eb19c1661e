"""The typed result of a rasterization."""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor


@dataclass
class RenderOutput:
    image: Tensor  # [H, W, 3] RGB, background composited (C + T * background)
    alpha: Tensor  # [H, W] accumulated opacity, 1 - T
    depth: Tensor  # [H, W] alpha-weighted view depth (sum_i w_i z_i), world units
    means2d: Tensor  # [N, 2] pixel-space projected means; call .retain_grad() before backward
    # to read the view-space positional gradient that densification accumulates
    radii: Tensor  # [N] int32 pixel radius ceil(3 sqrt(lambda_max)); 0 when culled
    visible: Tensor  # [N] bool: in front of the near plane, on screen, radius > 0
    depths: Tensor  # [N] view-space z of each mean
