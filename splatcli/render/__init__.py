"""Differentiable Gaussian rasterization (PyTorch, CPU and CUDA) and its reference;
gsplat's CUDA kernels behind the same call (backends.py)."""

from .backends import Renderer, render_camera, resolve_renderer
from .output import RenderOutput
from .rasterize import rasterize

__all__ = ["RenderOutput", "Renderer", "rasterize", "render_camera", "resolve_renderer"]
