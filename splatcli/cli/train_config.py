"""The train command's options, by name, into a typed TrainConfig: the one place train
options are taken by name. `options.parse` parses them once (text as the command line gives
it, `--max-gaussians` and the other options every strategy shares sent to the strategy chosen,
an option of a strategy not chosen refused) into an `options.Given`; planning.py reads it by
field and builds the one config a run trains from it. Past this edge, train/ edits configs
through their fields alone (`dataclasses.replace`, `TrainConfig.with_refine`, the presets).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import torch

from .. import options
from ..errors import SplatError
from ..project import Project
from ..train.config import PRESETS, TrainConfig, preset_config
from ..train.distributed import in_worker
from .planning import Chosen, build, choose, inherited, resumed


def make_config(preset: str | None = None, *, device: str = "cpu", renderer: str = "torch",
                chosen: Chosen | None = None, **given: Any) -> TrainConfig:
    """The config of the options given (None: not given) and of what was `chosen`, for `device`
    and `renderer` (resolved): planning.build of them, as `train` builds its own."""
    return build(options.parse(TrainConfig, {**given, "preset": preset}), chosen or Chosen(), device, renderer)


def configure(project: Project, given: dict[str, Any], nproc: int | None, device: torch.device, renderer: str,
              resume: bool) -> tuple[TrainConfig, Chosen]:
    """The one config `train` runs (with --resume, the stored one with the options given on
    top), and what it chose (planning.py) with the processes to run. A process the launcher
    started trains the config it was sent."""
    parsed = options.parse(TrainConfig, given)
    chosen, sent = inherited() if in_worker() else (choose(project, parsed, nproc, device, resume), None)
    if sent is not None:  # built and resumed by the launcher
        return replace(sent, device=str(device), renderer=renderer), chosen
    cfg = build(parsed, chosen, str(device), renderer)  # (a plain torchrun: each process builds its own)
    cfg = resumed(project, cfg, parsed) if resume else cfg
    if given.get("compact_keep") is not None and not cfg.compact.enabled:
        raise SplatError("--compact-keep is the share --compact keeps: give --compact too")
    return cfg, chosen


def preset_options() -> dict[str, dict[str, Any]]:
    """Each preset's options, by name: those it sets apart from the defaults (the default
    strategy's), as `train --help` shows them."""
    out: dict[str, dict[str, Any]] = {}
    for name in PRESETS:
        base, cfg = TrainConfig(preset=name), preset_config(name)
        out[name] = {n: options.value(cfg, n) for n in options.table(TrainConfig)
                     if options.resolve(cfg, n) is not None and options.value(cfg, n) != options.value(base, n)}
    return out
