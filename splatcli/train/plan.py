"""`train --time-budget SECONDS`: a schedule planned to end within a training time on
the machine the run is on.

The preset's schedule is kept in shape and scaled in length: every step count of
it (iterations, refinement start/stop/period, opacity reset, SH growth, the
compaction fine-tune) is multiplied by one factor, so a budgeted run is the preset
compressed in time, learning-rate decay included. The run measures its own speed
over its first steps (`probe_s`), plans the step count that fits the rest of the
budget, and plans again every `replan_every` of the budget: steps slow down as
densification adds Gaussians, and a shared machine changes speed. Once the budget
is spent the main schedule ends at that step. Training seconds are counted, as in
train_log.jsonl (held-out evaluation is not training); the plan and its outcome
are recorded in train.json.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from .. import options
from .config import TrainConfig

# Step counts of the schedule, scaled together (options counted in steps="schedule").
SCHEDULE = options.steps_options(TrainConfig, "schedule")
MIN_ITERATIONS = 30  # a plan never shrinks the run below this
MIN_REFINE_EVERY = 25  # steps between refinements, at least (or the template's, when smaller)


@dataclass
class TimePlan:
    budget_s: float
    template: dict[str, int]  # the preset's schedule, unscaled
    probe_s: float = 0.0  # training seconds measured before the first plan
    replan_every: float = 0.1  # fraction of the budget between plans
    history: list[dict[str, Any]] = field(default_factory=list)  # one entry per plan

    @staticmethod
    def start(cfg: TrainConfig) -> "TimePlan":
        template = {k: int(cfg.value(k)) for k in SCHEDULE if options.resolve(cfg, k) is not None}
        return TimePlan(budget_s=float(cfg.time_budget), template=template,
                        probe_s=min(5.0, 0.05 * float(cfg.time_budget)))

    def scaled(self, cfg: TrainConfig, iterations: int) -> TrainConfig:
        """`cfg` with the template schedule scaled to `iterations` main steps. Refinement
        keeps at least MIN_REFINE_EVERY steps between decisions: gradients averaged over
        fewer views are noise, and growth that fast outruns a short budget (fox at 480 px,
        120 s: refining every 2 steps grew 10k Gaussians to 72k in 167 steps)."""
        f = iterations / self.template["iterations"]
        out = {k: max(1, round(v * f)) if v else 0 for k, v in self.template.items()}  # 0: off stays off
        out["iterations"] = iterations
        out["refine_every"] = max(out["refine_every"], min(MIN_REFINE_EVERY, self.template["refine_every"]))
        return options.apply(cfg, out, strict=False)  # (a stored template may name the other strategy's options)

    def due(self, step: int, elapsed: float) -> bool:
        nxt = self.probe_s if not self.history else self.history[-1]["elapsed_s"] + self.replan_every * self.budget_s
        return elapsed >= nxt or elapsed >= self.budget_s

    def replan(self, cfg: TrainConfig, step: int, elapsed: float) -> TrainConfig | None:
        """The schedule that ends the main steps when the budget is spent, at the speed of
        the steps since the last plan; at once when it is spent already. None once the
        main schedule is over (a fine-tune may follow): nothing is left to plan."""
        if step >= cfg.iterations:
            return None
        last = self.history[-1] if self.history else {"step": 0, "elapsed_s": 0.0}
        rate = (step - last["step"]) / max(elapsed - last["elapsed_s"], 1e-9)  # steps per training second, recently
        # The compaction fine-tune (if any) runs after the main steps at about the same speed.
        share = self.template["iterations"] / (self.template["iterations"] + (
            self.template["compact_finetune"] if cfg.compact.enabled else 0))
        # At least one more step: this step's post-processing hooks have run already.
        iterations = step + max(1, int(rate * (self.budget_s - elapsed) * share))
        iterations = max(iterations, min(MIN_ITERATIONS, self.template["iterations"]))
        self.history.append({"step": step, "elapsed_s": round(elapsed, 3), "steps_per_s": round(rate, 3),
                             "iterations": iterations})
        return self.scaled(cfg, iterations)

    def record(self) -> dict[str, Any]:
        return {"budget_s": self.budget_s, "template": self.template, "probe_s": self.probe_s,
                "history": list(self.history)}

    @staticmethod
    def from_record(d: dict[str, Any]) -> "TimePlan":
        renamed = {"reset_every": "opacity_reset"}  # as stored before the option took its command-line name
        template = {renamed.get(k, k): int(v) for k, v in d["template"].items()}
        return TimePlan(budget_s=float(d["budget_s"]), template=template,
                        probe_s=float(d["probe_s"]), history=list(d["history"]))
