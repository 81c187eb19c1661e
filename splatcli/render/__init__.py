"""Differentiable Gaussian rasterization (PyTorch, CPU and CUDA) and its reference."""

from .output import RenderOutput
from .rasterize import rasterize, render_camera

__all__ = ["RenderOutput", "rasterize", "render_camera"]
