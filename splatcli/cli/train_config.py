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
from ..files.checkpoint import read_checkpoint_config
from ..project import Project
from ..train.config import PRESETS, TrainConfig, preset_config
from ..train.distributed import in_worker
from .planning import Asked, Chosen, choose, inherited


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
    """The options given that `planning.choose` decides around, typed (checked first): the last
    place before planning and training that reads options by name."""
    cfg = options.apply(TrainConfig(), given)
    options.check(cfg)
    mcmc = replace(TrainConfig(), strategy="mcmc")
    named = {k: options.value(cfg, k) for k in ("preset", "iterations", "time_budget", "max_size", "appearance",
                                                "strategy", "max_gaussians") if given.get(k) is not None}
    return Asked(**named, downscale=cfg.downscale,
                 mcmc_fits=all(options.resolve(mcmc, k) is not None for k in given))


def resumed(project: Project, cfg: TrainConfig, given: dict[str, Any]) -> TrainConfig:
    """What `train --resume` goes on with: the run's stored config (its latest checkpoint's) with
    the options given on top, but the preset and the seed (the run's own), on `cfg`'s device and
    renderer (either renderer resumes either's run); `cfg` itself where there is no checkpoint yet."""
    path = project.latest_checkpoint()
    if path is None:
        return cfg
    stored = TrainConfig.from_dict(read_checkpoint_config(path), where=f"{path}: stored train config")
    named = {k: v for k, v in given.items() if k not in ("preset", "seed") and v is not None}
    new = options.apply(stored, named).checked()
    if new.compact.enabled and not stored.compact.enabled:
        # --compact added on resume brings its own settings (this version's), not the ones stored unused with the run
        new = replace(new, compact=replace(cfg.compact, enabled=True))
    return replace(new, device=cfg.device, renderer=cfg.renderer)


def configure(project: Project, given: dict[str, Any], nproc: int | None, device: torch.device, renderer: str,
              resume: bool) -> tuple[TrainConfig, Chosen]:
    """The one config `train` runs (with --resume, the stored one with the options given on
    top), and what it chose (planning.py) with the processes to run. A process the launcher
    started trains the config it was sent."""
    if in_worker():
        chosen, sent = inherited()
        if sent is not None:  # built and resumed by the launcher
            return replace(sent, device=str(device), renderer=renderer), chosen
        cfg = make_config(**given, device=str(device), renderer=renderer)  # a plain torchrun
    else:
        chosen = choose(project, asked(given), nproc, device, resume)
        cfg = make_config(**given, chosen=chosen, device=str(device), renderer=renderer)
    return (resumed(project, cfg, given) if resume else cfg), chosen


def preset_options() -> dict[str, dict[str, Any]]:
    """Each preset's options, by name: those it sets apart from the defaults (the default
    strategy's), as `train --help` shows them."""
    out: dict[str, dict[str, Any]] = {}
    for name in PRESETS:
        base, cfg = TrainConfig(preset=name), preset_config(name)
        out[name] = {n: options.value(cfg, n) for n in options.table(TrainConfig)
                     if options.resolve(cfg, n) is not None and options.value(cfg, n) != options.value(base, n)}
    return out

