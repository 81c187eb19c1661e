"""Training's outputs besides checkpoints: the JSONL log (eval/curve.py holds its
line and its reader), train.json and the manifest summary (config.py)."""

from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path
from typing import Any

import torch

from ..eval.curve import TrainLogLine, read_log
from ..eval.score import REPORTED
from ..events import EventSink, Note, emit
from ..files.atomic import append_line, atomic_write_json, atomic_write_text
from ..formats.ply import ply_bytes
from ..gaussians import histogram
from ..project import Project
from ..render.blocks import BlockTuner
from ..strategy import RefineStats
from .config import TrainConfig, TrainReport, TrainSummary
from .distributed import Comm
from .plan import step_costs
from .state import Counters, TrainState

PROGRESS_PERIOD_S = 0.25  # progress-bar refresh; a loss read is a host sync on CUDA
ETA_AFTER_S = 20.0  # training seconds measured before a run without a time budget says when it ends
REFINED = ("cloned", "split", "pruned")


class LogWriter:
    """Accumulates the loss without a host sync per step, and the refinement counts;
    writes one JSONL line every `log_every` steps, at evaluations and at the end."""

    def __init__(self, path: Path, state: TrainState, enabled: bool = True) -> None:
        self.path = path
        self.enabled = enabled  # only rank 0 of a data-parallel run writes
        self.state = state  # the running sums live in the state, so they survive a resume
        last = read_log(path) if enabled else []
        self.psnr = next((r["psnr"] for r in reversed(last) if "psnr" in r), None)
        self.loss = last[-1].get("loss") if last else None
        self.last_refine = ""  # the latest refinement, for the progress bar
        self._t_info = 0.0
        self._rate = (time.perf_counter(), state.counts.elapsed_s, state.counts.images)
        self._steps_per_s: float | None = None
        self._info: dict[str, Any] = {}

    def add(self, loss: torch.Tensor | None) -> None:
        if loss is not None:
            acc = self.state.counts.loss_acc
            acc[0] += loss.to(acc.dtype)
            acc[1] += 1

    def refined(self, stats: RefineStats | None) -> None:
        """Count what a strategy call changed."""
        if stats is None or not (stats.cloned or stats.split or stats.pruned):
            return
        acc = self.state.counts.refine_acc
        for k in REFINED:
            acc[k] = acc.get(k, 0) + getattr(stats, k)
        self.last_refine = f"+{stats.cloned}/+{stats.split}/-{stats.pruned}"

    def _mean_loss(self) -> float | None:
        s, n = self.state.counts.loss_acc.tolist()
        return s / n if n else self.loss

    def line(self, step: int, state: TrainState, evaluated: tuple[float, float] | None,
             fitted: tuple[float, float] | None, log_every: int, force: bool = False) -> None:
        """`evaluated`: held-out (PSNR, SSIM) measured at this step, if any; `fitted`: the
        same on training views."""
        if not (force or evaluated is not None or (log_every and step % log_every == 0)):
            return
        loss = self._mean_loss()
        rec = TrainLogLine(step=state.counts.images, elapsed_s=round(state.counts.elapsed_s, 4),
                           loss=float("nan") if loss is None else round(loss, 6),
                           num_gaussians=state.num_gaussians, bad_steps=state.counts.bad_steps, rss_mb=rss_mb(),
                           open_fds=open_fds(),
                           **{k: state.counts.refine_acc.get(k, 0) for k in REFINED})
        if evaluated is not None:
            rec.psnr, rec.ssim = round(evaluated[0], 4), round(evaluated[1], 5)
            self.psnr = rec.psnr
        if fitted is not None:
            rec.train_psnr, rec.train_ssim = round(fitted[0], 4), round(fitted[1], 5)
        if self.enabled:
            append_line(self.path, json.dumps(rec.to_json()))
        self.loss = loss
        self.state.counts.loss_acc.zero_()
        self.state.counts.refine_acc.clear()

    def info(self, state: TrainState) -> dict[str, Any]:
        """Live figures for the progress bar, refreshed at most every PROGRESS_PERIOD_S."""
        now = time.perf_counter()
        if now - self._t_info < PROGRESS_PERIOD_S:
            return self._info
        self._t_info = now
        _, e0, s0 = self._rate
        if state.counts.elapsed_s - e0 > 1.0:  # training-time rate over the last second or more
            self._steps_per_s = (state.counts.images - s0) / (state.counts.elapsed_s - e0)
            self._rate = (now, state.counts.elapsed_s, state.counts.images)
        info: dict[str, Any] = {}
        if self._steps_per_s is not None:
            info["steps/s"] = round(self._steps_per_s, 2)
        loss = self._mean_loss()
        if loss is not None:
            info["loss"] = round(loss, 4)
        if self.psnr is not None:
            info["psnr"] = round(self.psnr, 2)
        info["gaussians"] = state.num_gaussians
        if self.last_refine:
            info["refined"] = self.last_refine  # +cloned/+split/-pruned of the latest refinement
        self._info = info
        return info


class Eta:
    """The notes a run without a time budget gives once its speed is measured: when it ends
    at that speed, the steps left priced by their coarse-to-fine resolution as a time
    budget's plans price them (train/plan.py). The first is a lower bound (a growing model
    slows it); a second comes once the model has stopped growing (the strategy's refine_stop)."""

    def __init__(self, counts: Counters, cfg: TrainConfig) -> None:
        self.start = (counts.step, counts.elapsed_s)
        self.cfg = cfg
        self.told = False
        self.grown = cfg.refine.refine_stop  # the step growth ends at
        self.again = counts.step < self.grown < cfg.total_steps  # a second note is due then
        self.since: tuple[int, float] | None = None  # (step, elapsed) once grown
        self.last: tuple[float, float | None] = (-1.0, None)  # (elapsed, seconds left) of the latest estimate

    def left(self, counts: Counters, cfg: TrainConfig | None = None) -> float | None:
        """Training seconds left: the steps left priced by their resolution at the speed measured
        since the model stopped growing (once it has), else since the start; None until
        ETA_AFTER_S seconds are measured. Estimated again at most once a training second. `cfg`:
        the schedule now, where a plan has changed it since."""
        self.cfg = cfg or self.cfg
        if counts.elapsed_s - self.last[0] >= 1.0:
            est = self._left(counts, self.since or self.start)
            self.last = (counts.elapsed_s, None if est is None else est[0])
        return self.last[1]

    def _left(self, counts: Counters, start: tuple[int, float]) -> tuple[float, float] | None:
        """(seconds left, steps/s) measured from `start`, once ETA_AFTER_S seconds have passed."""
        done, elapsed = counts.step - start[0], counts.elapsed_s - start[1]
        if elapsed < ETA_AFTER_S or done <= 0:
            return None
        total = self.cfg.total_steps
        spent = float(step_costs(self.cfg, total, start[0], counts.step).sum())
        left = elapsed * float(step_costs(self.cfg, total, counts.step, total).sum()) / spent
        return left, done * counts.world / elapsed

    def tell(self, counts: Counters, gaussians: int, on_event: EventSink | None) -> None:
        if self.again and counts.step >= self.grown:
            self.since = self.since or (counts.step, counts.elapsed_s)
            est = self._left(counts, self.since)
            if est is not None:
                self.again = False
                emit(on_event, Note(f"the model has stopped growing ({gaussians:,} Gaussians): about "
                                    f"{duration(est[0])} of training left at {est[1]:.2f} steps/s"))
        if self.told or (est := self._left(counts, self.start)) is None:
            return
        self.told = True
        emit(on_event, Note(f"at least {duration(est[0])} of training left at {est[1]:.2f} "
                            "steps/s (more as the model grows; --time-budget SECONDS plans the run to end in time)"))


def duration(seconds: float) -> str:
    """12 s, 4 min, 1 h 05 min."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{int(seconds // 3600)} h {int(seconds % 3600 // 60):02d} min"


def rss_mb() -> int | None:
    """Current resident set size in MiB (Linux /proc; None elsewhere)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") // (1 << 20)
    except (OSError, ValueError, IndexError):
        return None


def open_fds() -> int | None:
    """Open file descriptors of this process (Linux /proc; None elsewhere)."""
    try:
        return len(os.listdir("/proc/self/fd"))
    except OSError:
        return None


def trim_log(path: Path, step: int) -> None:
    """On resume: drop lines written after the checkpoint (that work is redone)."""
    if path.exists():
        keep = [r for r in read_log(path) if r["step"] <= step]
        atomic_write_text(path, "".join(json.dumps(r) + "\n" for r in keep))


def start_fresh(project: Project, on_event: EventSink | None) -> None:
    """A new run replaces the previous run's checkpoints and log."""
    old = project.checkpoints()
    if old:
        emit(on_event, Note(f"starting a new run: removing {len(old)} old checkpoint(s) (use --resume to continue)"))
    for _, p in old:
        p.unlink(missing_ok=True)
    project.train_log_path.unlink(missing_ok=True)


def prune_checkpoints(project: Project, keep: int) -> None:
    for _, p in project.checkpoints()[: -max(keep, 1)]:
        p.unlink(missing_ok=True)


def finish(project: Project, cfg: TrainConfig, state: TrainState, resumed_from: int | None,
           comm: Comm | None = None, chosen: list[dict[str, Any]] | None = None) -> TrainSummary:
    """Write reports/train.json and the manifest's train summary (rank 0 of a
    data-parallel run; the others only return it). Steps count views seen."""
    comm = comm or Comm()
    g = state.model()  # as drawn and exported (--mip-filter folded in)
    deg = state.active_sh_degree(state.counts.images, cfg.sh_degree_interval)
    log = read_log(project.train_log_path)
    last_eval = next((r for r in reversed(log) if "psnr" in r), None)
    psnr = last_eval.get("psnr") if last_eval else None
    owned: dict[str, Any] = {}
    for s, st in zip(state.strategies, state.splats.states):
        owned.update(s.summary(st, len(g), deg, psnr))
    summary = TrainSummary(
        steps=state.counts.images,
        train_seconds=round(state.counts.elapsed_s, 3),
        num_gaussians=len(g),
        sh_degree=deg,
        ply_bytes=ply_bytes(len(g), deg),
        device=cfg.device,
        renderer=cfg.renderer,
        final_loss=float(log[-1]["loss"]) if log else math.nan,
        psnr=psnr,
        ssim=last_eval.get("ssim") if last_eval else None,
        bad_steps=state.counts.bad_steps,
        checkpoint=str(project.latest_checkpoint() or ""),
        resumed_from=resumed_from,
        plan=state.plan.record() if state.plan is not None else None,
        nproc=comm.world,
        comm_seconds=round(comm.seconds, 3) if comm.world > 1 else None,
        rank_checks=comm.checks if comm.world > 1 else None,
        mask_mode=project.mask_mode(cfg.mask_mode),
        chosen=chosen or None,
        quantisation=REPORTED,
        protocol=cfg.heldout_protocol,
        compiled=state.render.compiled,
        blocks=state.render.block.summary() if isinstance(state.render.block, BlockTuner) and state.render.block.calls
        else None,
        **owned,
    )
    if not comm.main:
        return summary
    max_scale = g.log_scales.amax(dim=1).double().cpu().numpy() / math.log(10)
    opac = torch.sigmoid(g.opacity_logits.double()).cpu().numpy()
    report = TrainReport(summary=summary, scale_hist=histogram(max_scale),
                         opacity_hist=histogram(opac, range_=(0.0, 1.0)), config=cfg.to_dict())
    atomic_write_json(project.train_report_path, report.to_json())
    project.record_step("train", config=cfg.to_dict(), summary=summary.to_json())
    return summary
