"""What `splatcli train` is asked to do, and what it reports back.

`TrainConfig` holds every training option once, at its field: default, help, range, and
the `--help` heading when the command line shows it (options.py; cli/options.py builds the
Typer options from it). Defaults are named after the 3DGS paper (Kerbl et al. 2023) where
they come from one. The chosen strategy's hyperparameters, its schedule and its budget are
its own section (`default` or `mcmc`, declared in strategy/). Presets override a few
options; explicit options override the preset. Everything here is typed: a preset is a
function of the config (`replace` on its fields and sections), and the chosen strategy's
section is `refine` / `with_refine`; options by name (`--max-gaussians` for whichever
strategy is chosen) are set at the command line's edge alone (cli/train_config.py, through
options.py). `TrainSummary` is the contract other commands read from the manifest
(`steps.train.summary`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

from .. import options
from ..errors import SplatError
from ..gaussians import Histogram
from ..options import APPEARANCE as APPEARANCE_GROUP, DATA, INIT, MODEL, OUTPUT, RUN, SCHEDULE, opt, section
from ..strategy import (
    CompactConfig,
    CompactReport,
    DefaultStrategyConfig,
    MCMCStrategyConfig,
    RefineConfig,
    ShAutoConfig,
    SupportConfig,
)
from .appearance import APPEARANCE, ExposureConfig
from .transients import TRANSIENTS, TransientsConfig

MAX_SH_DEGREE = 3
PRESET_NAMES = ("default", "fast", "demo")
STRATEGIES = ("default", "mcmc")  # --strategy: each is the section of its name
MASK_MODES = ("auto", "ignore", "background", "off")  # --mask-mode (Project.mask_mode resolves them)
COMPILE_MODES = ("auto", "on", "off")  # --compile (train/compiling.compile_mode resolves auto)
BLOCKS = ("auto", "model", "4", "8", "16")  # --block (render/blocks.py)


def parse_sh_degree(text: str) -> int | str:
    t = text.strip().lower()
    if t == "auto":
        return "auto"
    if t.isdigit() and 0 <= int(t) <= MAX_SH_DEGREE:
        return int(t)
    raise ValueError("expected 0, 1, 2, 3 or auto")


def _lower(text: str) -> str:
    return text.strip().lower()


@dataclass(frozen=True)
class TrainConfig:
    # ---- schedule ------------------------------------------------------------
    preset: str = opt("default", "default = the paper's 30k steps; fast = 7k steps, densify to 4k with no opacity "
                      "reset, the first half at a resolution rising from 1/4 (CPU: less time per step early, at the "
                      "cost of fine detail learnt later); demo = a few minutes (make demo).",
                      group=SCHEDULE, choices=PRESET_NAMES, parse=_lower)
    iterations: int = opt(30_000, "Optimiser steps (the paper's schedule).", group=SCHEDULE, short="-n", at_least=1,
                          steps="schedule")
    time_budget: float | None = opt(None, "Training seconds to fit in: the run measures its speed and plans the "
                                    "preset's schedule, compressed, to end within them (evaluation not counted). "
                                    "Alone, on a CPU, it also chooses the preset, strategy, Gaussian budget, "
                                    "training size and processes (train.json says why).",
                                    group=SCHEDULE, more_than=0, metavar="SECONDS")
    time_budget_gaussians: int | None = opt(None, "With --time-budget and --strategy mcmc: the plan may raise "
                                            "max_gaussians up to this, by as much as the steps it finds the budget "
                                            "affords, once (train/plan.py: RAISE_STEPS, RAISE_AT).",
                                            at_least=1)
    sh_degree: int | str = opt(3, "0-3, or auto: train at 3, keep the lowest degree within sh_auto_tol_db of it on "
                               "training views.", group=SCHEDULE, parse=parse_sh_degree, at_least=0,
                               at_most=MAX_SH_DEGREE, metavar="[0|1|2|3|auto]")
    sh_degree_interval: int = opt(1000, "The active SH degree grows by one every this many steps.", at_least=1,
                                  steps="schedule")

    # ---- data ----------------------------------------------------------------
    downscale: float = opt(1.0, "Train at the stored image size divided by this.", group=DATA, more_than=0, at_most=64)
    max_size: int = opt(1600, "Then cap the longest image side at this (pixels), as 3DGS does for large photos "
                        "(a planned CPU run picks 480, more for budgets over 10 min).",
                        group=DATA, at_least=16)
    coarse_scale: float = opt(1.0, "Coarse to fine: the resolution (a fraction of the above) at step 0; 1 = off ...",
                              at_least=0.1, at_most=1)
    coarse_until: float = opt(0.5, "... rising linearly (in steps of 1/8) to full resolution by this fraction of "
                              "`iterations`.", more_than=0, at_most=1)
    mask_mode: str = opt("auto", "What the project's masks do: ignore = masked pixels take no part in the loss "
                         "(people, moving objects); background = they are trained to the background colour (object "
                         "captures); off = masks unused; auto = background for masks from an alpha channel, ignore "
                         "for mask files.", group=DATA, choices=MASK_MODES, parse=_lower, metavar="MODE")
    lambda_dssim: float = opt(0.2, "loss = (1 - l) L1 + l (1 - SSIM).", at_least=0, at_most=1)
    depth_weight: float = opt(0.0, "Add this x the mean |log depth error| at the SfM points each training photo "
                              "observed: the surfaces stay where structure from motion found them (0: off; "
                              "no effect without SfM tracks).", at_least=0, group=MODEL)

    # ---- model and density control (strategy/) ---------------------------------
    strategy: str = opt("default", "Density control: default = 3DGS's clone/split/prune; mcmc = a fixed budget "
                        "(--max-gaussians), grown by at least mcmc_growth per refinement and to the cap by "
                        "mcmc_grow_until of the refinement window, dead Gaussians moved onto live ones, noise on nearly "
                        "transparent ones, opacity and scale penalties (Kheradmand et al. 2024).",
                        group=MODEL, choices=STRATEGIES, parse=_lower)
    default: DefaultStrategyConfig = section(DefaultStrategyConfig, "3DGS adaptive density control",
                                             when=("strategy", "default"))
    mcmc: MCMCStrategyConfig = section(MCMCStrategyConfig, "MCMC (a fixed budget)", prefix="mcmc_",
                                       when=("strategy", "mcmc"))
    support: SupportConfig = section(SupportConfig, "--prune-views")
    sh_auto: ShAutoConfig = section(ShAutoConfig, "--sh-degree auto", prefix="sh_auto_")
    compact: CompactConfig = section(CompactConfig, "--compact", prefix="compact_")
    average: float = opt(0.02, "The run ends with each Gaussian's parameters averaged over its last steps (an "
                         "exponential moving average whose time constant is this share of the steps), not the last "
                         "step's values: the last views and MCMC's noise pull the model about less (0: off).",
                         group=MODEL, at_least=0, less_than=0.25)
    mip_filter: bool = opt(False, "Mip-Splatting's filters (Yu et al. 2024): no Gaussian finer than the training "
                           "views sample it (a 3D filter, folded into the exported scales and opacities), drawn with "
                           "the 2D antialiasing filter: renders at other resolutions keep their look.", group=MODEL)

    # ---- starting points -------------------------------------------------------
    init_ply: str | None = opt(None, "Start from a splat file (.ply, .spz, .sog, .compressed.ply, .splat) instead of "
                               "the SfM/random points.", group=INIT, metavar="PATH")
    init_far: int = opt(0, "Also start with Gaussians on a sphere init_far_radius x the cameras' extent away, this "
                        "many over the whole sphere (those a training view sees are kept, coloured from it): a backdrop "
                        "that structure from motion left empty gets a far depth instead of floaters (0: off).",
                        group=INIT, at_least=0)
    init_far_radius: float = opt(5.0, "The sphere's radius, x the cameras' extent, about their centre.", more_than=1)
    init_opacity: float = opt(0.1, "Starting opacity, the paper's (--strategy mcmc: mcmc_init_opacity for SfM points).",
                              more_than=0, less_than=1)
    init_random_points: int = opt(100_000, "Scenes with no SfM points: this many uniform in the bounds (3DGS).",
                                  at_least=0)
    init_knn: int = opt(3, "Starting log scale from the RMS distance to this many nearest neighbours.", at_least=1)

    # ---- appearance ----------------------------------------------------------
    appearance: str = opt("none", "none | exposure: exposure learns one colour transform (a 3x3 matrix and an offset) "
                          "per training photo, pulled towards the identity, for captures whose exposure or white "
                          "balance varies; what varies smoothly from camera to camera is left to the scene (held-out "
                          "views between them see it); held-out views, eval and exported files use the scene alone.",
                          group=APPEARANCE_GROUP, choices=APPEARANCE, parse=_lower)
    exposure: ExposureConfig = section(ExposureConfig, "--appearance exposure", prefix="exposure_")
    transients: str = opt("keep", "keep | ignore: ignore leaves out of each photo's loss the regions that disagree "
                          "with the scene (people, cars, banners, clouds that move), from a quarter of the run on: "
                          "a photo collection's passers-by then do not become floaters.", group=APPEARANCE_GROUP,
                          choices=TRANSIENTS, parse=_lower)
    robust: TransientsConfig = section(TransientsConfig, "--transients ignore", prefix="robust_")

    # ---- optimiser (Adam, per attribute) -------------------------------------
    lr_means: float = opt(1.6e-4, "Learning rate of the means, x scene extent, decaying exponentially ...", more_than=0)
    lr_means_final: float = opt(1.6e-6, "... to this x extent by the end of `iterations` ...", more_than=0)
    lr_hold: float = opt(0.0, "... after holding lr_means for this fraction of them (--time-budget: 0.6).", at_least=0,
                         less_than=1)
    lr_scale: float = opt(1.0, "Every learning rate above and below x this (--time-budget: 1.5).", more_than=0)
    lr_means_scale: float = opt(1.0, "The means' learning rate x this as well (--time-budget: 0.5, so 0.75x lr_means).",
                                more_than=0)
    lr_sh0: float = opt(2.5e-3, "Learning rate of the SH DC.", more_than=0)
    lr_shN_div: float = opt(20.0, "Higher SH bands learn this many times slower (--time-budget: 10).", more_than=0)
    lr_opacity: float = opt(0.05, "Learning rate of the opacity logits (the reference code's and the paper's).",
                            more_than=0)
    lr_scales: float = opt(5e-3, "Learning rate of the log scales.", more_than=0)
    lr_quats: float = opt(1e-3, "Learning rate of the quaternions.", more_than=0)
    adam_eps: float = opt(1e-15, "As 3DGS: moments of tiny gradients must still move parameters.", more_than=0)
    adam_beta1: float = opt(0.9, "Adam's beta1.", at_least=0, less_than=1)
    adam_beta2: float = opt(0.999, "Adam's beta2.", at_least=0, less_than=1)

    # ---- checkpoints and logs --------------------------------------------------
    eval_every: int = opt(1000, "Held-out PSNR/SSIM every this many steps (0: only at the end).", group=OUTPUT,
                          at_least=0, steps="cadence")
    eval_max_views: int = opt(0, "0: every held-out view; else an evenly spaced subset.", at_least=0)
    log_every: int = opt(100, "One train_log.jsonl line every this many steps.", at_least=1, steps="cadence")
    checkpoint_every: int = opt(5000, "Write a checkpoint every this many steps (also at the end and on Ctrl-C).",
                                group=OUTPUT, at_least=1, steps="cadence")
    profile: bool = opt(False, "Write where each step's time went (projection, planning, compositing, backward, "
                        "optimiser, densification, data), with the pairs per step, to reports/profile.json and "
                        "profile.md.", group=OUTPUT)
    keep_checkpoints: int = opt(2, "Keep the newest this many checkpoints (each holds parameters and Adam's state).",
                                group=OUTPUT, at_least=1)

    # ---- run -----------------------------------------------------------------
    max_bad_steps: int = opt(20, "Consecutive non-finite steps before the run stops (TrainingDiverged).", at_least=0)
    seed: int = opt(0, "Random seed; the same seed on CPU gives the same result, bit for bit, unless --block is auto (the default).",
                    group=RUN)
    compile: str = opt("auto", "Compile the rasterizer's planner with torch.compile on a CPU (a C++ compiler is "
                       "needed; kernels are kept in ~/.cache/splatcli, so only a machine's first run compiles, "
                       "20-30 s): on, off, or auto = on for runs long enough to repay it: 30 min, 15 when cached "
                       "(docs/guide.md, \"Compiled kernels\"). The result is the same either way.", group=RUN,
                       choices=COMPILE_MODES,
                       parse=_lower)
    block: str = opt("auto", "The PyTorch compositor's pixel block, a speed knob (the picture is the same up to float "
                     "rounding): auto measures which of 4, 8 and 16 px is fastest on this CPU as training goes "
                     "(docs/guide.md, \"Block size\"); model takes a cost model's pick for each view; 4, 8 or 16 fix "
                     "it. model and a fixed size make runs with the same seed, and resumed runs, equal bit for bit.",
                     group=RUN, choices=BLOCKS, parse=_lower)
    device: str = "cpu"  # the resolved device, for the record (the command line's --device is shared by commands)
    renderer: str = "torch"  # the resolved renderer (torch | gsplat), likewise from the shared --renderer

    @property
    def refine(self) -> RefineConfig:
        """The chosen strategy's section: its schedule, budget and penalties."""
        return self.mcmc if self.strategy == "mcmc" else self.default

    @property
    def heldout_protocol(self) -> str:
        """How the held-out views are scored while training: "compensated" where each photo's
        appearance is learnt (no model of the others predicts a held-out photo's light:
        eval/metrics.half_fit), else "raw"; eval's headline follows the same rule."""
        return "raw" if self.appearance == "none" else "compensated"

    @property
    def max_sh_degree(self) -> int:
        """The degree trained (auto trains the full degree and chooses after)."""
        return MAX_SH_DEGREE if self.sh_degree == "auto" else int(self.sh_degree)

    def train_scale(self, step: int) -> float:
        """The resolution (a fraction of the training resolution) step `step` renders at."""
        return float(self.train_scales(np.array([step]))[0])

    def train_scales(self, steps: np.ndarray, iterations: int | None = None) -> np.ndarray:
        """`train_scale` of each of `steps`, in a run of `iterations` steps (default: this
        config's; the time plan prices runs of other lengths): the coarse-to-fine rule, once."""
        end = self.coarse_until * (self.iterations if iterations is None else iterations)
        steps = np.asarray(steps, dtype=np.float64)
        if self.coarse_scale >= 1.0 or end <= 0:
            return np.ones_like(steps)
        s = np.minimum(1.0, np.ceil((self.coarse_scale + (1.0 - self.coarse_scale) * steps / end) * 8) / 8)
        return np.where(steps >= end, 1.0, s)

    @property
    def total_steps(self) -> int:
        """Optimiser steps including the compaction fine-tune."""
        return self.iterations + (self.compact.finetune if self.compact.enabled else 0)

    def with_refine(self, **changes: Any) -> TrainConfig:
        """This config with fields of the chosen strategy's section (`refine`) replaced."""
        if self.strategy == "mcmc":
            return replace(self, mcmc=replace(self.mcmc, **changes))
        return replace(self, default=replace(self.default, **changes))

    def checked(self) -> TrainConfig:
        """This config, once every option is of its type and in its range and --strategy mcmc
        has its budget (else a one-line SplatError)."""
        _check(self)
        return self

    def for_world(self, k: int) -> TrainConfig:
        """The schedule K data-parallel ranks run so as to see the same images as one
        process: each step averages K views' gradients, so every step count is divided
        by K, and Adam follows the square-root scaling rule for a K-times larger batch
        (Malladi et al. 2022, as gsplat and Grendel-GS apply it): learning rates times
        sqrt(K), epsilon divided by sqrt(K), betas raised to the power K (one step then
        forgets as much history as K steps did). K = 1 returns the config unchanged."""
        if k == 1:
            return self

        def per_rank(v: int) -> int:  # (0 stays off)
            return max(1, round(v / k)) if v > 0 else v

        # Every count of steps (the fields whose option has `steps`: tests/test_options.py holds
        # this list to them), the chosen strategy's alone.
        r = math.sqrt(k)
        cfg = replace(self, iterations=per_rank(self.iterations), sh_degree_interval=per_rank(self.sh_degree_interval),
                      compact=replace(self.compact, finetune=per_rank(self.compact.finetune)),
                      eval_every=per_rank(self.eval_every), log_every=per_rank(self.log_every),
                      checkpoint_every=per_rank(self.checkpoint_every),
                      # (not exposure.lr: the transforms' Adam steps a view's row once per time the view is
                      # trained, however many ranks share a step; appearance.py)
                      lr_means=self.lr_means * r, lr_means_final=self.lr_means_final * r, lr_sh0=self.lr_sh0 * r,
                      lr_opacity=self.lr_opacity * r, lr_scales=self.lr_scales * r, lr_quats=self.lr_quats * r,
                      adam_eps=self.adam_eps / r, adam_beta1=self.adam_beta1 ** k, adam_beta2=self.adam_beta2 ** k)
        refine = self.refine
        cfg = cfg.with_refine(refine_start=per_rank(refine.refine_start), refine_stop=round(refine.refine_stop / k),
                              refine_every=per_rank(refine.refine_every))
        if isinstance(refine, DefaultStrategyConfig):
            cfg = cfg.with_refine(opacity_reset=per_rank(refine.opacity_reset))
        return cfg

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict[str, Any], where: str = "stored train config") -> TrainConfig:
        """The stored form back (unknown keys ignored, missing ones the defaults; a config
        stored before the strategies had their own sections is read as it trained). A
        value of the wrong type or out of range (a damaged or hand-edited file) is a
        one-line SplatError naming `where` and the key."""
        cfg = options.load(TrainConfig, _upgrade(d), where)
        try:
            _check(cfg)
        except SplatError as exc:
            raise SplatError(f"{where}: {exc}") from None
        return cfg




def _upgrade(d: dict[str, Any]) -> dict[str, Any]:
    """A config stored before dced6d2's successor (`density` chose the strategy, `strategy`
    held the default strategy's settings and every strategy's schedule and cap, and `reg`
    the extra penalties) in today's form. Old MCMC runs with `reg` trained with both
    penalties, which add up (the extra one also went on past mcmc_reg_until)."""
    if "density" not in d:
        return d
    d = dict(d)
    old = d.pop("strategy", None)
    old = dict(old) if isinstance(old, dict) else {}
    reg = d.pop("reg", None)
    reg = reg if isinstance(reg, dict) else {}
    d["strategy"] = d.pop("density")
    if "reset_every" in old:
        old["opacity_reset"] = old.pop("reset_every")
    shared = {k: old[k] for k in ("refine_start", "refine_stop", "refine_every", "max_gaussians") if k in old}
    d["default"] = {**old, **{k: reg[k] for k in ("opacity_reg", "scale_reg") if k in reg}}
    mcmc = d.get("mcmc")
    mcmc = dict(mcmc) if isinstance(mcmc, dict) else {}
    if "shrink" not in mcmc:
        mcmc["shrink"] = 1.0  # stored before the option: its copies kept their scale
    for k in ("opacity_reg", "scale_reg"):
        extra = reg.get(k)
        if isinstance(extra, (int, float)) and not isinstance(extra, bool) and extra:
            base = mcmc.get(k, 0.01)
            mcmc[k] = base + extra if isinstance(base, (int, float)) and not isinstance(base, bool) else base
    d["mcmc"] = {**mcmc, **shared}
    return d


# Presets override the defaults above; explicit options override the preset. A preset's
# option that does not apply to the chosen strategy is left out (the opacity reset is the
# default strategy's alone).
def _default(cfg: TrainConfig) -> TrainConfig:
    """The paper: 30k steps, densify 500..15k (the defaults)."""
    return cfg


def _fast(cfg: TrainConfig) -> TrainConfig:
    """A CPU preset with the same shape in fewer steps. Most of the PSNR arrives in the first
    7k steps (the paper reports its 7k numbers for that reason); densifying for the first
    ~half keeps the paper's grow-then-settle ratio and gives the last 3k steps to refine a
    fixed set, which is where SSIM improves.

    Coarse to fine: the first half renders at a resolution rising from 1/4 (on lego its
    PSNR-against-time curve stayed above the full-resolution one throughout).
    No opacity reset: with 4k steps of densifying, the reset at 3k leaves too few to win the
    model back (an object capture's held-out PSNR fell at the reset and never recovered; without
    it, it ends at its best)."""
    cfg = replace(cfg, iterations=7000, checkpoint_every=1000, init_random_points=10_000, coarse_scale=0.25,
                  coarse_until=0.5)
    return _no_opacity_reset(cfg.with_refine(refine_stop=4000))


def _demo(cfg: TrainConfig) -> TrainConfig:
    """`make demo` on sample_data (320x240): a few minutes on 2 cores (docs/benchmarks.md, "demo").
    Everything 3DGS does, compressed: densify 300..900, SH every 300 steps, and a budget of
    20k Gaussians (unbudgeted it grows more for a little PSNR at much more time); the block of
    the cost model, so that the demo gives the same figure on every run."""
    cfg = replace(cfg, iterations=1500, sh_degree_interval=300, eval_every=500, checkpoint_every=500, max_size=256,
                  init_random_points=20_000, block="model")
    return _no_opacity_reset(cfg.with_refine(refine_start=300, refine_stop=900, max_gaussians=20_000))


def _no_opacity_reset(cfg: TrainConfig) -> TrainConfig:
    return cfg.with_refine(opacity_reset=0) if isinstance(cfg.refine, DefaultStrategyConfig) else cfg


PRESETS: dict[str, Callable[[TrainConfig], TrainConfig]] = {"default": _default, "fast": _fast, "demo": _demo}
assert tuple(PRESETS) == PRESET_NAMES


def preset_config(preset: str = "default", strategy: str = "default", *, device: str = "cpu",
                  renderer: str = "torch") -> TrainConfig:
    """The preset's config for `strategy`, before any option is given, for `device` and
    `renderer` (resolved). The command line's builder, options by name on top, is
    cli/train_config.py's make_config."""
    return PRESETS[preset](TrainConfig(preset=preset, strategy=strategy, device=device, renderer=renderer))


def _check(cfg: TrainConfig) -> None:
    options.check(cfg)
    if cfg.strategy == "mcmc" and cfg.mcmc.max_gaussians is None:
        raise SplatError("--strategy mcmc needs --max-gaussians N: the fixed number of Gaussians it grows to")


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
    renderer: str = "torch"  # what drew while training: torch (the PyTorch path) or gsplat
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
    chosen: list[dict[str, Any]] | None = None  # what `train` chose for options not given, and why (cli/planning.py)
    quantisation: str = "8-bit"  # how psnr/ssim (the held-out log's last figures) were scored (eval/score.py)
    protocol: str = "raw"  # ... and under which protocol: raw, or compensated (TrainConfig.heldout_protocol)
    compiled: dict[str, Any] | None = None  # --compile: mode, why, seconds in first calls, graphs, why it fell back
    blocks: dict[str, Any] | None = None  # --block auto: renders per block size, and what each measured

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    def model_line(self) -> str:
        """The model in one line: its count, SH degree and .ply size (and what --compact cut)."""
        line = f"{self.num_gaussians:,} Gaussians, SH degree {self.sh_degree}, .ply {self.ply_bytes / 1e6:.2f} MB"
        plan = self.plan or {}
        at = next((h for h in plan.get("history", []) if "raised" in h), None)
        if at is not None:  # the plan's decision on the count (train/plan.py, TimePlan._raise)
            raised = at["raised"]
            line += ("; the plan " + (f"raised max-gaussians from {raised['from']:,} to {raised['to']:,}"
                                      if raised["to"] > raised["from"] else f"kept max-gaussians at {raised['from']:,}")
                     + f" (time for {raised['steps']:,} steps, planned at {at['elapsed_s']:.0f} s of "
                       f"{plan['budget_s']:.0f})")
            if self.num_gaussians < raised["to"] and self.compact is None and self.steps < raised["steps"]:
                # MCMC grows to the cap by a share of the steps planned; a run that trains fewer ends that share sooner
                line += (f", and growth ended at {self.num_gaussians / raised['to']:.0%} of it: the run trained "
                         f"{self.steps:,} steps")
        c = self.compact
        if c is not None:
            psnr = f", {c.before_psnr:.2f} dB held out" if c.before_psnr is not None else ""
            line += f"; --compact kept these of {c.before_count:,} ({c.before_bytes / 1e6:.2f} MB{psnr})"
        why = next((x["why"] for x in self.chosen or () if x["option"] == "max_gaussians"), None)
        if why and at is None and c is None:  # the count train chose, grown to; say why it is that count
            line += f"; the count chosen for the capture: {why}"
        return line


@dataclass
class TrainReport:
    """reports/train.json: the summary, histograms and the config."""

    summary: TrainSummary
    scale_hist: Histogram  # log10 of each Gaussian's largest scale (world units)
    opacity_hist: Histogram  # sigmoid(opacity_logit)
    config: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

