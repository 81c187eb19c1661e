"""torch.compile for the rasterizer's hot functions on the CPU, with the eager code as the fallback.

The functions compiled here are ordinary PyTorch (the same code runs eagerly, and the tests hold
both to `reference.py`); PyTorch's compiler (inductor) writes and builds C++ kernels from them,
fusing their element-wise chains. Today that is the planner's pair enumeration (composite.py),
whose compiled form gives the same pairs (the compositor, compiled, measured no faster than eager
on a 2-core Zen 4 and was left eager).

    set_mode("on" | "off")   process-wide; rasterize() itself never decides (train does, by config)
    fast(fn, device, small)  fn, compiled while the mode is on and the inputs live on the CPU, if
                             the compiled form measures faster on this machine (the first calls
                             take turns); eager when `small(*args)` says the call is too small to be
                             worth a graph of its own (sizes 0 and 1 would each compile another)

Compiled kernels are kept in the user's cache folder (`cache_dir()`), so only the first run on a
machine pays for compiling (docs/guide.md, "Compiled kernels"). When no C++ compiler is found, or
compiling fails, every call runs eagerly from then on, and `status()` says why.
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch


@dataclass
class Status:
    mode: str = "off"  # "on" or "off"
    failed: str | None = None  # why compiling was given up (every call eager since)
    compile_s: float = 0.0  # seconds spent since set_mode in calls that compiled (or loaded from the cache) a graph
    graphs: int = 0  # graphs compiled or loaded since set_mode
    chosen: dict[str, dict] = field(default_factory=dict)  # per function: the form kept, and the medians that chose it
    trials: dict[str, dict] = field(default_factory=dict)  # per function: seconds of the calls timed so far


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
    _status.compile_s, _status.graphs = 0.0, 0  # this run's figures (what was chosen stays for the process)
    if mode == "on":
        if compiler() is None:
            _status.failed = "no C++ compiler found (c++, g++ or clang++); running eagerly"
        else:
            _use_cache_dir()
            import torch.fx.experimental._config as fx_config

            # Sizes that happen to be equal in the first call must not be tied together in the graph
            # (each later mismatch would compile another one).
            fx_config.use_duck_shape = False
    return _status


def _use_cache_dir() -> None:
    """Point inductor at `cache_dir()`, unless the user chose a folder of their own. torch writes its
    default (a folder in /tmp) into TORCHINDUCTOR_CACHE_DIR the first time it asks, and processes that
    `--nproc` starts inherit it from the launcher: that value is torch's, not the user's."""
    from torch._inductor.runtime.cache_dir_utils import default_cache_dir

    now = os.environ.get("TORCHINDUCTOR_CACHE_DIR")
    if now is None or os.path.abspath(now) == os.path.abspath(default_cache_dir()):
        os.environ["TORCHINDUCTOR_CACHE_DIR"] = str(cache_dir())


def status() -> Status:
    return _status


def active() -> bool:
    return _status.mode == "on" and _status.failed is None


def _graphs() -> int:
    """Graphs compiled so far in this process (torch's own count)."""
    from torch._dynamo.utils import counters

    return counters["stats"]["unique_graphs"]


# Calls of each compiled function timed eager and compiled, taking turns, before the faster one is
# kept for the rest of the process: whether compiling pays depends on the CPU and on torch's version
# (a 16-core Xeon with torch 2.11 ran the compiled planner slower than eager).
TRIALS = 5


def fast(fn: Callable, device: Callable[..., torch.device], small: Callable[..., bool] | None = None) -> Callable:
    """`fn` (one graph: no data-dependent sizes inside), run compiled while compiling is on,
    `device(*args)` is the CPU, `small(*args)` is false and the compiled form measured faster here
    (TRIALS calls each way, taking turns, after the compiling call); otherwise `fn` itself. Both
    forms must give the same result, so that the choice changes nothing but speed."""
    compiled = None
    name = fn.__name__

    def call(*args, **kw):
        nonlocal compiled
        if not active() or device(*args).type != "cpu" or (small is not None and small(*args)):
            return fn(*args, **kw)
        chosen = _status.chosen.get(name)
        if chosen is not None:
            return (compiled if chosen["kept"] == "compiled" else fn)(*args, **kw)
        if compiled is None:
            compiled = torch.compile(fn, dynamic=True, fullgraph=True)
        trial = _status.trials.setdefault(name, {"eager": [], "compiled": []})
        graphs = _graphs()
        way = "eager" if len(trial["eager"]) < len(trial["compiled"]) else "compiled"
        t = time.perf_counter()
        try:
            out = (fn if way == "eager" else compiled)(*args, **kw)
        except Exception as exc:  # a compiler error, a missing header: eager from now on
            _status.failed = f"compiling failed ({type(exc).__name__}: {' '.join(str(exc).split())[:200]}); running eagerly"
            return fn(*args, **kw)
        dt, new = time.perf_counter() - t, _graphs() - graphs
        if new:  # this call compiled (or loaded from the cache) a graph: its time is the compile's
            _status.compile_s += dt
            _status.graphs += new
        else:
            trial[way].append(dt)
        if min(len(v) for v in trial.values()) >= TRIALS:
            e, c = (1e3 * sorted(trial[k])[TRIALS // 2] for k in ("eager", "compiled"))
            _status.chosen[name] = {"kept": "compiled" if c < e else "eager", "eager_ms": round(e, 3),
                                    "compiled_ms": round(c, 3)}
        return out

    call.__wrapped__ = fn
    return call
