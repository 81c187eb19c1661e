"""The typed result of a rasterization."""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor


@dataclass
class RenderOutput:
    image: Tensor  # [H, W, 3] RGB, background composited (C + T * background)
    alpha: Tensor  # [H, W] accumulated opacity, 1 - T
    depth: Tensor  # [H, W] alpha-weighted view depth (sum_i w_i z_i), world units
    means2d: Tensor  # [N, 2] pixel-space projected means ([1, N, 2] from gsplat); call .retain_grad()
    # before backward to read the view-space positional gradient that densification accumulates
    radii: Tensor  # [N] int32 pixel radius ceil(3 sqrt(lambda_max)); 0 when culled
    visible: Tensor  # [N] bool: in front of the near plane, on screen, radius > 0
    depths: Tensor  # [N] view-space z of each mean

    def screen_grad(self) -> Tensor | None:  # [N, 2] d loss / d means2d, or None before backward
        """The gradient `means2d.retain_grad()` kept, one row per Gaussian whichever renderer drew."""
        g = self.means2d.grad
        return None if g is None else g.reshape(-1, 2)
