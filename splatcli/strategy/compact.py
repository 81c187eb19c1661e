"""Model only what the scene needs, once the main schedule ends.

`ShAutoStep` (--sh-degree auto): score a validation subset of the *training* views
  with the SH truncated to each degree and keep the lowest degree whose PSNR is
  within `tol_db` of the full degree; the unused bands leave the parameters (so
  they are neither stored nor exported).
`CompactStep` (--compact): rank Gaussians by their total blending weight
  sum_pixels alpha_i T_i over the training views and keep the top `keep` fraction of
  MCMC's cap (--max-gaussians, which it grows to; with the default strategy, whose cap is
  only a ceiling, of the count when the main schedule ends), so that the kept count does
  not depend on how far growth got in the time, in `rounds` cuts spread over the first
  half of a `finetune`-step fine-tune (no densification: the default strategy stops at the
  end of the main schedule).
What a plain weight threshold would drop is not free: on fox at 58,000 Gaussians, the 17% under
one pixel of training-view weight between them all (0.06% of the total) cost 0.12 dB on the
held-out views (docs/benchmarks.md, "Model size"), so the cut keeps a count, not a threshold:
the one asked for, or (a planned run on a capture seen all round, cli/planning.py) the one the
capture's pixels or SfM points call for, after growing several times that to find the detail.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ..formats.ply import ply_bytes
from ..gaussians import kept_count, sh_degree_from_bases, top_by_weight
from ..options import MODEL, opt
from . import ops
from .base import Context, ModelStep, RefineStats, RowState, Splats, StepInfo


def sh_degree_of(splats: Splats) -> int:
    """The highest SH degree the parameters hold."""
    shn = splats.params.get("shN")
    return sh_degree_from_bases(1 + (int(shn.shape[1]) if shn is not None else 0))


@dataclass(frozen=True)
class ShAutoConfig:
    tol_db: float = opt(0.05, "--sh-degree auto keeps the lowest degree within this of the full degree's validation "
                        "PSNR (dB).", at_least=0)
    val_views: int = opt(8, "... measured on this many of the *training* views.", at_least=1)


@dataclass
class ShAutoState(RowState):
    degree: int | None = None  # chosen, once done
    psnr: dict[str, float] = field(default_factory=dict)  # validation PSNR per degree


class ShAutoStep(ModelStep):
    name = "sh_auto"
    state_type = ShAutoState
    config: ShAutoConfig

    def step_post_backward(self, splats: Splats, state: ShAutoState, step: int, info: StepInfo) -> None:
        if step == self.at:
            self.catch_up(splats, state, step)

    def catch_up(self, splats: Splats, state: ShAutoState, step: int) -> None:
        if step < self.at or state.degree is not None:
            return
        cap = sh_degree_of(splats)
        scores = {d: self.ctx.evaluator.score(f"val:{self.config.val_views}", d)[0] for d in range(cap + 1)}
        chosen = min(d for d, p in scores.items() if p >= scores[cap] - self.config.tol_db)
        state.psnr = {str(d): round(p, 4) for d, p in scores.items()}
        state.degree = chosen
        if chosen < cap:
            ops.truncate_bands(splats, "shN", (chosen + 1) ** 2 - 1)
        self.ctx.note(f"--sh-degree auto: degree {chosen} (validation PSNR "
                      + ", ".join(f"{d}: {p:.2f}" for d, p in scores.items()) + " dB)")

    def summary(self, state: ShAutoState, num_gaussians: int, sh_degree: int, psnr: float | None) -> dict:
        return {"sh_auto_psnr": state.psnr or None}


@dataclass(frozen=True)
class CompactConfig:
    enabled: bool = opt(False, "After training, keep compact_keep (a third) of mcmc's --max-gaussians (the default "
                        "strategy: of the Gaussians trained), those with the most blending weight, cut in "
                        "compact_rounds rounds while fine-tuning compact_finetune more steps (chosen with no options "
                        "for a capture seen all round: it grows, then keeps what it needs).",
                        name="compact", group=MODEL)
    keep: float = opt(1 / 3, "With --compact: the share kept of mcmc's --max-gaussians (the default strategy, whose "
                      "cap is only a ceiling: of the Gaussians when training ends), those with the most blending "
                      "weight over the training views.",
                      more_than=0, at_most=1, group=MODEL)
    finetune: int = opt(3000, "Steps after the first cut (lego: 1000 lost 0.42 dB, 3000 0.04).", at_least=0,
                        steps="schedule")
    rounds: int = opt(3, "Cuts, spread over the first half of the fine-tune.", at_least=1)


def cut_steps(config: CompactConfig, at: int) -> list[int]:
    """Steps ending with a cut (CompactStep; train/plan.py prices their scoring): the first at `at`,
    the others spread over the first half of the fine-tune, so the final set still gets at least half
    of it. Cutting in rounds lets the survivors take over the pruned Gaussians' work before the next
    cut (one cut loses more)."""
    spacing = config.finetune // (2 * config.rounds)
    if spacing == 0:  # too short a fine-tune for rounds: one cut
        return [at]
    return [at + r * spacing for r in range(config.rounds)]


@dataclass
class CompactState(RowState):
    round: int = 0  # cuts done
    before_count: int = 0  # the model when the main schedule ended
    before_bytes: int = 0
    before_psnr: float | None = None  # held-out
    kept_weight: list[float] = field(default_factory=list)  # fraction of the blending weight each cut kept


@dataclass
class CompactReport:
    """--compact: the model before the blending-weight prune and after fine-tuning."""

    before_count: int
    before_bytes: int
    before_psnr: float | None  # held-out
    after_count: int
    after_bytes: int
    after_psnr: float | None


class CompactStep(ModelStep):
    name = "compact"
    state_type = CompactState
    config: CompactConfig

    def __init__(self, config: CompactConfig, at: int, ctx: Context, cap: int | None = None) -> None:
        super().__init__(config, at, ctx)
        self.cap = cap  # MCMC's --max-gaussians: `keep` is a share of it (None: of the count at `at`)

    def target(self, n0: int) -> int:
        """The count the last cut keeps of the `n0` Gaussians the main schedule ended with: `keep`
        of the cap (so runs that grew to different counts in their time keep the same model), at
        most all of them; without a cap, `keep` of `n0`."""
        return min(n0, kept_count(self.cap if self.cap is not None else n0, self.config.keep))

    def prune_steps(self) -> list[int]:
        return cut_steps(self.config, self.at)

    def step_post_backward(self, splats: Splats, state: CompactState, step: int, info: StepInfo) -> RefineStats | None:
        sched = self.prune_steps()
        if step in sched and state.round < sched.index(step) + 1:
            return self._cut(splats, state, step, sched.index(step) + 1, info.heldout)
        return None

    def catch_up(self, splats: Splats, state: CompactState, step: int) -> RefineStats | None:
        # A finished run resumed with --compact. A run of K processes can end a step past its
        # schedule (its steps come in K views), and is resumed there by one process.
        if step >= self.at and state.round == 0:
            return self._cut(splats, state, step, 1, None)
        return None

    def _cut(self, splats: Splats, state: CompactState, step: int, r: int,
             heldout: tuple[float, float] | None) -> RefineStats:
        """Round r of R: keep the n0 * (k / n0)^(r/R) Gaussians with the most blending weight,
        k = `target(n0)` (gaussians.kept_count rounds it: the last round keeps k)."""
        n = len(splats)
        if state.round == 0:  # the first cut made (round 1, unless a resume skipped its step)
            if heldout is None:
                heldout = self.ctx.evaluator.score("test", sh_degree_of(splats))
            state.before_count, state.before_bytes = n, ply_bytes(n, sh_degree_of(splats))
            state.before_psnr = heldout[0] if heldout is not None else None
        n0, rounds = state.before_count, len(self.prune_steps())
        k = kept_count(n0, (self.target(n0) / max(n0, 1)) ** (r / rounds))
        stats = RefineStats(step=step, before=n, after=n)
        if k < n:
            weight = self.ctx.evaluator.weights()
            keep = top_by_weight(weight, k)
            state.kept_weight.append(float(weight[keep].sum() / weight.sum().clamp_min(1e-12)))
            ops.keep(splats, keep)
            stats.pruned, stats.after = n - k, k
        state.round = r
        self.ctx.note(f"--compact round {r}/{rounds}: kept {len(splats)} of {n0} Gaussians by blending weight")
        return stats

    def summary(self, state: CompactState, num_gaussians: int, sh_degree: int, psnr: float | None) -> dict:
        if state.round == 0:
            return {}
        return {"compact": CompactReport(before_count=state.before_count, before_bytes=state.before_bytes,
                                         before_psnr=state.before_psnr, after_count=num_gaussians,
                                         after_bytes=ply_bytes(num_gaussians, sh_degree), after_psnr=psnr)}
