"""What `splatcli train` is asked to do, and what it reports back.

`TrainConfig` holds every training default once, named after the 3DGS paper
(Kerbl et al. 2023) where it comes from one; the strategies' hyperparameters are
nested in it, declared once in strategy/. Presets override a few of them.
`TrainSummary` is the contract other commands read from the manifest
(`steps.train.summary`).

Options are given flat, as on the command line (`max_gaussians`, `compact`,
`compact_finetune`, `refine_stop`); `OPTION_PATHS` says where each one lives.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any

from ..errors import SplatError
from ..gaussians import Histogram
from ..strategy import (CompactConfig, CompactReport, DefaultStrategyConfig, MCMCStrategyConfig, RegularizeConfig,
                        ShAutoConfig, SupportConfig)
from .appearance import APPEARANCE, ExposureConfig

MAX_SH_DEGREE = 3


@dataclass(frozen=True)
class TrainConfig:
    # ---- schedule ------------------------------------------------------------
    iterations: int = 30_000  # the paper's schedule
    preset: str = "default"
    sh_degree: int | str = 3  # 0..3, or "auto" (train at 3, keep the lowest degree within sh_auto.tol_db)
    sh_degree_interval: int = 1000  # the active SH degree grows by one every this many steps

    time_budget: float | None = None  # training seconds: plan the schedule to end within them (train/plan.py)

    # ---- data ----------------------------------------------------------------
    downscale: float = 1.0  # divide the stored image size by this
    max_size: int = 1600  # then cap the longest side (pixels), as 3DGS does for large photos
    coarse_scale: float = 1.0  # coarse-to-fine: resolution (fraction of the above) at step 0; 1 = off
    coarse_until: float = 0.5  # ... rising linearly (in steps of 1/8) to full resolution by this fraction of `iterations`
    eval_every: int = 1000  # held-out PSNR/SSIM every this many steps (0: only at the end)
    eval_max_views: int = 0  # 0: every held-out view; else an evenly spaced subset
    log_every: int = 100  # one train_log.jsonl line every this many steps
    checkpoint_every: int = 5000  # also on interrupt and at the end
    keep_checkpoints: int = 2  # older step files are deleted (each holds params + Adam state)

    # ---- initialisation ------------------------------------------------------
    init_opacity: float = 0.1  # sigma^-1(0.1), the paper's (--strategy mcmc: mcmc_init_opacity)
    init_random_points: int = 100_000  # Blender scenes with no SfM points: uniform in the bounds (3DGS)
    init_knn: int = 3  # log scale from the RMS distance to the 3 nearest neighbours
    init_ply: str | None = None  # start from a splat file instead
    init_far: int = 0  # also points on a far sphere (this many over the whole sphere; those some training view sees are kept)
    init_far_radius: float = 5.0  # ... of this radius x the cameras' extent, about their centre, coloured from the views

    # ---- optimiser (Adam, per attribute) -------------------------------------
    lr_means: float = 1.6e-4  # x scene extent, decays exponentially ...
    lr_means_final: float = 1.6e-6  # ... to this x extent over `iterations`
    lr_sh0: float = 2.5e-3
    lr_shN_div: float = 20.0  # higher SH bands learn 20x slower
    lr_opacity: float = 0.05  # the reference code's 0.05 (the paper's table says 0.05 too)
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    adam_eps: float = 1e-15  # as 3DGS: moments of tiny gradients must still move parameters
    adam_beta1: float = 0.9
    adam_beta2: float = 0.999

    # ---- loss ----------------------------------------------------------------
    lambda_dssim: float = 0.2  # loss = (1 - l) L1 + l (1 - SSIM)
    mask_mode: str = "auto"  # the project's masks: auto | ignore | background | off (Project.mask_mode)
    appearance: str = "none"  # --appearance: "none" or "exposure" (a colour transform per training image, appearance.py)
    exposure: ExposureConfig = field(default_factory=ExposureConfig)  # its learning rate and pull towards identity

    # ---- strategies (strategy/) ----------------------------------------------
    density: str = "default"  # --strategy: "default" (3DGS adaptive density control) or "mcmc" (a fixed budget)
    strategy: DefaultStrategyConfig = field(default_factory=DefaultStrategyConfig)  # adaptive density control
    mcmc: MCMCStrategyConfig = field(default_factory=MCMCStrategyConfig)  # --strategy mcmc (its schedule and cap: strategy's)
    reg: RegularizeConfig = field(default_factory=RegularizeConfig)  # --opacity-reg, --scale-reg (mcmc has its own)
    support: SupportConfig = field(default_factory=SupportConfig)  # --prune-views
    sh_auto: ShAutoConfig = field(default_factory=ShAutoConfig)  # used with sh_degree "auto"
    compact: CompactConfig = field(default_factory=CompactConfig)  # --compact
    mip_filter: bool = False  # Mip-Splatting's 3D smoothing filter and 2D filter (strategy/mip.py)

    # ---- reliability ---------------------------------------------------------
    max_bad_steps: int = 20  # consecutive non-finite steps before TrainingDiverged

    # ---- run -----------------------------------------------------------------
    seed: int = 0
    device: str = "cpu"  # resolved device string, for the record

    @property
    def max_sh_degree(self) -> int:
        """The degree trained (auto trains the full degree and chooses after)."""
        return MAX_SH_DEGREE if self.sh_degree == "auto" else int(self.sh_degree)

    def train_scale(self, step: int) -> float:
        """The resolution (a fraction of the training resolution) step `step` renders at."""
        end = self.coarse_until * self.iterations
        if self.coarse_scale >= 1.0 or step >= end:
            return 1.0
        s = self.coarse_scale + (1.0 - self.coarse_scale) * step / end
        return min(1.0, math.ceil(s * 8) / 8)

    @property
    def total_steps(self) -> int:
        """Optimiser steps including the compaction fine-tune."""
        return self.iterations + (self.compact.finetune if self.compact.enabled else 0)

    def for_world(self, k: int) -> "TrainConfig":
        """The schedule K data-parallel ranks run so as to see the same images as one
        process: each step averages K views' gradients, so every step count is divided
        by K, and Adam follows the square-root scaling rule for a K-times larger batch
        (Malladi et al. 2022, as gsplat and Grendel-GS apply it): learning rates times
        sqrt(K), epsilon divided by sqrt(K), betas raised to the power K (one step then
        forgets as much history as K steps did). K = 1 returns the config unchanged."""
        if k == 1:
            return self
        steps = {name: max(1, round(option(self, name) / k)) for name in _STEP_COUNTS if option(self, name) > 0}
        steps["refine_stop"] = round(self.strategy.refine_stop / k)
        r = math.sqrt(k)
        # (not exposure_lr: the transforms' Adam steps a view's row once per time the view is
        # trained, however many ranks share a step; appearance.py)
        lrs = {name: option(self, name) * r for name in ("lr_means", "lr_means_final", "lr_sh0", "lr_opacity",
                                                           "lr_scales", "lr_quats")}
        return with_options(self, {**steps, **lrs, "adam_eps": self.adam_eps / r,
                                   "adam_beta1": self.adam_beta1 ** k, "adam_beta2": self.adam_beta2 ** k})

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict[str, Any], where: str = "stored train config") -> "TrainConfig":
        """The stored form back (unknown keys ignored; flat option names accepted). A
        value of the wrong type or out of range (a damaged or hand-edited file) is a
        one-line SplatError naming `where` and the key."""
        by_path = {path: name for name, path in OPTION_PATHS.items()}
        opts: dict[str, Any] = {}
        for k, v in d.items():
            if k in _NESTED and isinstance(v, dict):
                opts.update({by_path[(k, s)]: x for s, x in v.items() if (k, s) in by_path})
            elif k in OPTION_PATHS:
                opts[k] = v
        if isinstance(d.get("mcmc"), dict) and "shrink" not in d["mcmc"]:
            opts.setdefault("mcmc_shrink", 1.0)  # stored before the option: its copies kept their scale
        for k, v in opts.items():
            if not _type_ok(v, OPTION_TYPES[k]):
                shown = " ".join(repr(v).split())[:40]
                raise SplatError(f"{where}: {k} is {shown}, expected {OPTION_TYPES[k]}")
        cfg = with_options(TrainConfig(), opts)
        try:
            _check(cfg)
        except SplatError as exc:
            raise SplatError(f"{where}: {exc}") from None
        return cfg


_NESTED = {"strategy": "", "reg": "", "support": "", "sh_auto": "sh_auto_", "compact": "compact_", "mcmc": "mcmc_",
           "exposure": "exposure_"}  # nested config -> option prefix


def _option_paths() -> dict[str, tuple[str, ...]]:
    paths: dict[str, tuple[str, ...]] = {}
    for f in fields(TrainConfig):
        if f.name not in _NESTED:
            paths[f.name] = (f.name,)
    defaults = TrainConfig()
    for name, prefix in _NESTED.items():
        for sub in fields(type(getattr(defaults, name))):
            paths[prefix + sub.name] = (name, sub.name)
    paths["compact"] = ("compact", "enabled")  # --compact
    paths.pop("compact_enabled")
    return paths


OPTION_PATHS = _option_paths()


def _option_types() -> dict[str, str]:
    """Each flat option's annotation, as written in the dataclasses ("int | None", ...)."""
    types: dict[str, str] = {}
    for name, path in OPTION_PATHS.items():
        owner: Any = TrainConfig
        for part in path[:-1]:
            owner = {f.name: f for f in fields(owner)}[part].default_factory  # type: ignore[union-attr]
        types[name] = str({f.name: f for f in fields(owner)}[path[-1]].type)
    return types


OPTION_TYPES = _option_types()


def _type_ok(v: Any, annotation: str) -> bool:
    kinds = {k.strip() for k in annotation.split("|")}
    if v is None:
        return "None" in kinds
    if isinstance(v, bool):
        return "bool" in kinds
    if isinstance(v, int):
        return bool(kinds & {"int", "float"})
    if isinstance(v, float):
        return "float" in kinds and math.isfinite(v)
    if isinstance(v, str):
        return "str" in kinds
    return False


def with_options(cfg: TrainConfig, options: dict[str, Any]) -> TrainConfig:
    """`cfg` with flat options applied (see OPTION_PATHS); an unknown name is a bug."""
    top: dict[str, Any] = {}
    subs: dict[str, dict[str, Any]] = {}
    for k, v in options.items():
        path = OPTION_PATHS[k]
        if len(path) == 1:
            top[path[0]] = v
        else:
            subs.setdefault(path[0], {})[path[1]] = v
    for name, vals in subs.items():
        top[name] = replace(getattr(cfg, name), **vals)
    return replace(cfg, **top)


def option(cfg: TrainConfig, name: str) -> Any:
    """The value of a flat option (see OPTION_PATHS)."""
    v: Any = cfg
    for part in OPTION_PATHS[name]:
        v = getattr(v, part)
    return v


# Presets override the defaults above; explicit options override the preset.
PRESETS: dict[str, dict[str, Any]] = {
    # The paper: 30k steps, densify 500..15k.
    "default": {},
    # A CPU preset with the same shape in fewer steps. Most of the PSNR arrives in
    # the first 7k steps (the paper reports its 7k numbers for that reason); densifying
    # for the first ~half keeps the paper's grow-then-settle ratio and gives the
    # last 3k steps to refine a fixed set, which is where SSIM improves.
    # Coarse to fine: the first half renders at a resolution rising from 1/4 (bench/versus.py, lego
    # 200 px, 2k steps: the PSNR-against-time curve above the full-resolution one everywhere,
    # 1.15-1.5x sooner to a given PSNR; docs/benchmarks.md, "time to quality").
    # No opacity reset: with 4k steps of densifying, the reset at 3k leaves too few to win the
    # model back (bench/overfit.py: held-out 24.4 -> 16.8 dB on the object capture, 23.6 at the
    # end; without it 25.0, its best; fox from its photos ends at 32.21, 0.03 below its best).
    "fast": {"iterations": 7000, "refine_stop": 4000, "reset_every": 0, "checkpoint_every": 1000,
             "init_random_points": 10_000, "coarse_scale": 0.25, "coarse_until": 0.5},
    # `make demo` on sample_data (320x240, ~2k SfM points): a few minutes on 2 cores.
    # Everything 3DGS does, compressed: densify 300..900, SH every 300 steps, and a
    # budget of 20k Gaussians (unbudgeted it reaches ~30k for +0.3 dB at ~1.5x the time).
    "demo": {"iterations": 1500, "refine_start": 300, "refine_stop": 900, "reset_every": 0,
             "sh_degree_interval": 300, "eval_every": 500, "checkpoint_every": 500,
             "max_size": 256, "init_random_points": 20_000, "max_gaussians": 20_000},
}


def make_config(preset: str = "default", **options: Any) -> TrainConfig:
    """The preset, then every option that is not None. Validates ranges."""
    if preset not in PRESETS:
        raise SplatError(f"--preset {preset!r} is not known; choose one of {', '.join(PRESETS)}")
    cfg = with_options(replace(TrainConfig(), preset=preset), PRESETS[preset])
    given = {k: v for k, v in options.items() if v is not None}
    sh = given.get("sh_degree")
    if isinstance(sh, str):
        s = sh.strip().lower()
        if s == "auto":
            given["sh_degree"] = "auto"
        elif s.isdigit() and 0 <= int(s) <= MAX_SH_DEGREE:
            given["sh_degree"] = int(s)
        else:
            raise SplatError(f"--sh-degree {sh!r}: expected 0, 1, 2, 3 or auto")
    cfg = with_options(cfg, given)
    _check(cfg)
    return cfg


DENSITY = ("default", "mcmc")  # --strategy
MASK_MODES = ("auto", "ignore", "background", "off")  # --mask-mode (Project.mask_mode resolves them)

# Options counted in optimiser steps (TrainConfig.for_world divides them by the ranks).
_STEP_COUNTS = ("iterations", "sh_degree_interval", "eval_every", "log_every", "checkpoint_every", "refine_start",
                "refine_every", "reset_every", "compact_finetune")

# Counts that must be at least 1 / at least 0 (flat option names).
_AT_LEAST_1 = ("sh_degree_interval", "log_every", "checkpoint_every", "keep_checkpoints", "refine_every",
               "split_samples", "init_knn", "compact_rounds", "sh_auto_val_views")
_AT_LEAST_0 = ("reset_every", "eval_max_views", "init_random_points", "init_far", "prune_views", "refine_start", "refine_stop", "compact_finetune",
               "max_bad_steps")


def _check(cfg: TrainConfig) -> None:
    if isinstance(cfg.sh_degree, str) and cfg.sh_degree != "auto":
        raise SplatError(f"--sh-degree {cfg.sh_degree!r}: expected 0, 1, 2, 3 or auto")
    for name in _AT_LEAST_1 + _AT_LEAST_0:
        v, low = option(cfg, name), 1 if name in _AT_LEAST_1 else 0
        if not isinstance(v, int) or v < low:
            raise SplatError(f"{name} {v!r}: must be a whole number of at least {low}")
    if cfg.time_budget is not None and not (math.isfinite(cfg.time_budget) and cfg.time_budget > 0):
        raise SplatError(f"--time-budget {cfg.time_budget}: must be a positive number of seconds")
    if cfg.iterations < 1:
        raise SplatError(f"--iterations {cfg.iterations}: must be at least 1")
    if isinstance(cfg.sh_degree, int) and not 0 <= cfg.sh_degree <= MAX_SH_DEGREE:
        raise SplatError(f"--sh-degree {cfg.sh_degree}: expected 0..{MAX_SH_DEGREE} or auto")
    if cfg.strategy.max_gaussians is not None and cfg.strategy.max_gaussians < 1:
        raise SplatError(f"--max-gaussians {cfg.strategy.max_gaussians}: must be at least 1")
    if cfg.mask_mode not in MASK_MODES:
        raise SplatError(f"--mask-mode {cfg.mask_mode!r} is not known; choose one of {', '.join(MASK_MODES)}")
    if cfg.density not in DENSITY:
        raise SplatError(f"--strategy {cfg.density!r} is not known; choose one of {', '.join(DENSITY)}")
    if cfg.density == "mcmc" and cfg.strategy.max_gaussians is None:
        raise SplatError("--strategy mcmc needs --max-gaussians N: the fixed number of Gaussians it grows to")
    if not (math.isfinite(cfg.init_far_radius) and cfg.init_far_radius > 1):
        raise SplatError(f"init_far_radius {cfg.init_far_radius}: must be more than 1 (the sphere lies outside the cameras)")
    for name in ("init_opacity", "mcmc_init_opacity", "mcmc_min_opacity"):
        if not 0 < option(cfg, name) < 1:
            raise SplatError(f"{name} {option(cfg, name)}: must be in (0, 1)")
    for name in ("mcmc_relocate_until", "mcmc_reg_until", "mcmc_grow_until"):
        if not 0 <= option(cfg, name) <= 1:
            raise SplatError(f"{name} {option(cfg, name)}: must be in [0, 1] (a fraction of the run, or of the refinement window for mcmc_grow_until)")
    if not (math.isfinite(cfg.mcmc.spread) and cfg.mcmc.spread >= 0):
        raise SplatError(f"mcmc_spread {cfg.mcmc.spread}: must be 0 or more")
    if not (math.isfinite(cfg.mcmc.shrink) and cfg.mcmc.shrink >= 1):
        raise SplatError(f"mcmc_shrink {cfg.mcmc.shrink}: must be 1 (no shrinking) or more")
    for name in ("opacity_reg", "scale_reg"):
        v = option(cfg, name)
        if not (math.isfinite(v) and v >= 0):
            raise SplatError(f"--{name.replace('_', '-')} {v}: must be 0 or more")
    if cfg.downscale <= 0 or cfg.downscale > 64:
        raise SplatError(f"--downscale {cfg.downscale}: must be in (0, 64]")
    if cfg.max_size < 16:
        raise SplatError(f"--max-size {cfg.max_size}: must be at least 16 pixels")
    if cfg.eval_every < 0:
        raise SplatError(f"--eval-every {cfg.eval_every}: must be 0 or more")
    if not 0.1 <= cfg.coarse_scale <= 1 or not 0 < cfg.coarse_until <= 1:
        raise SplatError(f"coarse_scale {cfg.coarse_scale} / coarse_until {cfg.coarse_until}: must be in [0.1, 1] / (0, 1]")
    if not (0 <= cfg.adam_beta1 < 1 and 0 <= cfg.adam_beta2 < 1):
        raise SplatError(f"adam_beta1 {cfg.adam_beta1} / adam_beta2 {cfg.adam_beta2}: must be in [0, 1)")
    if not 0 < cfg.compact.keep <= 1:
        raise SplatError(f"compact_keep {cfg.compact.keep}: must be in (0, 1]")
    if cfg.appearance not in APPEARANCE:
        raise SplatError(f"--appearance {cfg.appearance!r} is not known; choose one of {', '.join(APPEARANCE)}")
    e = cfg.exposure
    if not (e.lr > 0 and e.lr_final > 0 and e.reg >= 0):
        raise SplatError(f"exposure_lr {e.lr} / exposure_lr_final {e.lr_final} / exposure_reg {e.reg}: "
                         "the learning rates must be positive, the weight 0 or more")
    if not 0 <= e.smooth <= 1:
        raise SplatError(f"exposure_smooth {e.smooth}: must be in [0, 1] (a fraction of the training photos)")


# ---- the contract other commands read -------------------------------------------


@dataclass
class TrainSummary:
    """`steps.train.summary` in the manifest; reports/train.json holds it plus the
    histograms and the config. Eval and the benchmarks read these keys."""

    steps: int  # optimiser steps done (including the compaction fine-tune)
    train_seconds: float  # training only, evaluation excluded
    num_gaussians: int
    sh_degree: int  # the degree stored and exported
    ply_bytes: int  # size of the .ply `export` writes for this model
    device: str
    final_loss: float
    psnr: float | None = None  # last held-out PSNR (None without held-out views)
    ssim: float | None = None
    bad_steps: int = 0
    checkpoint: str = ""  # path of the final checkpoint
    sh_auto_psnr: dict[str, float] | None = None  # --sh-degree auto: validation PSNR per degree
    compact: CompactReport | None = None
    resumed_from: int | None = None  # step of the checkpoint a --resume started from
    plan: dict[str, Any] | None = None  # --time-budget: the budget, the template schedule and every plan made
    nproc: int = 1  # data-parallel training processes (steps count views seen, whatever this is)
    comm_seconds: float | None = None  # time rank 0 spent in collectives (exchanging and waiting)
    rank_checks: int | None = None  # checkpoints at which every rank's parameters equalled rank 0's
    mask_mode: str = "off"  # what was done with the masks (Project.mask_mode); eval scores the same way

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class TrainReport:
    """reports/train.json: the summary, histograms and the config."""

    summary: TrainSummary
    scale_hist: Histogram  # log10 of each Gaussian's largest scale (world units)
    opacity_hist: Histogram  # sigmoid(opacity_logit)
    config: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

