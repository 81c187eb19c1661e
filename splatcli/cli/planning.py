"""What `splatcli train` chooses when it is not told, before anything trains: on a CPU, a run
that ends in minutes, sized to the capture and to the machine.

With no schedule given (no --preset, --iterations or --time-budget) a CPU run gets the
fast preset's shape planned into a time budget that grows with the number of training views
(`default_budget`), at a training size a CPU handles, with MCMC's fixed Gaussian budget (from a
view's pixels or the SfM points, whichever is more; a capture seen all round grows to several
times that, then --compact keeps that many: `_budget`) grown on a curve tied to the time
(train/plan.py), and one process per free core (a resumed run: as many as trained it). A run
given only a --time-budget gets the same but the appearance model, at a training size that grows
with the budget beyond the default one
(`train_size`). Every choice yields to the option given for it; each is recorded with
its reason (train.json's `chosen`). On CUDA nothing is chosen: the paper's schedule.

What was given comes in typed (`Asked`: a field per option a choice yields to, None where not
given, read by field from the options cli/train_config.py parsed: `Asked.of`), and what is chosen goes out
typed (`Chosen`: the preset and strategy a config starts from, and values `Chosen.applied`
sets with `replace`); `build` makes the one config a run trains. The processes of `train --nproc` are sent the config itself
(`Chosen.env`), not the choices as words to parse again. train/ never calls back here.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any, TypeVar

import torch

from .. import options
from ..camera import SceneData
from ..files.checkpoint import read_checkpoint_config, read_checkpoint_world
from ..gaussians import kept_count
from ..project import Project
from ..sfm.colmap import read_project_scene
from ..train.config import TrainConfig, preset_config
from ..train.plan import RAISE_AT, RAISE_STEPS

BUDGET_S = 600.0  # training seconds of a default CPU run: with loading and the last evaluation, ends within 15 min
MAX_SIZE = 480  # px, the longest side a default CPU run trains at
GAUSSIANS_PER_PIXEL = 0.225  # the model kept, per training pixel (fox at 480 px: 29k; lego 52k)
# A capture's own content: the model keeps at least this many Gaussians per SfM point (a scene seen all round,
# background and all, holds far more than one view's pixels suggest: 250 video frames, 98k; cut to 1.5 per point,
# 51k, they ended 0.35 dB lower, docs/benchmarks.md "Model size"). Not 3: fox's 9,998 points then outbid its pixels
# (30k against 29k), and 30k ended within 29k's runs (31.72 against 31.73 and 31.41 dB, a Xeon: fox's spread).
GAUSSIANS_PER_POINT = 2.9
# What one view's pixels miss: photos whose SfM points are each seen by t of n show about k = (n / t) / COVERAGE_SEEN
# views' worth of surface (at least 1). Such a capture grows to k^2 times the per-pixel model (at most
# MAX_GROWTH times) to find its detail, then keeps the Gaussians with the most blending weight (--compact), where
# the run is long enough to fine-tune what it keeps. Fox (50 photos facing one way, t = 5.6: k = 1) trains its 29k
# directly (58k cut to half in the same 10 minutes ended 0.16 dB lower); lego (100 all round, t = 5.2: k = 2.1)
# trained at 52k ends 1.28 dB below a 222k budget, and grown to 207k then cut to a quarter ends 0.36 dB above it
# (docs/benchmarks.md, "Model size").
# A run shorter than the default budget has no time to cut and fine-tune: it trains and keeps 2k times the per-pixel
# model (k at most MAX_GROWTH), the count that reached the highest PSNR in 90 s and 300 s (fox at 300 s: 58k 31.63 dB,
# 30k 31.38; lego at 90 s: 39k 34.15, 36k 34.09). A capture seen all round may have up to 2 min(MAX_GROWTH, k^2)
# times the per-pixel model where the CPU trains the steps for it: the plan raises the count by what the steps it
# measures afford (train/plan.py, RAISE_STEPS), since a budget buys 2.3x the steps on one 2-core CPU that it buys on
# another, and more Gaussians pay only where enough steps train them.
COVERAGE_SEEN, MAX_GROWTH = 9.0, 4.0
COMPACT_FROM = 1.5  # compacted only where the model grown is at least this many times the one kept
# Where structure from motion left tracks in photographs, a planned run holds each photo's surfaces at the depth of
# the points it observed (train/loss.py sparse_depth_loss), at this weight (docs/benchmarks.md, "Time budgets");
# not in a rendered scene (alpha masks), whose exact pixels placed the surfaces better without it (lego).
DEPTH_WEIGHT = 0.2
# Captures of more training views train longer, so that each photo is still seen often enough: the
# default budget up to VIEWS_AT_BUDGET views, then growing with the square root of the count, to at
# most MAX_BUDGET_FACTOR times it (about 18 minutes: with loading and evaluation, within 20).
VIEWS_AT_BUDGET = 100
MAX_BUDGET_FACTOR = 1.75
MIN_GAUSSIANS, MAX_GAUSSIANS = 5_000, 400_000
MAX_PROCESSES = 8  # data-parallel processes at most: each one added gains less (docs/benchmarks.md, "Many processes")
# torch threads per chosen process at most, where cores are left over: on 16 cores 6 processes with 2 threads each took
# more steps to a higher PSNR than with 1, and 1 process with 16 far fewer (docs/benchmarks.md, "Many processes")
MAX_THREADS = 2
CHOSEN_ENV = "SPLATCLI_CHOSEN"  # the launcher's choices, for the record its processes write
CONFIG_ENV = "SPLATCLI_CONFIG"  # the launcher's config (TrainConfig.to_dict as JSON), which its processes train

T = TypeVar("T")


@dataclass(frozen=True)
class Asked:
    """What the command line gave that `choose` decides around (`of` the options parsed):
    each option a choice yields to, None where not given."""

    preset: str | None = None
    iterations: int | None = None
    time_budget: float | None = None
    max_size: int | None = None
    appearance: str | None = None
    strategy: str | None = None
    max_gaussians: int | None = None
    compact: bool | None = None
    compact_keep: float | None = None
    depth_weight: float | None = None
    downscale: float = 1.0  # given or the default: the training size is chosen in its units
    mcmc_fits: bool = True  # every option given applies to --strategy mcmc (none is the default strategy's alone)

    @classmethod
    def of(cls, given: options.Given) -> Asked:
        """The options given that a choice yields to, read by field from the parsed options."""
        mcmc = replace(TrainConfig(), strategy="mcmc")
        named = {f.name: given.values[f.name] for f in fields(cls) if f.name in given}  # (parsed once, by parse)
        return cls(**{**named, "downscale": given.typed.downscale,
                      "mcmc_fits": all(options.resolve(mcmc, k) is not None for k in given.values)})


@dataclass(frozen=True)
class Choice:
    option: str  # the option's name (as the command line's, with underscores), "nproc" or "threads"
    value: Any
    why: str


@dataclass
class Chosen:
    """What `choose` chose for options not given (None: not chosen), typed; the processes to
    run; and each choice with its reason, in the order made (train.json's `chosen`). A config
    starts from the preset and strategy chosen (config.preset_config) and takes the rest
    from `applied`; the options given go on top (`build`)."""

    nproc: int | None = None  # data-parallel processes, given or chosen (None: one, in this process)
    preset: str | None = None
    time_budget: float | None = None
    max_size: int | None = None
    appearance: str | None = None
    strategy: str | None = None
    max_gaussians: int | None = None  # MCMC's budget (chosen with --strategy mcmc alone)
    time_budget_gaussians: int | None = None  # what the plan may raise max_gaussians to (chosen with it)
    compact_keep: float | None = None  # --compact chosen, keeping this share of max_gaussians
    depth_weight: float | None = None  # the SfM points' depth term
    threads: int | None = None  # torch threads of each process
    choices: list[Choice] = field(default_factory=list)

    def applied(self, cfg: TrainConfig) -> TrainConfig:
        """`cfg` (of the preset and strategy chosen) with the other values chosen."""
        if self.time_budget is not None:
            cfg = replace(cfg, time_budget=self.time_budget)
        if self.max_size is not None:
            cfg = replace(cfg, max_size=self.max_size)
        if self.appearance is not None:
            cfg = replace(cfg, appearance=self.appearance)
        if self.max_gaussians is not None:
            cfg = replace(cfg, mcmc=replace(cfg.mcmc, max_gaussians=self.max_gaussians))
        if self.time_budget_gaussians is not None:
            cfg = replace(cfg, time_budget_gaussians=self.time_budget_gaussians)
        if self.compact_keep is not None:
            cfg = replace(cfg, compact=replace(cfg.compact, enabled=True, keep=self.compact_keep))
        if self.depth_weight is not None:
            cfg = replace(cfg, depth_weight=self.depth_weight)
        return cfg

    def record(self) -> list[dict[str, Any]]:
        return [asdict(c) for c in self.choices]

    def env(self, cfg: TrainConfig) -> dict[str, str]:
        """What the processes of `train --nproc` inherit: the config they train (built here,
        from the options given and the choices), the record, and their torch threads where
        they were chosen."""
        env = {CONFIG_ENV: json.dumps(cfg.to_dict()), CHOSEN_ENV: json.dumps(self.record())}
        if self.threads is not None:
            env["OMP_NUM_THREADS"] = str(self.threads)
        return env


def inherited() -> tuple[Chosen, TrainConfig | None]:
    """In a process the launcher started: the launcher's record of what it chose and why
    (its values are in the config), and the config it sent (None where none came: under a
    plain torchrun each process builds its own from its options)."""
    try:
        choices = [Choice(**c) for c in json.loads(os.environ.get(CHOSEN_ENV) or "[]")]
    except (ValueError, TypeError):
        choices = []
    sent = os.environ.get(CONFIG_ENV)
    cfg = TrainConfig.from_dict(json.loads(sent), where=f"${CONFIG_ENV}") if sent else None
    return Chosen(choices=choices), cfg


def _allowed_cpus() -> set[int]:
    """The CPUs this process's affinity mask allows (empty where the platform cannot say)."""
    try:
        return os.sched_getaffinity(0)
    except (AttributeError, OSError):
        return set()


def usable_cores() -> int:
    """The cores this process's affinity mask allows."""
    return len(_allowed_cpus()) or os.cpu_count() or 1


def free_cores(window_s: float = 0.5, settle_s: float = 2.0) -> int:
    """Cores this process may use that are idle now (never fewer than 1): the affinity
    mask's size less its busy CPUs over `window_s` (`_busy_cores`; the load average lags
    by minutes, both after a job ends and after one starts, and is used only where
    /proc/stat is not there). Where a core is busy, a second window `settle_s` later
    decides with the first (the idler of the two): a burst of a few seconds (a test, a
    compile, a job ending) would otherwise cost a 10-minute run a process."""
    cores = usable_cores()
    busy = _busy_cores(window_s)
    if busy is not None and settle_s > 0 and round(busy) >= 1:
        time.sleep(settle_s)
        again = _busy_cores(window_s)
        busy = busy if again is None else min(busy, again)
    if busy is None:
        try:
            busy = os.getloadavg()[0]
        except OSError:
            busy = 0.0
    return max(1, min(cores, cores - int(round(busy))))


PROC_STAT = "/proc/stat"


def _busy_cores(window_s: float) -> float | None:
    """How many CPUs were busy over `window_s` among those this process may use: from each
    allowed CPU's own line of /proc/stat, so a job pinned to other CPUs of a large machine
    (`taskset`, a scheduler's CPU set) takes nothing from this one; where those lines are
    missing, the whole machine's busy share times its CPUs. None where /proc/stat cannot
    be read."""
    def sample() -> dict[str, tuple[int, int]]:
        out = {}
        with open(PROC_STAT) as f:
            for line in f:
                if not line.startswith("cpu"):
                    break
                name, *v = line.split()
                n = [int(x) for x in v[:8]]  # all but guest time (counted in user time too)
                out[name] = (n[3] + (n[4] if len(n) > 4 else 0), sum(n))  # idle + iowait, all
        return out

    try:
        s0 = sample()
        time.sleep(window_s)
        s1 = sample()
    except (OSError, ValueError, IndexError):
        return None

    def busy(name: str) -> float:  # this line's busy share of its time
        di, dt = s1[name][0] - s0[name][0], s1[name][1] - s0[name][1]
        return 1.0 - di / dt if dt > 0 else 0.0

    own = [f"cpu{c}" for c in sorted(_allowed_cpus())]
    if own and all(n in s0 and n in s1 for n in own):
        return sum(busy(n) for n in own)
    if "cpu" in s0 and "cpu" in s1:
        return busy("cpu") * (os.cpu_count() or len(own) or 1)
    return None


def default_budget(train_views: int) -> float:
    """Training seconds of a run with no schedule given, for a capture of `train_views` views."""
    factor = min(MAX_BUDGET_FACTOR, (train_views / VIEWS_AT_BUDGET) ** 0.5)
    return BUDGET_S if factor <= 1.0 else float(round(BUDGET_S * factor, -1))


def train_size(budget_s: float) -> int:
    """The longest side (px) a planned CPU run of `budget_s` trains at: MAX_SIZE up to the
    default budget (where the planned runs were measured: docs/benchmarks.md, "Time budgets"),
    then growing with the square root of the time, so a longer run keeps the default's number
    of steps, spent on views with proportionally more pixels."""
    return int(round(MAX_SIZE * max(1.0, (budget_s / BUDGET_S) ** 0.5), -1))


def build(given: options.Given, chosen: Chosen, device: str, renderer: str) -> TrainConfig:
    """The config a run trains: the preset and strategy given (else chosen, else the defaults'),
    what else was `chosen`, then every option given on top, for `device` and `renderer`; checked."""
    t = given.typed
    cfg = preset_config(t.preset if "preset" in given else chosen.preset or "default",
                        t.strategy if "strategy" in given else chosen.strategy or "default",
                        device=device, renderer=renderer)
    return given.over(chosen.applied(cfg)).checked()


def resumed(project: Project, cfg: TrainConfig, given: options.Given) -> TrainConfig:
    """What `train --resume` goes on with: the run's stored config (its latest checkpoint's) with
    the options given on top, but the preset and the seed (the run's own), on `cfg`'s device and
    renderer (either renderer resumes either's run); `cfg` itself where there is no checkpoint yet."""
    path = project.latest_checkpoint()
    if path is None:
        return cfg
    stored = TrainConfig.from_dict(read_checkpoint_config(path), where=f"{path}: stored train config")
    new = given.over(stored, leave=("preset", "seed")).checked()
    if new.compact.enabled and not stored.compact.enabled:
        # --compact added on resume brings its own settings (this version's), not the ones stored unused with the run
        new = replace(new, compact=replace(cfg.compact, enabled=True))
    return replace(new, device=cfg.device, renderer=cfg.renderer)


def choose(project: Project, given: options.Given, nproc: int | None, device: torch.device,
           resume: bool = False) -> Chosen:
    """What to choose for a run of `project` on `device` beside the options `given` (module
    docstring); `nproc` as given. Each choice yields to its option given."""
    out = Chosen(nproc)
    asked = Asked.of(given)
    if device.type != "cpu":
        return out
    if resume:
        if nproc is None:
            _resumed_processes(out, project)
        return out
    default_run = asked.preset is None and asked.iterations is None and asked.time_budget is None
    if not default_run and asked.time_budget is None:
        return out  # a step schedule: what was asked, in one process unless --nproc

    def pick(given: object, option: str, value: T, why: str) -> T | None:
        """`value`, recorded with `why`, unless its option was `given` (None: its value is the given one)."""
        if given is not None:
            return None
        out.choices.append(Choice(option, value, why))
        return value

    scene = read_project_scene(project)
    cams = scene.cameras
    longest = max(max(c.width, c.height) for c in cams)
    held = set(project.splits([c.name for c in cams])["test"])
    views = sum(c.name not in held for c in cams)
    out.preset = pick(asked.preset, "preset", "fast", "the fast preset's shape (coarse to fine; grow, then refine a "
                      "fixed set), planned into the time")
    planned = default_budget(views)
    out.time_budget = pick(asked.time_budget, "time_budget", planned, f"{planned / 60:.0f} minutes of training on a "
                           "CPU" + ("; more time, more quality" if planned == BUDGET_S else
                                    f" for {views} training views, so that each is seen often enough"))
    budget = float(asked.time_budget if out.time_budget is None else out.time_budget)  # type: ignore[arg-type]
    # (time chosen for the number of views goes to seeing them, not to a larger size)
    size = train_size(budget if out.time_budget is None else BUDGET_S)
    if longest / asked.downscale > size:
        out.max_size = pick(asked.max_size, "max_size", size, f"the photos are {longest} px across; {size} px fits "
                            f"{budget / 60:.0f} min on a CPU")
    photos = project.mask_source() != "alpha"  # alpha: a rendered (synthetic) scene, one exposure
    if default_run and photos and len(cams) >= 8:  # (a --time-budget run keeps the appearance it was measured with)
        out.appearance = pick(asked.appearance, "appearance", "exposure", "photographs: their exposure and white "
                              "balance vary from shot to shot")
    if photos and any(len(seen) for seen in scene.observed.values()):  # (a rendered scene's pixels are exact)
        out.depth_weight = pick(asked.depth_weight, "depth_weight", DEPTH_WEIGHT, "structure from motion's points: "
                                "each photo's hold its surfaces at the depth it saw them")
    _choose_model(out, asked, pick, scene, budget)
    if nproc is None:
        _processes(out, len(cams))
    return out


def _choose_model(out: Chosen, asked: Asked, pick: Callable[..., Any], scene: SceneData, budget: float) -> None:
    """MCMC and its Gaussian budget sized to the capture (`_budget`), and `--compact` where the model
    grown is COMPACT_FROM times the one kept, into `out` (`pick`: choose's, each yielding to its option)."""
    if asked.strategy not in (None, "mcmc") or not asked.mcmc_fits:
        return
    cams = scene.cameras
    trained = [c.at_resolution(asked.downscale, out.max_size or asked.max_size or TrainConfig().max_size) for c in cams]
    train_px = sorted(c.width * c.height for c in trained)[len(cams) // 2]
    out.strategy = pick(asked.strategy, "strategy", "mcmc", "a fixed Gaussian budget, grown on a curve planned "
                        "to the time")
    size = _budget(train_px, scene, short=budget < BUDGET_S)
    out.max_gaussians = pick(asked.max_gaussians, "max_gaussians", size.grown, size.why)
    out.time_budget_gaussians = size.up_to if out.max_gaussians is not None else None
    compact = size.grown >= COMPACT_FROM * size.kept and out.max_gaussians is not None
    if compact and asked.compact is None and asked.compact_keep is None:
        out.compact_keep = pick(None, "compact_keep", round(size.kept / size.grown, 6),
                                f"grown to find the detail, then {size.kept:,} kept, those with the most "
                                "blending weight (--no-compact keeps all)")


@dataclass(frozen=True)
class Budget:
    """MCMC's Gaussian budget for a capture: the count it grows to, the count kept at the end
    (where the run compacts; else it keeps what grew), and why."""

    grown: int
    kept: int
    why: str
    up_to: int | None = None  # a short run's: what its plan may raise `grown` to (None: it keeps `grown`)


def _budget(train_px: int, scene: SceneData, short: bool) -> Budget:
    """The Gaussian budget for a training view of `train_px` pixels in `scene`, in a run of the default
    budget or more, or a `short` one (the constants above)."""
    n, t = len(scene.cameras), scene.views_per_point
    k = max(1.0, n / t / COVERAGE_SEEN) if t > 0 else 1.0
    growth = 2 * min(MAX_GROWTH, k) if short else min(MAX_GROWTH, k * k)
    by_px, by_pts = GAUSSIANS_PER_PIXEL * train_px, GAUSSIANS_PER_POINT * len(scene.points)

    def count(x: float) -> int:
        return int(min(MAX_GAUSSIANS, max(MIN_GAUSSIANS, round(x, -3))))

    grown = count(max(by_px * growth, by_pts))
    kept = grown if short else count(max(by_px, by_pts))
    up_to = count(by_px * 2 * min(MAX_GROWTH, k * k)) if short else 0
    px = f"{GAUSSIANS_PER_PIXEL} per pixel of a {train_px:,}-pixel training view"
    why = px if by_px >= by_pts else f"{GAUSSIANS_PER_POINT} per SfM point ({len(scene.points):,})"
    seen = f"each SfM point is seen by {t:.1f} of {n} views, so the capture shows about {k:.1f} views' worth of surface"
    if growth > 1 and by_px * growth > by_pts:  # (x 1: nothing to say)
        why = (f"{px} x {growth:.1f}: " + ("a run shorter than 10 min keeps twice the pixels' count (it has no time "
                                            "to cut), times the views' worth of surface; " if short else
                                            "to grow into; ") + seen)
    if up_to <= grown:
        return Budget(grown=grown, kept=kept, why=why)
    why += (f"; up to {up_to:,} where this CPU trains the steps for more: x1 for each {RAISE_STEPS:,} steps the "
            f"budget affords, set at {RAISE_AT:.0%} of it (train.json: plan)")
    return Budget(grown=grown, kept=kept, why=why, up_to=up_to)


def _resumed_processes(out: Chosen, project: Project) -> None:
    """A resumed run goes on with as many processes as trained it (--nproc not given): a
    planned run resumed in fewer would train fewer steps in its time."""
    path = project.latest_checkpoint()
    k = read_checkpoint_world(path) if path is not None else None
    if k is not None and k > 1:
        out.nproc = k
        out.choices.append(Choice("nproc", k, "the run's own; --nproc 1 for one"))


def _processes(out: Chosen, views: int) -> None:
    """Training processes and torch threads for the free cores, into `out` (--nproc not given)."""
    cap = min(MAX_PROCESSES, max(1, views // 8))
    free = free_cores() if cap > 1 else 1  # one process whatever is free: not sampled
    k = min(free, cap)
    if k <= 1:
        cores = usable_cores()
        if cap > 1 and cores > 1:  # said, or a run that takes twice as long would go unexplained
            out.choices.append(Choice("nproc", 1, f"{cores - free} of {cores} cores busy: one training process; "
                                      f"--nproc {min(cores, cap)} to use more"))
        return
    out.nproc = k
    out.choices.append(Choice("nproc", k, f"{free} free cores: {k} training processes (--nproc 1 for one)"))
    threads = min(MAX_THREADS, free // k)
    if threads > 1 and torch.get_num_threads() == 1:  # OMP_NUM_THREADS above 1 is the user's: kept
        out.threads = threads
        out.choices.append(Choice("threads", threads, f"{free} free cores for {k} processes: "
                                  f"{threads} torch threads each (OMP_NUM_THREADS to choose)"))


def chosen_line(chosen: Chosen, cfg: TrainConfig, resume: bool) -> str | None:
    """`summary_line` for the run `cfg` (None: nothing was chosen)."""
    if not chosen.choices:
        return None
    return summary_line(chosen, None if resume else cfg.time_budget, resume,
                        cfg.compact.keep if cfg.compact.enabled else None)


def summary_line(chosen: Chosen, budget_s: float | None, resume: bool = False, keep: float | None = None) -> str:
    """The one line a CLI shows before training: what was chosen (and how the Gaussian count
    was, `keep`: the share --compact keeps of it), the time it will take, and what to change for
    more quality or more speed."""
    listed = [c for c in chosen.choices if resume or c.option != "compact_keep"]  # (else said with `keep`)
    def why(c: Choice) -> bool:  # beside the value: the count's reasons, and cores found busy
        return resume or c.option == "max_gaussians" or (c.option == "nproc" and c.value == 1)

    what = ", ".join(f"{c.option.replace('_', '-')} {c.value}" + (f" ({c.why})" if why(c) else "") for c in listed)
    if resume:
        return f"resumes with {what}"
    if budget_s is None:
        return f"chose {what}"
    eta = f"trains for {budget_s / 60:.0f} min" if budget_s >= 180 else f"trains for {budget_s:.0f} s"
    if keep is not None:
        cap = next((c.value for c in chosen.choices if c.option == "max_gaussians"), None)
        count = f" ({kept_count(cap, keep):,})" if isinstance(cap, int) else ""
        what += f"; then --compact keeps {keep:.0%} of them{count}, those with the most blending weight"
    sooner = f", sooner: --time-budget {int(max(30, budget_s / 4))}" if budget_s > 30 else ""
    return (f"{eta} ({what}); more quality: --time-budget {int(budget_s * 3)}{sooner}; every choice yields to its "
            "option (train --help)")
