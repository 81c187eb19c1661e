"""`train --time-budget SECONDS`: a run planned to end within a training time on the
machine it runs on (issue 35).

The run measures its own speed over its first seconds (`probe_s`) and plans how many
views it can train in the rest of the budget; it plans again every `replan_every` of the
budget, since steps slow down as the model grows and a shared machine changes speed.
Once the budget is spent the main schedule ends at that step. A step's cost is taken as
OVERHEAD + scale^2 (its pixels; the Gaussian curve below follows the same area): the
seconds per unit come from the steps since the last plan, and the plan is the longest run
whose remaining steps, at their own resolutions, fit the budget. Extrapolating the
coarse steps' speed instead planned fox for several times the steps its last plans did,
and the refinement window closed before the count reached its cap.
What a plan sets:

* the preset's schedule in proportion (refinement window, SH growth, fine-tune), with
  refinement at least every MIN_REFINE_EVERY steps; with --compact, the main steps, the
  fine-tune they bring and the cuts' scoring (SCORE_COST) fit the budget together, and once
  the main steps end the fine-tune is lengthened to the time its cuts leave, at its own speed
  (the cuts make its steps faster);
* the means' learning rate held at its initial value for the first LR_HOLD of the run
  (`lr_hold`), then decaying: a compressed exponential decay leaves a short run's last
  half at a tenth of the rate, before the model has its shape; the means' rate below the
  preset's and every other rate higher (`tuned`, from the first step);
* the Gaussian count on a curve tied to the resolution schedule (as DashGaussian does):
  the strategy's budget is cap x (scale at the next plan)^2, where scale is the
  coarse-to-fine resolution, so that cheap coarse steps are not slowed by Gaussians
  only the full resolution can use, and the full budget arrives with the full size;
* once, at the first plan from RAISE_AT of the budget, where the config allows it
  (`time_budget_gaussians`), that cap raised by as much as the steps planned then afford: x1 per
  RAISE_STEPS of them, up to the allowed count. More Gaussians pay only where the run still
  trains enough steps to fit them, and a budget buys 2.3x the steps on one 2-core CPU that it
  buys on another (docs/benchmarks.md, "Model size").

Counts are in views seen (one process's steps): with K data-parallel processes each
step trains K views, every rank plans from the same (averaged) clock, and the config
they run is the plan's `for_world(K)`. Training seconds are counted, as in
train_log.jsonl (held-out evaluation is not training); the plan and its outcome are
recorded in train.json.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np

from ..strategy import DefaultStrategyConfig, cut_steps
from .config import TrainConfig

MIN_ITERATIONS = 30  # a plan never shrinks the run below this
MIN_REFINE_EVERY = 25  # steps between refinements, at least (or the template's, when smaller)
LR_HOLD = 0.6  # the fraction of a planned run the means' learning rate stays at its initial value
# A planned run's learning rates: a budget buys a few thousand steps, where the presets' rates are
# the paper's for 30,000, so every rate is LR_SCALE x the preset's and the higher SH bands learn at
# 1/SHN_DIV of the DC's rate, not 1/20 (docs/benchmarks.md, "Time budgets") ...
LR_SCALE = 1.5
SHN_DIV = 10.0
# ... or at 1/SHN_DIV_FLAT where no appearance model learns each photo's light. On a Zen 4 EPYC, taking turns:
# fox's 300 s run 31.74-32.16 dB (median 31.91, seven runs) against 31.62-31.97 (median 31.82, eight), lego's
# 90 s run 34.63-35.05 (median 34.91, eight) against 34.47-34.69 (five); but fox with no options (exposure on)
# lost 0.2-0.3 dB compensated at 1/5, so runs with an appearance model keep 1/SHN_DIV.
SHN_DIV_FLAT = 5.0
# ... but the means learn at MEANS_LR x that, 0.75x the preset's rate. Lego at 200 px in 90 s, taking turns: a
# Xeon (family 6 model 207, 1,100-1,200 steps of 2 processes) reached 33.89 / 34.09 dB at 0.75x, 33.80-33.99 (four
# runs) at 1.0x and 32.75 / 33.12 at 3.0x, against 33.60-33.80 (median 33.74, eight runs) at 1.5x; a Zen 4 EPYC
# (1,500-1,700 steps) 34.70-34.77 dB (five runs; 0.5x: 34.41 / 34.45) against 34.32-34.48 (docs/benchmarks.md,
# "Time budgets").
MEANS_LR = 0.5
# A step's cost that does not grow with its pixels, as a share of a full-size step's: fitted so that
# (a + 1) / (a + 1/16) is fox's speed at 1/4 of the size over its speed at full (480 px, 2 processes).
OVERHEAD = 0.07
# A --compact cut scores every training view with a forward pass (render/weights.py), each about this share
# of a full-size training step's cost on the same model (fox, 58,000 Gaussians at 480 px, one thread on a
# Zen 1 EPYC: 0.25 s a view, a step 0.49-0.59 s). The main steps leave that time for the cuts: unpriced, lego
# grown to 207,000 spent a fifth of a 10-minute budget scoring, and a loaded host ran 43% past it.
SCORE_COST = 0.5
# A Gaussian budget that may rise (`time_budget_gaussians`) is raised at the first plan from this share of the budget,
# by x1 for every RAISE_STEPS steps of one process that plan affords at the budget given. Lego at 200 px, 2 processes, a
# Zen 1 EPYC: given 200 s (about 2,000 steps at 39,000 Gaussians) 72,000 reached 34.29-34.30 dB against 33.99-34.14
# (60,000: 34.24, 100,000: 34.22); in 90 s (about 800 steps) 39,000 reached 32.90-33.06 dB and 70,000-72,000
# 32.59-32.96; a Zen 4 in 90 s (2,072 steps at 40,000) 60,000 34.37 dB against 34.17; a Xeon in 90 s (1,254 steps at
# 39,000) 60,000 33.57 dB against 33.69. Not sooner: the plans of a tenth of the budget foresaw lego's steps at 200 px
# within 7% (1,335-2,307 against 1,376-2,168 trained) but 1.5x too many at 480 px (880 against 586 trained, a Zen 1,
# 300 s), where a fifth's foresaw 630; a raise from such a count would have cost steps the run did not have (400,000 at
# 480 px: 0.6 dB below 222,000 in 300 s there).
RAISE_AT = 0.2
RAISE_STEPS = 1000


def shN_div(cfg: TrainConfig) -> float:
    """A planned run's ratio of the DC's learning rate to the higher SH bands'."""
    return SHN_DIV if cfg.appearance != "none" else SHN_DIV_FLAT


def ceiling(cfg: TrainConfig) -> int | None:
    """The count a time plan of `cfg` may raise its Gaussian budget to, once (None: it may not)."""
    return cfg.time_budget_gaussians if cfg.time_budget is not None and cfg.strategy == "mcmc" else None


def step_costs(cfg: TrainConfig, iterations: int, start: int, stop: int) -> np.ndarray:
    """The relative cost (OVERHEAD + scale^2) of steps [start, stop) of `cfg` run for
    `iterations` steps, at their coarse-to-fine resolutions (`TrainConfig.train_scales`)."""
    return OVERHEAD + cfg.train_scales(np.arange(start, stop), iterations) ** 2


@dataclass(frozen=True)
class Schedule:
    """A run's step counts that a plan scales together (those whose option is counted in
    steps="schedule"; tests/test_options.py holds this list to them): the config's own, its
    strategy's and the compaction fine-tune's. None: not in a stored template (the opacity
    reset of a run of the other strategy), so left as the config has it."""

    iterations: int
    refine_every: int
    sh_degree_interval: int | None = None
    refine_start: int | None = None
    refine_stop: int | None = None
    opacity_reset: int | None = None  # the default strategy's alone
    compact_finetune: int | None = None

    @staticmethod
    def of(cfg: TrainConfig) -> Schedule:
        r = cfg.refine
        return Schedule(iterations=int(cfg.iterations), refine_every=int(r.refine_every),
                        sh_degree_interval=int(cfg.sh_degree_interval), refine_start=int(r.refine_start),
                        refine_stop=int(r.refine_stop),
                        opacity_reset=int(r.opacity_reset) if isinstance(r, DefaultStrategyConfig) else None,
                        compact_finetune=int(cfg.compact.finetune))

    def scaled(self, f: float) -> Schedule:
        """Every count times `f`, at least 1 (0 stays off)."""

        def s(v: int | None) -> Any:
            return None if v is None else max(1, round(v * f)) if v else 0

        return Schedule(**{f.name: s(getattr(self, f.name)) for f in fields(self)})

    def applied(self, cfg: TrainConfig) -> TrainConfig:
        """`cfg` with these counts (those that are not None; the opacity reset only where the
        chosen strategy has one)."""

        def kept(v: int | None, old: int) -> int:
            return old if v is None else v

        r = cfg.refine
        cfg = replace(cfg, iterations=self.iterations, sh_degree_interval=kept(self.sh_degree_interval,
                                                                              cfg.sh_degree_interval),
                      compact=replace(cfg.compact, finetune=kept(self.compact_finetune, cfg.compact.finetune)))
        cfg = cfg.with_refine(refine_start=kept(self.refine_start, r.refine_start),
                              refine_stop=kept(self.refine_stop, r.refine_stop), refine_every=self.refine_every)
        if isinstance(r, DefaultStrategyConfig) and self.opacity_reset is not None:
            cfg = cfg.with_refine(opacity_reset=self.opacity_reset)
        return cfg

    def record(self) -> dict[str, int]:
        """The stored form (train.json's plan.template; checkpoints): by option name, in the
        options' order."""
        named = {"iterations": self.iterations, "sh_degree_interval": self.sh_degree_interval,
                 "refine_start": self.refine_start, "refine_stop": self.refine_stop, "refine_every": self.refine_every,
                 "opacity_reset": self.opacity_reset, "compact_finetune": self.compact_finetune}
        return {k: v for k, v in named.items() if v is not None}

    @staticmethod
    def from_record(d: dict[str, Any]) -> Schedule:
        d = {"opacity_reset" if k == "reset_every" else k: int(v) for k, v in d.items()}  # (its name before the option's)
        return Schedule(**{f.name: d[f.name] for f in fields(Schedule) if f.name in d})


@dataclass
class TimePlan:
    budget_s: float
    template: Schedule  # the preset's schedule, unscaled
    probe_s: float = 0.0  # training seconds measured before the first plan
    replan_every: float = 0.1  # fraction of the budget between plans
    cap: int | None = None  # the strategy's Gaussian budget at the end (None: no curve)
    history: list[dict[str, Any]] = field(default_factory=list)  # one entry per plan
    scored: int = 0  # views a process scores at each --compact cut (the largest share of the training views)
    up_to: int | None = None  # the Gaussian budget `cap` may be raised to, once (None: it is not)

    @staticmethod
    def start(cfg: TrainConfig, scored: int = 0) -> TimePlan:
        return TimePlan(budget_s=float(cfg.time_budget), template=Schedule.of(cfg),
                        probe_s=min(5.0, 0.05 * float(cfg.time_budget)), cap=cfg.refine.max_gaussians, scored=scored,
                        up_to=ceiling(cfg))

    def scoring(self, cfg: TrainConfig, views: int) -> float:
        """What --compact's cuts after view `views` will spend scoring (all of them, before the main
        steps end), in full-size steps on the model at hand: `scored` views at SCORE_COST a view at
        each cut (strategy.cut_steps), the model smaller by keep^(1 / cuts) after each (CompactStep._cut)."""
        if not cfg.compact.enabled:
            return 0.0
        steps = cut_steps(cfg.compact, cfg.iterations)
        done, keep = sum(s <= views for s in steps), cfg.compact.keep
        return self.scored * SCORE_COST * sum(keep ** ((r - done) / len(steps)) for r in range(done, len(steps)))

    @staticmethod
    def tuned(cfg: TrainConfig) -> TrainConfig:
        """`cfg` with a planned run's learning rates (LR_HOLD, LR_SCALE, shN_div, MEANS_LR); the same
        config again leaves it as it is."""
        return replace(cfg, lr_hold=max(cfg.lr_hold, LR_HOLD), lr_scale=max(cfg.lr_scale, LR_SCALE),
                       lr_shN_div=min(cfg.lr_shN_div, shN_div(cfg)), lr_means_scale=min(cfg.lr_means_scale, MEANS_LR))

    def scaled(self, cfg: TrainConfig, iterations: int, at: int = 0) -> TrainConfig:
        """`cfg` with the template schedule scaled to `iterations` main steps, the learning
        rate held, and the Gaussian budget of the curve at step `at`. Refinement keeps at
        least MIN_REFINE_EVERY steps between decisions: gradients averaged over fewer
        views are noise, and growth that fast outruns a short budget (on fox, refining every 2
        steps multiplied the count within a few hundred steps)."""
        out = self.template.scaled(iterations / self.template.iterations)
        out = replace(out, iterations=iterations,
                      refine_every=max(out.refine_every, min(MIN_REFINE_EVERY, self.template.refine_every)))
        cfg = out.applied(self.tuned(cfg))
        if self.cap is not None:
            cfg = cfg.with_refine(max_gaussians=self.curve(cfg, at))
        return cfg

    def curve(self, cfg: TrainConfig, step: int) -> int:
        """The Gaussian budget at `step` of `cfg`: cap x the resolution's area then."""
        return max(1, round(self.cap * cfg.train_scale(step) ** 2))  # type: ignore[operator]

    def extend(self, cfg: TrainConfig, views: int, elapsed: float) -> TrainConfig | None:
        """A finished run resumed with a budget that leaves time (`--resume --time-budget S`): its
        main schedule reopened and planned to the new budget at the speed it last ran (the
        learning-rate decay laid over the new length, as `--resume --iterations N` does for a
        stepped run); a compacted run's fine-tune lengthened instead. None while the run is
        unfinished (the plan goes on by itself) or it ended within the plan's resolution of the
        budget (a `replan_every` share of it: plans land that close, and the same budget given
        again has nothing left to do)."""
        if views < cfg.iterations or elapsed >= self.budget_s * (1.0 - self.replan_every) or not self.history:
            return None
        if cfg.compact.enabled and views > cfg.iterations:
            # Compacted: the kept model fine-tunes on, at its last speed (reopened, the main steps would grow it
            # back, with no cut to follow).
            rate = self.rate() or 1.0
            return self._lengthened(cfg, views, elapsed, rate, 0.0, fine_tune="extended")
        return self.replan(cfg, views, elapsed, self.history[-1].get("stalled_s", 0.0), reopen=True)

    def rate(self) -> float | None:
        """Views a training second, as the last plan that measured them found (None: none has)."""
        return next((h["steps_per_s"] for h in reversed(self.history) if "steps_per_s" in h), None)

    def seconds_left(self, views: int, total: int, elapsed: float) -> float | None:
        """Training seconds until view `total`: the budget left; past the budget (the step that ends
        the run once it is spent, or a finished run resumed with --compact), the views left at the
        last speed measured. None: nothing measured yet."""
        if elapsed < self.budget_s:
            return self.budget_s - elapsed
        rate = self.rate()
        return max(total - views, 0) / rate if rate else None

    def finetune_due(self, cfg: TrainConfig, views: int, elapsed: float) -> bool:
        """Whether to plan the compaction fine-tune now: at its first step (to start measuring its
        speed, faster than the main steps' once cut), and `probe_s` seconds later (to plan from it)."""
        if not cfg.compact.enabled or views < cfg.iterations or not self.history:
            return False
        last = self.history[-1]
        return last["step"] < cfg.iterations or (last.get("fine_tune") == "measuring"
                                                 and elapsed >= last["elapsed_s"] + self.probe_s)

    def due(self, elapsed: float, stalled: float = 0.0) -> bool:
        """Whether to plan now. The first plan waits for `probe_s` seconds of steps, `stalled` seconds
        (compiling kernels) left out: a compile that filled the probe left a second or less of steps
        to measure, and a short lego run planned far too few steps from them."""
        if not self.history:
            return elapsed - stalled >= self.probe_s or elapsed >= self.budget_s
        return elapsed >= self.history[-1]["elapsed_s"] + self.replan_every * self.budget_s or elapsed >= self.budget_s

    def replan(self, cfg: TrainConfig, views: int, elapsed: float, stalled: float = 0.0, *,
               reopen: bool = False) -> TrainConfig | None:
        """The schedule (one process's, in views) that ends the main steps when the budget
        is spent, at the speed of the views since the last plan; at once when it is spent
        already. Once the main schedule is over, the compaction fine-tune (if any) lengthened to
        the time left, else None; unless `reopen` (`extend`). `stalled`: seconds of `elapsed` that
        were not steps' own work (compiling kernels, --compile): spent from the budget, but left
        out of the speed."""
        last = self.history[-1] if self.history else {"step": 0, "elapsed_s": 0.0}
        spent = max(elapsed - last["elapsed_s"] - max(stalled - last.get("stalled_s", 0.0), 0.0), 1e-9)
        rate = (views - last["step"]) / spent  # views per training second, recently
        if views >= cfg.iterations and not reopen:
            return self._finetune(cfg, views, elapsed, rate, stalled)
        # Seconds per unit of cost, from the steps since the last plan as they ran.
        unit = spent / max(float(step_costs(cfg, cfg.iterations, last["step"], views).sum()), 1e-9)
        # Cost units the budget still holds, less what the compaction cuts will spend scoring.
        left = max(max(self.budget_s - elapsed, 0.0) / unit - self.scoring(cfg, views) * (OVERHEAD + 1.0), 0.0)
        # The longest run whose remaining steps fit (the total grows with the run's length), with
        # the compaction fine-tune (if any) that a run of that length ends with, its steps priced as
        # full-size ones; at least one more step: this step's post-processing hooks have run already.
        def cost(n: int) -> float:
            finetune = self.template.scaled(n / self.template.iterations).compact_finetune if cfg.compact.enabled else 0
            return float(step_costs(cfg, n, views, n + (finetune or 0)).sum())

        lo, hi = views + 1, views + 1 + int(left / (OVERHEAD + min(cfg.coarse_scale, 1.0) ** 2))
        while lo < hi:
            mid = (lo + hi + 1) // 2
            if cost(mid) <= left:
                lo = mid
            else:
                hi = mid - 1
        iterations = max(lo, min(MIN_ITERATIONS, self.template.iterations))
        raised = self._raise(cfg, iterations, elapsed)
        # The budget until the next plan: where the run will be then, at the planned speeds.
        until_next = self.replan_every * self.budget_s / unit
        ahead = views + int(np.searchsorted(np.cumsum(step_costs(cfg, iterations, views, iterations)), until_next))
        ahead = min(iterations, ahead)
        planned = self.scaled(cfg, iterations, ahead)
        self._record(views, elapsed, stalled, steps_per_s=round(rate, 3), iterations=iterations,
                     **({"max_gaussians": planned.refine.max_gaussians} if self.cap is not None else {}),
                     **({"raised": raised} if raised is not None else {}))
        return planned

    def _raise(self, cfg: TrainConfig, iterations: int, elapsed: float) -> dict[str, int] | None:
        """At the first plan from RAISE_AT of the budget, once: the Gaussian budget `cap` raised to
        cap x (`iterations` / RAISE_STEPS), in thousands, at most `up_to` and at least as it was; what
        was decided (from, to, the steps it was decided on), or None where nothing is decided now. Not
        with --compact, whose cuts keep a share of the budget."""
        if (self.up_to is None or self.cap is None or self.up_to <= self.cap or cfg.compact.enabled
                or elapsed < RAISE_AT * self.budget_s or any("raised" in h for h in self.history)):
            return None
        was, self.cap = self.cap, min(self.up_to, max(self.cap, int(round(self.cap * iterations / RAISE_STEPS, -3))))
        return {"from": was, "to": self.cap, "steps": iterations}

    def _record(self, views: int, elapsed: float, stalled: float, **what: Any) -> None:
        """One entry of the plan's history (train.json): where the run was, and what was planned."""
        self.history.append({"step": views, "elapsed_s": round(elapsed, 3),
                             **({"stalled_s": round(stalled, 3)} if stalled else {}), **what})

    def _finetune(self, cfg: TrainConfig, views: int, elapsed: float, rate: float, stalled: float) -> TrainConfig | None:
        """The compaction fine-tune lengthened to the budget left at the speed since the last plan
        (all its steps are full-size, and its cuts make them faster than the plan priced them);
        shortened only to end it once the budget is spent past its first half, so no cut of its
        schedule is passed over (lego's lengthened fine-tune, slower than measured, went 16 steps
        past the budget, planning again at each). None: nothing to change."""
        if not cfg.compact.enabled:
            return None
        if self.history and self.history[-1]["step"] < cfg.iterations:  # the speed since mixes in main steps
            self._record(views, elapsed, stalled, fine_tune="measuring")
            return None
        if self.history and self.history[-1].get("fine_tune") == "ended":
            return None
        done = views - cfg.iterations
        if elapsed >= self.budget_s and 2 * done >= cfg.compact.finetune:
            # Spent, and past every cut (they lie in its first half): it ends with the next view (this step's hooks
            # have run, as when the main steps end), not a step at a time.
            fits = done + 1
            self._record(views, elapsed, stalled, fine_tune="ended", iterations=cfg.iterations, compact_finetune=fits)
            return replace(cfg, compact=replace(cfg.compact, finetune=fits))
        return self._lengthened(cfg, views, elapsed, rate, stalled, steps_per_s=round(rate, 3))

    def _lengthened(self, cfg: TrainConfig, views: int, elapsed: float, rate: float, stalled: float,
                    **mark: Any) -> TrainConfig | None:
        """The fine-tune lengthened to the budget left at `rate` views a second, less its cuts still to
        come, recorded (with `mark`); None where that is no longer than it is."""
        left = self.budget_s - elapsed - (self.scoring(cfg, views) / rate if rate > 0 else 0.0)  # (a step: 1 / rate s)
        fits = views + int(rate * max(left, 0.0)) - cfg.iterations
        self._record(views, elapsed, stalled, **mark, iterations=cfg.iterations,
                     compact_finetune=max(fits, cfg.compact.finetune))
        return replace(cfg, compact=replace(cfg.compact, finetune=fits)) if fits > cfg.compact.finetune else None

    def record(self) -> dict[str, Any]:
        return {"budget_s": self.budget_s, "template": self.template.record(), "probe_s": self.probe_s, "cap": self.cap,
                "scored": self.scored, "up_to": self.up_to, "history": list(self.history)}

    @staticmethod
    def from_record(d: dict[str, Any]) -> TimePlan:
        return TimePlan(budget_s=float(d["budget_s"]), template=Schedule.from_record(d["template"]),
                        probe_s=float(d["probe_s"]), cap=d.get("cap"), history=list(d["history"]),
                        scored=int(d.get("scored", 0)), up_to=d.get("up_to"))
