"""Resolve the `--device` option to a torch.device, explicitly."""

from __future__ import annotations

import torch

from .errors import SplatError

DEVICE_CHOICES = ("auto", "cpu", "cuda")


def resolve_device(name: str = "auto") -> torch.device:
    """"auto" picks CUDA when available, else CPU. "cuda" without a GPU is a user error."""
    name = (name or "auto").strip().lower()
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cpu":
        return torch.device("cpu")
    if name == "cuda" or name.startswith("cuda:"):
        if not torch.cuda.is_available():
            raise SplatError(
                "--device cuda: no CUDA GPU is available to torch; allowed values: auto, cpu, cuda"
            )
        return torch.device(name)
    raise SplatError(f"--device {name!r} is not known; allowed values: auto, cpu, cuda")
