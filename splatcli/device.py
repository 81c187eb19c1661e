"""The `--device` option resolved to a torch.device, explicitly, and the device in words."""

from __future__ import annotations

import platform
from functools import cache
from pathlib import Path

import torch

from .errors import SplatError

try:
    import resource
except ImportError:  # Windows: no RLIMIT_AS; the other limits still apply
    resource = None  # type: ignore[assignment]

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


def _cpuinfo(path: str) -> dict[str, str]:
    """/proc/cpuinfo's fields (keys lower case), each as the first processor gives it (ARM's
    "Hardware" comes after them all); {} where there is none."""
    info: dict[str, str] = {}
    try:
        with open(path) as f:
            for line in f:
                key, sep, val = line.partition(":")
                if sep:
                    info.setdefault(key.strip().lower(), val.strip())
    except OSError:
        pass
    return info


def _flags(info: dict[str, str]) -> set[str]:
    return set((info.get("flags") or info.get("features") or "").split())


def cpu_flags(path: str = "/proc/cpuinfo") -> set[str]:
    """The CPU's feature flags, as /proc/cpuinfo names them (empty where it is absent)."""
    return _flags(_cpuinfo(path))


@cache
def cpu_name(path: str = "/proc/cpuinfo") -> str:
    """The CPU model and its widest vector extensions, for every timing's record: "AMD EPYC 7B13
    (avx2, fma)". A model name without a number (virtual machines often give "AMD EPYC") gets the
    family and model numbers, which tell generations apart: "AMD EPYC (family 25 model 1; avx2, fma)"."""
    info = _cpuinfo(path)
    model = info.get("model name") or info.get("hardware") or platform.processor() or platform.machine()
    flags = _flags(info)
    ext = [f for f in VECTOR_FLAGS if f in flags]
    if "avx512f" in ext:  # the widest says enough
        ext = [f for f in ext if f.startswith("avx512")]
    elif "avx2" in ext:
        ext = [f for f in ext if f in ("avx2", "fma")]
    generic = not any(c.isdigit() for c in model) and "cpu family" in info and "model" in info
    family = f"family {info['cpu family']} model {info['model']}" if generic else ""
    detail = "; ".join(x for x in (family, ", ".join(ext)) if x)
    return f"{model or 'unknown CPU'} ({detail})" if detail else (model or "unknown CPU")


def synchronize(device: torch.device) -> None:
    """Wait for the device's queued work (timings of CUDA work need it)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _read_int(path: Path) -> int | None:
    try:
        text = path.read_text().split()[0]
    except (OSError, IndexError):
        return None
    return int(text) if text.isdigit() else None  # "max": no limit


def _cgroup_free() -> int | None:
    """memory.max - memory.current of this process's cgroup (v2, or v1's names)."""
    try:
        rel = next((ln.split(":", 2)[2].strip() for ln in Path("/proc/self/cgroup").read_text().splitlines()
                    if ln.startswith("0::")), None)
    except OSError:
        rel = None
    for base, lim, cur in ((Path("/sys/fs/cgroup") / (rel or "/").lstrip("/"), "memory.max", "memory.current"),
                           (Path("/sys/fs/cgroup"), "memory.max", "memory.current"),
                           (Path("/sys/fs/cgroup/memory"), "memory.limit_in_bytes", "memory.usage_in_bytes")):
        limit, used = _read_int(base / lim), _read_int(base / cur)
        if limit is not None and used is not None and limit < 1 << 60:
            return max(0, limit - used)
    return None


def _rlimit_free() -> int | None:
    if resource is None:
        return None
    soft = resource.getrlimit(resource.RLIMIT_AS)[0]
    if soft == resource.RLIM_INFINITY:
        return None
    try:
        vm = next(int(ln.split()[1]) * 1024 for ln in Path("/proc/self/status").read_text().splitlines()
                  if ln.startswith("VmSize:"))
    except (OSError, StopIteration):
        return None
    return max(0, soft - vm)


def _available() -> int | None:
    try:
        return next(int(ln.split()[1]) * 1024 for ln in Path("/proc/meminfo").read_text().splitlines()
                    if ln.startswith("MemAvailable:"))
    except (OSError, StopIteration):
        return None


def free_memory() -> tuple[int | None, str]:
    """Bytes this process may still allocate, and which limit says so."""
    found = [(v, name) for v, name in ((_cgroup_free(), "the cgroup's memory limit"),
                                       (_rlimit_free(), "RLIMIT_AS (ulimit -v)"),
                                       (_available(), "available RAM")) if v is not None]
    return min(found) if found else (None, "unknown")
