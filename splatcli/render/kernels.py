"""torch.compile for the rasterizer's hot functions on the CPU, with the eager code as the fallback.

The functions compiled here are ordinary PyTorch (the same code runs eagerly, and the tests hold
both to `reference.py`); PyTorch's compiler (inductor) writes and builds C++ kernels from them,
fusing the element-wise chains so that each [blocks, pixels, slots] tensor is read and written
fewer times. Nothing here changes a result beyond float32 rounding.

    set_mode("on" | "off")   process-wide; rasterize() itself never decides (train does, by config)
    fast(fn, device, small)  fn, compiled while the mode is on and the inputs live on the CPU;
                             eager when `small(*args)` says the call is too small to be worth a
                             compiled graph of its own (sizes 0 and 1 would each compile another)

Compiled kernels are kept in the user's cache folder (`cache_dir()`), so only the first run on a
machine pays for compiling (docs/guide.md, "Compiled kernels"). When no C++ compiler is found, or
compiling fails, every call runs eagerly from then on, and `status()` says why.
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch


@dataclass
class Status:
    mode: str = "off"  # "on" or "off"
    failed: str | None = None  # why compiling was given up (every call eager since)
    compile_s: float = 0.0  # seconds spent since set_mode in calls that compiled (or loaded from the cache) a graph
    graphs: int = 0  # graphs compiled or loaded since set_mode


_status = Status()


def cache_dir() -> Path:
    """Where compiled kernels persist: $SPLATCLI_CACHE_DIR, else $XDG_CACHE_HOME/splatcli, else
    ~/.cache/splatcli; then `inductor/`."""
    env = os.environ.get("SPLATCLI_CACHE_DIR")
    if env:
        base = Path(env)
    else:
        base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "splatcli"
    return base / "inductor"


def compiler() -> str | None:
    """The C++ compiler inductor would use ($CXX, else c++, g++, clang++), or None."""
    for name in (os.environ.get("CXX"), "c++", "g++", "clang++"):
        if name and shutil.which(name):
            return name
    return None


def warm_cache() -> bool:
    """Whether this machine's cache already holds compiled kernels (a quick look, not a promise)."""
    d = cache_dir()
    return d.is_dir() and any(d.iterdir())


def set_mode(mode: str) -> Status:
    """Turn compiling on or off for this process. "on" without a C++ compiler is "off" with the
    reason in status().failed."""
    if mode not in ("on", "off"):
        raise ValueError(f"compile mode must be 'on' or 'off', got {mode!r}")
    _status.mode = mode
    _status.compile_s, _status.graphs = 0.0, 0  # this run's figures
    if mode == "on":
        if compiler() is None:
            _status.failed = "no C++ compiler found (c++, g++ or clang++); running eagerly"
        else:
            os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", str(cache_dir()))
            import torch.fx.experimental._config as fx_config

            # Sizes that happen to be equal in the first call must not be tied together in the graph
            # (each later mismatch would compile another one).
            fx_config.use_duck_shape = False
    return _status


def status() -> Status:
    return _status


def active() -> bool:
    return _status.mode == "on" and _status.failed is None


def _graphs() -> int:
    """Graphs compiled so far in this process (torch's own count)."""
    from torch._dynamo.utils import counters

    return counters["stats"]["unique_graphs"]


def fast(fn: Callable, device: Callable[..., torch.device], small: Callable[..., bool] | None = None) -> Callable:
    """`fn` (one graph: no data-dependent sizes inside), run compiled while compiling is on,
    `device(*args)` is the CPU and `small(*args)` is false; otherwise `fn` itself."""
    compiled = None

    def call(*args, **kw):
        nonlocal compiled
        if not active() or device(*args).type != "cpu" or (small is not None and small(*args)):
            return fn(*args, **kw)
        if compiled is None:
            compiled = torch.compile(fn, dynamic=True, fullgraph=True)
        graphs = _graphs()
        t = time.perf_counter()
        try:
            out = compiled(*args, **kw)
        except Exception as exc:  # a compiler error, a missing header: eager from now on
            _status.failed = f"compiling failed ({type(exc).__name__}: {' '.join(str(exc).split())[:200]}); running eagerly"
            return fn(*args, **kw)
        new = _graphs() - graphs
        if new:  # this call compiled (or loaded from the cache) a graph: its time is the compile's
            _status.compile_s += time.perf_counter() - t
            _status.graphs += new
        return out

    call.__wrapped__ = fn
    return call
