"""Training checkpoints: tensors and plain Python data only, never code.

A checkpoint is a `torch.save` zip archive of one dict holding tensors, ints,
floats, strings, bools, None, lists, tuples and dicts. It is read back with
`torch.load(weights_only=True)`, whose unpickler refuses every other global, so
a file carrying a pickled object (a `__reduce__` payload, a class instance)
cannot run code: it is refused with a one-line `SplatError`.

Layout (schema 1):

    {"format": "splatcli-checkpoint", "schema": 1, "step": int,
     "sh_degree": int,                    # the active SH degree at `step`
     "gaussians": {means, quats, log_scales, opacity_logits, sh},   # raw, see gaussians.py
     "optimizer": {...},                  # per-parameter Adam state_dicts (train.py)
     "strategy": {...},                   # densification state (strategy/); a state's
                                          # "filter3d" rows [N] are folded by model()
     "rng": {"torch": ByteTensor, "cuda": [ByteTensor] | None},
     "config": {...},                     # the resolved TrainConfig as plain data
     "appearance": {...} | None,          # optional: train --appearance's per-image transforms and Adam
     "extra": {...}}                      # loop counters: elapsed seconds, bad steps, ...

`sh` is stored at the degree training allocated; `load_gaussians` truncates it
to `sh_degree` (what render, eval and export use), so unused bands never leave.
"""

from __future__ import annotations

import pickle
import re
import warnings
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from ..errors import SplatError
from ..gaussians import Gaussians, num_sh_bases
from .atomic import atomic_path

CHECKPOINT_SCHEMA = 1
CHECKPOINT_FORMAT = "splatcli-checkpoint"
FILTER_ROWS = "filter3d"  # a strategy state's 3D smoothing filter, world units (strategy/mip.py)
_REQUIRED = ("format", "schema", "step", "sh_degree", "gaussians", "optimizer", "strategy", "rng", "config")


@dataclass
class Checkpoint:
    """A checkpoint as loaded. `gaussians.sh` keeps every stored band; use
    `model()` for the model truncated to the active degree."""

    path: Path
    schema: int
    step: int
    gaussians: Gaussians
    sh_degree: int  # active SH degree at `step`
    optimizer: dict[str, Any]
    strategy: dict[str, Any]
    rng: dict[str, Any]
    config: dict[str, Any]
    extra: dict[str, Any] = field(default_factory=dict)
    appearance: dict[str, Any] = field(default_factory=dict)  # train --appearance (empty without); never exported

    def model(self) -> Gaussians:
        """The Gaussians as drawn: truncated to the active SH degree, with the 3D
        smoothing filter of `train --mip-filter` folded into the scales and opacities
        (gaussians.smooth_3d), so every reader and exported file sees the same model."""
        g = self.gaussians.with_sh_degree(self.sh_degree)
        for state in self.strategy.values():
            f = state.get(FILTER_ROWS) if isinstance(state, dict) else None
            if isinstance(f, Tensor):
                if tuple(f.shape) != (len(g),) or not bool(torch.isfinite(f).all()) or bool((f < 0).any()):
                    raise SplatError(f"{self.path}: checkpoint's {FILTER_ROWS} is not [{len(g)}] finite values >= 0")
                g = g.smoothed(f.to(g.device))
        return g

    @property
    def antialiased(self) -> bool:
        """Trained with the 2D filter (`train --mip-filter`): draw it with it too."""
        return bool(self.config.get("mip_filter"))


def save_checkpoint(
    path: str | Path,
    *,
    step: int,
    gaussians: Gaussians,
    sh_degree: int,
    optimizer: dict[str, Any] | None = None,
    strategy: dict[str, Any] | None = None,
    rng: dict[str, Any] | None = None,
    config: dict[str, Any] | None = None,
    extra: dict[str, Any] | None = None,
    appearance: dict[str, Any] | None = None,
) -> Path:
    """Write a checkpoint atomically (temp file, fsync, rename): a crash mid-write
    leaves the previous file, never a partial one. Tensors are detached and moved
    to CPU so the file loads on any device."""
    path = Path(path)
    if not 0 <= int(sh_degree) <= gaussians.sh_degree:
        raise ValueError(f"sh_degree {sh_degree} outside the stored 0..{gaussians.sh_degree}")
    payload = {
        "format": CHECKPOINT_FORMAT,
        "schema": CHECKPOINT_SCHEMA,
        "step": int(step),
        "sh_degree": int(sh_degree),
        "gaussians": {k: v.detach().cpu().contiguous() for k, v in gaussians.as_dict().items()},
        "optimizer": _to_cpu(optimizer or {}),
        "strategy": _to_cpu(strategy or {}),
        "rng": _to_cpu(rng or {}),
        "config": dict(config or {}),
        "extra": _to_cpu(extra or {}),
    }
    if appearance:
        payload["appearance"] = _to_cpu(appearance)
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)
    return path


def load_checkpoint(path: str | Path, device: torch.device | str = "cpu") -> Checkpoint:
    """Read and validate a checkpoint. Every failure (missing, truncated, not a
    checkpoint, a pickled object, a newer schema, missing keys, inconsistent
    shapes) is a one-line `SplatError` naming the file."""
    path = Path(path)
    raw = _safe_load(path)
    if not isinstance(raw, dict) or raw.get("format") != CHECKPOINT_FORMAT:
        raise SplatError(f"{path}: not a splatcli checkpoint")
    schema = raw.get("schema")
    if not isinstance(schema, int):
        raise SplatError(f"{path}: checkpoint has no valid schema version")
    if schema > CHECKPOINT_SCHEMA:
        raise SplatError(
            f"{path}: checkpoint schema {schema} is newer than this splatcli reads ({CHECKPOINT_SCHEMA}); upgrade splatcli"
        )
    missing = [k for k in _REQUIRED if k not in raw]
    if missing:
        raise SplatError(f"{path}: checkpoint is missing {', '.join(missing)}")
    g = raw["gaussians"]
    if not isinstance(g, dict) or any(not isinstance(g.get(k), Tensor) for k in Gaussians.PARAM_NAMES):
        raise SplatError(f"{path}: checkpoint's gaussians must hold tensors {', '.join(Gaussians.PARAM_NAMES)}")
    gaussians = _validate_gaussians(path, g)
    step, sh_degree = raw["step"], raw["sh_degree"]
    if not isinstance(step, int) or step < 0:
        raise SplatError(f"{path}: checkpoint step {step!r} is not a non-negative integer")
    if not isinstance(sh_degree, int) or not 0 <= sh_degree <= gaussians.sh_degree:
        raise SplatError(f"{path}: checkpoint sh_degree {sh_degree!r} is outside 0..{gaussians.sh_degree}")
    for k in ("optimizer", "strategy", "rng", "config"):
        if not isinstance(raw[k], dict):
            raise SplatError(f"{path}: checkpoint's {k} is not a mapping")
    dev = torch.device(device)
    return Checkpoint(
        path=path,
        schema=schema,
        step=step,
        gaussians=gaussians.to(dev),
        sh_degree=sh_degree,
        optimizer=raw["optimizer"],
        strategy=raw["strategy"],
        rng=raw["rng"],
        config=raw["config"],
        extra=raw.get("extra") or {},
        appearance=raw["appearance"] if isinstance(raw.get("appearance"), dict) else {},
    )


def _mapped(path: str | Path) -> dict[str, Any]:
    """A checkpoint with its tensors mapped, not read, once it is one with a stored train config."""
    path = Path(path)
    raw = _safe_load(path, mmap=True)
    if not isinstance(raw, dict) or raw.get("format") != CHECKPOINT_FORMAT or not isinstance(raw.get("config"), dict):
        raise SplatError(f"{path}: not a splatcli checkpoint with a stored train config")
    return raw


def read_checkpoint_config(path: str | Path) -> dict[str, Any]:
    """The train config a checkpoint stores, for `train --resume` to build the run's config
    before the checkpoint is loaded."""
    return _mapped(path)["config"]


def read_checkpoint_world(path: str | Path) -> int | None:
    """How many data-parallel processes trained up to a checkpoint (None: not recorded, as in
    checkpoints written before it was), for `train --resume` to go on with as many."""
    world = (_mapped(path).get("extra") or {}).get("world")
    return world if isinstance(world, int) and world >= 1 else None


def load_gaussians(path: str | Path, device: torch.device | str = "cpu") -> Gaussians:
    """The trained model in a checkpoint, truncated to its active SH degree (what
    render, eval and export use)."""
    return load_checkpoint(path, device).model()


# ---- internals ---------------------------------------------------------------


def _safe_load(path: Path, mmap: bool = False) -> Any:
    if not path.exists():
        raise SplatError(f"{path}: checkpoint not found")
    if not path.is_file():
        raise SplatError(f"{path}: checkpoint is not a file")
    if path.stat().st_size == 0:
        raise SplatError(f"{path}: not a readable checkpoint, truncated or corrupt (the file is empty)")
    # save_checkpoint always writes torch's zip archive. Anything else (a raw pickle
    # stream, a truncated archive, random bytes) is refused before any unpickling.
    if not zipfile.is_zipfile(path):
        raise SplatError(f"{path}: not a readable checkpoint, truncated or corrupt (not a PyTorch zip archive)")
    try:
        # weights_only=True: the unpickler only rebuilds tensors and plain containers,
        # so a crafted file can never run code on load.
        with warnings.catch_warnings():  # torch warns about foreign pickle protocols before refusing
            warnings.simplefilter("ignore")
            return torch.load(path, map_location="cpu", weights_only=True, mmap=mmap)
    except pickle.UnpicklingError as exc:
        # torch's message is a paragraph that suggests weights_only=False; keep only the culprit.
        m = re.search(r"GLOBAL ([\w.]+)", str(exc))
        if m is None:
            raise SplatError(f"{path}: not a readable checkpoint, truncated or corrupt (bad pickle data)") from None
        raise SplatError(
            f"{path}: refused: the checkpoint holds objects other than tensors and plain data "
            f"({m.group(1)}); it was not loaded"
        ) from None
    except (RuntimeError, EOFError, zipfile.BadZipFile, ValueError, OSError) as exc:
        reason = " ".join(str(exc).split())[:160]
        raise SplatError(f"{path}: not a readable checkpoint, truncated or corrupt ({reason})") from None
    except Exception as exc:  # any other unpickling failure is still a bad file, not a bug
        reason = f"{type(exc).__name__}: {' '.join(str(exc).split())[:160]}"
        raise SplatError(f"{path}: not a readable checkpoint ({reason})") from None


def _validate_gaussians(path: Path, g: dict[str, Tensor]) -> Gaussians:
    n = g["means"].shape[0] if g["means"].dim() == 2 else -1
    expect = {"means": (n, 3), "quats": (n, 4), "log_scales": (n, 3), "opacity_logits": (n,)}
    for k, shape in expect.items():
        if tuple(g[k].shape) != shape or not g[k].is_floating_point():
            raise SplatError(f"{path}: checkpoint tensor {k} has shape {tuple(g[k].shape)}, expected {shape}")
    sh = g["sh"]
    k = sh.shape[1] if sh.dim() == 3 else -1
    if sh.dim() != 3 or sh.shape[0] != n or sh.shape[2] != 3 or k not in [num_sh_bases(d) for d in range(5)]:
        raise SplatError(f"{path}: checkpoint tensor sh has shape {tuple(sh.shape)}, expected [{n}, (d+1)^2, 3]")
    return Gaussians(**{name: g[name] for name in Gaussians.PARAM_NAMES})


def _to_cpu(obj: Any) -> Any:
    """Detach tensors and move them to CPU, recursively through plain containers."""
    if isinstance(obj, Tensor):
        return obj.detach().cpu()
    if isinstance(obj, dict):
        return {k: _to_cpu(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_to_cpu(v) for v in obj]
    if isinstance(obj, tuple):
        return tuple(_to_cpu(v) for v in obj)
    return obj
