"""Differentiable Gaussian rasterization (PyTorch, CPU and CUDA) and its reference."""

from .output import RenderOutput
from .rasterize import rasterize

__all__ = ["RenderOutput", "rasterize"]
