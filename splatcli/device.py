"""The `--device` option resolved to a torch.device, explicitly, and the device in words."""

from __future__ import annotations

import platform
from functools import cache

import torch

from .errors import SplatError

# The vector extensions that rank the same code differently on different CPUs, as /proc/cpuinfo names them.
VECTOR_FLAGS = ("avx512f", "avx512_bf16", "avx2", "fma", "avx", "neon", "asimd", "sve")


# glibc's malloc hands blocks above a threshold to mmap and gives freed memory back to the system,
# so the rasterizer's dense temporaries (0.1-30 MB, made and freed many times a step) were fresh,
# page-faulting memory each time. Kept in the process below these sizes, bench/step.py measured lego
# (18k Gaussians, 200 px) 1.2-1.5x and fox (58k, 480 px) 1.05x faster on a Zen 3, at the same peak
# memory; whole training steps vary more than that there and showed no clear difference.
MMAP_THRESHOLD = 64 << 20
TRIM_THRESHOLD = 256 << 20


def tune_allocator() -> bool:
    """Keep freed memory for reuse (see MMAP_THRESHOLD) where the C library is glibc; whether it was set."""
    import ctypes
    import ctypes.util

    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        m_trim, m_mmap = -1, -3  # malloc.h: M_TRIM_THRESHOLD, M_MMAP_THRESHOLD
        return bool(libc.mallopt(m_mmap, MMAP_THRESHOLD)) and bool(libc.mallopt(m_trim, TRIM_THRESHOLD))
    except (OSError, AttributeError):
        return False


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
    return f"{device.type} ({n} thread{'' if n == 1 else 's'}; {cpu_name()})"


@cache
def cpu_name() -> str:
    """The CPU model and its widest vector extensions, for every timing's record:
    "AMD EPYC (avx2, fma)". From /proc/cpuinfo where there is one."""
    model, flags = platform.processor() or platform.machine(), set()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                key, _, val = line.partition(":")
                key = key.strip().lower()
                if key in ("model name", "hardware") and model in ("", platform.machine(), platform.processor()):
                    model = val.strip()
                elif key in ("flags", "features") and not flags:
                    flags = set(val.split())
    except OSError:
        pass
    ext = [f for f in VECTOR_FLAGS if f in flags]
    if "avx512f" in ext:  # the widest says enough
        ext = [f for f in ext if f.startswith("avx512")]
    elif "avx2" in ext:
        ext = [f for f in ext if f in ("avx2", "fma")]
    return f"{model or 'unknown CPU'} ({', '.join(ext)})" if ext else (model or "unknown CPU")


def synchronize(device: torch.device) -> None:
    """Wait for the device's queued work (timings of CUDA work need it)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
