"""The train command's options, by name, into a typed TrainConfig: the one place train
options are set by name (options.apply, which parses text as the command line gives it,
sends `--max-gaussians` and the other options every strategy shares to the strategy chosen,
and refuses an option of a strategy not chosen). Past this edge, train/ edits configs
through their fields alone (`dataclasses.replace`, `TrainConfig.with_refine`, the presets).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import torch

from .. import options
from ..errors import SplatError
from ..project import Project
from ..train.auto import Asked, Chosen, choose, inherited
from ..train.config import PRESETS, Overrides, TrainConfig, preset_config
from ..train.distributed import in_worker


def make_config(preset: str = "default", *, device: str = "cpu", renderer: str = "torch",
                chosen: Chosen | None = None, **given: Any) -> TrainConfig:
    """The preset (or the one `chosen`), for the strategy given (or chosen), then what else
    was chosen, then every option given that is not None (text is parsed as on the command
    line), for `device` and `renderer` (resolved). Checks types and ranges; an option of a
    strategy not chosen is an error."""
    given = {k: v for k, v in given.items() if v is not None}
    chosen = chosen or Chosen()
    start = options.apply(TrainConfig(), {"preset": chosen.preset or preset,
                                          "strategy": given.get("strategy", chosen.strategy or "default")})
    if start.preset not in PRESETS:
        raise SplatError(f"--preset {start.preset!r} is not known; choose one of {', '.join(PRESETS)}")
    cfg = chosen.applied(preset_config(start.preset, start.strategy, device=device, renderer=renderer))
    return options.apply(cfg, given).checked()


def asked(given: dict[str, Any]) -> Asked:
    """What train/auto.py's `choose` reads of the options given (checked first)."""
    cfg = options.apply(TrainConfig(), given)
    options.check(cfg)
    mcmc = replace(TrainConfig(), strategy="mcmc")
    return Asked(cfg, frozenset(given), all(options.resolve(mcmc, k) is not None for k in given))


def resume_overrides(given: dict[str, Any]) -> Overrides:
    """What `train --resume` changes in the run's stored config: the options given, but the
    preset and the seed (the run's own)."""
    named = {k: v for k, v in given.items() if k not in ("preset", "seed") and v is not None}
    return lambda stored: options.apply(stored, named).checked()


def configure(project: Project, given: dict[str, Any], nproc: int | None, device: torch.device, renderer: str,
              resume: bool) -> tuple[TrainConfig, Chosen]:
    """The config `train` runs, and what it chose (train/auto.py) with the processes to run. A
    process the launcher started trains the config it was sent."""
    if in_worker():
        chosen, cfg = inherited()
        if cfg is not None:
            return replace(cfg, device=str(device), renderer=renderer), chosen
        return make_config(**given, device=str(device), renderer=renderer), chosen  # a plain torchrun
    chosen = choose(project, asked(given), nproc, device, resume)
    return make_config(**given, chosen=chosen, device=str(device), renderer=renderer), chosen


def preset_options() -> dict[str, dict[str, Any]]:
    """Each preset's options, by name: those it sets apart from the defaults (the default
    strategy's), as `train --help` shows them."""
    out: dict[str, dict[str, Any]] = {}
    for name in PRESETS:
        base, cfg = TrainConfig(preset=name), preset_config(name)
        out[name] = {n: options.value(cfg, n) for n in options.table(TrainConfig)
                     if options.resolve(cfg, n) is not None and options.value(cfg, n) != options.value(base, n)}
    return out

