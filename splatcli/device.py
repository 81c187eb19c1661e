"""The `--device` option resolved to a torch.device, explicitly, and the device in words."""

from __future__ import annotations

import torch

from .errors import SplatError


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


def describe_device(device: torch.device) -> str:
    """The device in words, for reports: "cpu (2 threads)", "cuda:0 (NVIDIA H200)"."""
    if device.type == "cuda":
        return f"{device} ({torch.cuda.get_device_name(device)})"
    n = torch.get_num_threads()
    return f"{device.type} ({n} thread{'' if n == 1 else 's'})"


def synchronize(device: torch.device) -> None:
    """Wait for the device's queued work (timings of CUDA work need it)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
