"""The training run around the step: setup, signals, out-of-memory failures, checkpoints,
the time plan, ranks, events, the log and held-out measurement.

`train()` sets up (fresh or `--resume`), runs a `_Run` and hands the result to
`log.finish`. One step (render, loss, backward, optimiser, the strategies' hooks) is
trainer.py's `Trainer`; setup lives in state.py (parameters, optimisers, strategies,
checkpoints), data.py (cached images) and init.py (first Gaussians); density and
model control in strategy/.
"""

from __future__ import annotations

import contextlib
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
import torch
from torch import Tensor

from ..errors import Interrupted, SplatError, TrainingDiverged
from ..eval.score import REPORTED, score_image
from ..events import EventSink, Note, Progress, Snapshot, Stage, StageDone, emit
from ..files.checkpoint import Checkpoint, load_checkpoint
from ..project import Project, writer_lock
from ..render import kernels
from ..render.backends import rasterizer
from ..render.blocks import BlockTuner
from ..render.weights import blending_weights
from ..sfm.colmap import read_project_scene
from ..strategy import Context, StepInfo, TrainViews
from . import log
from .compiling import compile_mode
from .config import TrainConfig, TrainSummary
from .data import TrainData, TrainView, load_train_data, subset, views_seeing
from .distributed import Comm
from .init import initial_gaussians
from .memory import check_memory, is_out_of_memory, plan_memory
from .plan import ceiling
from .profile import StepProfile
from .state import RenderSettings, TrainState, new_state, save_state, state_from_checkpoint, time_plan
from .trainer import Trainer, render_view

STAGE = "train"


def train(
    project_dir: str | Path,
    cfg: TrainConfig,
    device: torch.device,
    *,
    resume: bool = False,
    on_event: EventSink | None = None,
    comm: Comm | None = None,
    chosen: list[dict[str, Any]] | None = None,
) -> TrainSummary:
    """Train (or resume) the project's model; return the summary also recorded in
    the manifest. `cfg` is the run's one config: with `resume`, the stored config with the
    options given on top (cli/train_config.py's `resumed`), used as it is.
    `comm`: this process's rank in a data-parallel run (distributed.py); rank 0
    alone writes the project. `chosen`: what cli/planning.py chose and why, for the record.
    SIGINT/SIGTERM: checkpoint, raise Interrupted."""
    project = Project.open(project_dir)
    comm = comm or Comm()
    with writer_lock(project.root, "train") if comm.main else contextlib.nullcontext():
        return _train(project, cfg, device, resume, on_event, comm, chosen)


def _train(project: Project, cfg: TrainConfig, device: torch.device, resume: bool, on_event: EventSink | None,
           comm: Comm, chosen: list[dict[str, Any]] | None) -> TrainSummary:
    project.require_processed()
    if comm.main and not resume:
        warning = pose_warning(project)
        if warning:
            emit(on_event, Note(warning, "warning"))
    ck = _latest(project, device, on_event) if resume else None
    if device.type == "cpu":  # a run that cannot fit stops here, before loading anything
        _check_fits(project, cfg, ck, comm)
    data = load_train_data(project, cfg.downscale, cfg.max_size, device, cfg.eval_max_views, cfg.mask_mode)
    if cfg.mask_mode in ("ignore", "background") and data.mask_mode == "off":
        emit(on_event, Note(f"--mask-mode {cfg.mask_mode}: the project has no masks; training on whole images",
                            "warning"))
    with _stop_on_signal() as stop:  # from here on a signal means: checkpoint, exit 130
        run = _Run(project, cfg, data, comm, stop, on_event)
        run.start(ck, device)
        run.loop()
    return log.finish(project, run.base, run.trainer.state, ck.step if ck is not None else None, comm, chosen)


def pose_warning(project: Project) -> str | None:
    """What `process` found wrong with the poses, said again before training on them: images it
    left out as placed apart from the rest, or poses that failed its consistency check."""
    summary = (project.step("process") or {}).get("summary") or {}
    apart, check = summary.get("placed_apart") or [], summary.get("consistency") or {}
    if apart:
        shown = ", ".join(apart[:8]) + (f" and {len(apart) - 8} more" if len(apart) > 8 else "")
        return (f"process left out {len(apart)} image(s) that no model placed where their image pairs say "
                f"({shown}); training on the {summary.get('registered')} it kept (reports/process.json lists them)")
    if check and not check.get("consistent", True):
        return f"the poses failed process's consistency check: {check.get('line')}"
    return None


def _latest(project: Project, device: torch.device, on_event: EventSink | None) -> Checkpoint | None:
    """--resume: the latest checkpoint; without one yet, None (a new run)."""
    path = project.latest_checkpoint()
    if path is None:
        emit(on_event, Note("--resume: no checkpoint yet; starting a new run", "warning"))
        return None
    return load_checkpoint(path, device)


def _check_fits(project: Project, cfg: TrainConfig, ck: Checkpoint | None, comm: Comm) -> None:
    """Stop a CPU run whose model cannot fit in memory (memory.py), before loading the images."""
    cams = [c.at_resolution(cfg.downscale, cfg.max_size) for c in read_project_scene(project).cameras]
    facts = project.manifest().get("scene") or {}
    init = len(ck.gaussians) if ck is not None else int(facts.get("num_points") or cfg.init_random_points)
    cap = cfg.refine.max_gaussians
    if cap is not None:
        cap = max(cap, ceiling(cfg) or 0)  # (the plan may raise it)
    check_memory(plan_memory(cams, init, cap, copies=comm.local_world), cfg.max_size)


def _compile(cfg: TrainConfig, device: torch.device, on_event: EventSink | None) -> dict[str, Any]:
    """--compile resolved and set for this process (render/kernels.py); the record train.json keeps."""
    mode, why = compile_mode(cfg, device)
    status = kernels.set_mode(mode)
    if status.failed:
        emit(on_event, Note(status.failed, "warning"))
    elif mode == "on":
        if kernels.warm_cache():
            what = f"loading the rasterizer's compiled planner for this CPU from {kernels.cache_dir()}"
        else:
            what = ("compiling the rasterizer's planner for this CPU (the first run on this machine compiles, about "
                    f"20 s, counted in the time); kernels kept in {kernels.cache_dir()}")
        emit(on_event, Note(f"{what}; --compile off to skip"))
    return {"mode": mode, "why": why}


def _compiled_record(state: TrainState, on_event: EventSink | None) -> None:
    """The compile's figures into the run's record; a fallback to eager said once."""
    rec, st = state.render.compiled, kernels.status()
    if rec is None or rec["mode"] != "on":
        return
    if st.failed and not rec.get("failed"):
        emit(on_event, Note(st.failed, "warning"))
    rec.update(failed=st.failed, seconds=round(st.compile_s, 2), graphs=st.graphs, kept=dict(st.chosen))


class _Run:
    """One process's run around its `Trainer`: setup, the steps in order, and what follows
    each (log, held-out measurement, refinement, the time plan, events, signals,
    out-of-memory failures, checkpoints). `base`: the run's config as given, for one
    process (what checkpoints record); the trainer's is `base.for_world(K)` for K ranks."""

    trainer: Trainer  # (start)
    writer: log.LogWriter  # (loop)
    eta: log.Eta | None  # (loop; from its first step's report)

    def __init__(self, project: Project, base: TrainConfig, data: TrainData, comm: Comm, stop: threading.Event,
                 on_event: EventSink | None) -> None:
        self.project, self.base, self.data, self.comm, self.stop = project, base, data, comm, stop
        self.on_event = on_event
        self.prof = StepProfile(base.profile)
        self.ctx = self._context()  # (its measurements read the trainer's state once there is one)
        self.stalled = 0.0  # seconds of training spent compiling kernels (spent from a --time-budget, not a step's speed)

    def start(self, ck: Checkpoint | None, device: torch.device) -> None:
        """The trainer of a new run, or of `ck`'s; a finished planned run given more time
        reopened; every rank starting from rank 0's parameters."""
        plan = time_plan(self.base, ck.extra.get("plan") if ck is not None else None, len(self.data.train),
                         self.comm.world)
        if plan is not None:
            self.base = plan.tuned(self.base)  # (its learning rates from the first step)
        data, comm, run = self.data, self.comm, self.base.for_world(self.comm.world)  # the schedule K ranks follow
        render = RenderSettings(rasterizer(self.base.renderer), BlockTuner() if self.base.block == "auto" else (
            "auto" if self.base.block == "model" else int(self.base.block)),
            _compile(self.base, device, self.on_event if comm.main else None))
        if ck is None:
            state = new_state(initial_gaussians(self.base, data, device), run, data.extent, device, len(data.train),
                              self.ctx, comm.world, plan, render)
        else:
            state = state_from_checkpoint(ck, run, data.extent, device, len(data.train), self.ctx, comm.world, plan,
                                          render)
        self.trainer = Trainer(state, run, data, self.ctx, comm, self.prof)
        if ck is not None:
            self._extend()
            if comm.main:
                log.trim_log(self.project.train_log_path, ck.step)
        elif comm.main:
            log.start_fresh(self.project, self.on_event)
        comm.broadcast_params(state.trainable())  # identical from the first step, whatever each rank computed

    def _extend(self) -> None:
        """A finished planned run resumed with more time (--resume --time-budget) plans on."""
        state, c = self.trainer.state, self.trainer.state.counts
        more = state.plan.extend(self.base, c.images, c.elapsed_s) if state.plan is not None else None
        if more is not None:
            self.base = more
            self.trainer.reschedule(more.for_world(self.comm.world))
            emit(self.on_event, Note(f"extending the run to {state.plan.budget_s:.0f} s of training: "
                                     f"{more.iterations} steps planned (from step {state.counts.images})"))

    def loop(self) -> None:
        """Run the trainer's schedule to its end (a --time-budget plan changes it on the way)."""
        t, comm = self.trainer, self.comm
        emit(self.on_event, Stage(STAGE, t.cfg.total_steps * comm.world))
        self.writer = log.LogWriter(self.project.train_log_path, t.state, enabled=comm.main)
        self.eta = None
        for stats in t.catch_up():  # a resumed run: what is due now
            self.writer.refined(stats)
        if _agreed_stop(comm, self.stop):  # signalled during setup: keep what there is (a resume starts here)
            self._interrupt()
        plan = t.state.plan
        self.stalled = plan.history[-1].get("stalled_s", 0.0) if plan is not None and plan.history else 0.0
        while t.state.counts.step < t.cfg.total_steps:
            self._step(t.state.counts.step + 1)
        emit(self.on_event, StageDone(STAGE, t.state.counts.elapsed_s))
        if comm.main:
            self.prof.write(self.project, {"nproc": comm.world, "compile": (t.state.render.compiled or {}).get("mode", "off")})

    def _step(self, step: int) -> None:
        """Step `step` and what follows it."""
        t, state = self.trainer, self.trainer.state
        t0, c0 = time.perf_counter(), kernels.status().compile_s
        batch = t.next_batch(step)
        with self._out_of_memory(step, save=True):  # until the update, the state is the last whole step's
            stats = t.step(step, batch, self.stop.is_set())
        state.counts.elapsed_s += time.perf_counter() - t0
        self.stalled += kernels.status().compile_s - c0  # (not evaluation's compiles: evaluation is not training time)
        self.writer.add(stats.loss if stats.finite else None)
        _compiled_record(state, self.on_event if self.comm.main else None)
        if state.counts.bad_run >= t.cfg.max_bad_steps:
            self._diverged()
        fitted = self._measure_update(step, stats.info)
        self._refine(step, stats.info)
        self._replan()
        if step == t.cfg.total_steps:  # (a planned run knows its last step only once it has planned again)
            t.finish()
        self._report(step, stats.info.heldout, fitted)
        if stats.stopping or (self.comm.world == 1 and self.stop.is_set()):
            self._interrupt()
        if step % t.cfg.checkpoint_every == 0 or step == t.cfg.total_steps:
            self._save()

    def _measure_update(self, step: int, info: StepInfo) -> tuple[float, float] | None:
        """Measure what this step's update produced (into `info.heldout`; the training views'
        figures returned), before its refinement or opacity reset (right after a reset every
        view is nearly transparent); the end of the main schedule is measured before a
        fine-tune starts, the final model after its last refinement. Evaluation is not
        training time."""
        cfg, state, total = self.trainer.cfg, self.trainer.state, self.trainer.cfg.total_steps
        info.heldout = _measure(cfg, self.data, state, step, total, self.comm, force=step == cfg.iterations < total)
        return _measure_fit(cfg, self.data, state, step, self.comm) if info.heldout is not None else None

    def _refine(self, step: int, info: StepInfo) -> None:
        t1 = time.perf_counter()
        with self._out_of_memory(step, save=False):  # may be half edited: keep the last checkpoint
            for stats in self.trainer.refine(step, info):
                self.writer.refined(stats)
        self.trainer.state.counts.elapsed_s += time.perf_counter() - t1
        self.prof.step_done()

    def _replan(self) -> None:
        """--time-budget: plan again when due; the trainer follows the new schedule."""
        state, k = self.trainer.state, self.comm.world
        if state.plan is None:
            return
        if k > 1:  # every rank plans from the same clock
            state.counts.elapsed_s, self.stalled = self.comm.mean(
                torch.tensor([state.counts.elapsed_s, self.stalled, 1.0], dtype=torch.float64)).tolist()
        c = state.counts
        due = state.plan.due(c.elapsed_s, self.stalled) or state.plan.finetune_due(self.base, c.images, c.elapsed_s)
        planned = state.plan.replan(self.base, c.images, c.elapsed_s, self.stalled) if due else None
        if planned is not None:
            self.base = planned
            self.trainer.reschedule(planned.for_world(k))

    def _report(self, step: int, heldout: tuple[float, float] | None, fitted: tuple[float, float] | None) -> None:
        """The log line (the final model measured at the last step), progress, the ETA, the live model."""
        t, comm = self.trainer, self.comm
        state, total = t.state, t.cfg.total_steps
        evaluated = heldout
        if step == total:
            evaluated = _measure(t.cfg, self.data, state, step, total, comm, force=True)
            fitted = _measure_fit(t.cfg, self.data, state, step, comm) if evaluated is not None else None
        self.writer.line(step, state, evaluated, fitted, t.cfg.log_every, force=step == total)
        c = state.counts
        if self.eta is None:  # measured from the end of the first step: its one-off costs (kernels loaded from the cache,
            self.eta = log.Eta(c, t.cfg)  # first allocations: 11 s of the full preset's first 20 on lego) said 17 h, not 12
        eta = (state.plan.seconds_left(c.images, total * comm.world, c.elapsed_s) if state.plan is not None
               else self.eta.left(c, t.cfg))
        # A planned run's step total moves each time it plans again; its clock does not.
        share = (c.elapsed_s / state.plan.budget_s if state.plan is not None and c.elapsed_s < state.plan.budget_s
                 and c.images < total * comm.world else None)
        emit(self.on_event, Progress(STAGE, c.images, total * comm.world, self.writer.info(state), eta, eta_own=True,
                                     share=share))
        if comm.main and state.plan is None:
            self.eta.tell(c, state.num_gaussians, self.on_event)
        if comm.main:
            emit(self.on_event, Snapshot(c.images, state.model))  # for live displays (train --viewer)

    def _save(self) -> Path:
        """A checkpoint of the run as one process would have written it: every rank folds its
        accumulators into rank 0's and confirms its parameters equal rank 0's; rank 0 writes."""
        state, comm = self.trainer.state, self.comm
        comm.fold_rows(state.splats.states)
        comm.check_agree(state.trainable())
        path = self.project.checkpoint_path(state.counts.images)
        if comm.main:
            save_state(path, state, self.base)
            log.prune_checkpoints(self.project, self.base.keep_checkpoints)
        return path

    def _interrupt(self) -> NoReturn:
        """Checkpoint the last whole step and stop (the CLI exits 130)."""
        path = self._save()
        raise Interrupted(f"interrupted at step {self.trainer.state.counts.images}; saved {path}; "
                          f"continue with `splatcli train {self.project.root} --resume`")

    def _diverged(self) -> NoReturn:
        state = self.trainer.state
        path = self._save()
        raise TrainingDiverged(
            f"training diverged: {state.counts.bad_run} consecutive steps with a non-finite loss or gradient "
            f"(step {state.counts.images}); the last good parameters are in {path}; "
            "try a lower learning rate or --resume"
        )

    @contextlib.contextmanager
    def _out_of_memory(self, step: int, save: bool) -> Iterator[None]:
        """An allocation failure inside becomes a one-line SplatError (exit 2) naming the last
        good checkpoint, written now from the state when `save` and no update had begun (the
        state is a whole step; one process only: the other ranks are not at a point where
        they could agree)."""
        try:
            yield
        except Exception as exc:
            if not is_out_of_memory(exc):
                raise
            whole = save and not self.trainer.updating and self.comm.world == 1
            raise _out_of_memory_error(self.project, self.base, self.trainer.state, step, exc, whole) from None

    def _context(self) -> Context:
        """What the strategies are given: this run's evaluator and training views (the ranks share
        the views and combine the answers, so every rank gets the same ones)."""
        data = self.data
        center = torch.as_tensor(data.center, dtype=torch.float32, device=data.background.device)
        views = TrainViews(cameras=[(v.viewmat, v.K, v.camera.width, v.camera.height) for v in data.train],
                           centres=torch.from_numpy(np.stack([v.camera.center for v in data.train])), center=center,
                           seeing=lambda means: views_seeing(data.train, means))
        return Context(_RunEvaluator(self), views, note=lambda m: emit(self.on_event, Note(m)))


class _RunEvaluator:
    """The run's strategy.Evaluator: held-out and training-view scores, blending weights."""

    def __init__(self, run: _Run) -> None:
        self.run = run

    def score(self, views: str, sh_degree: int) -> tuple[float, float] | None:
        """"test", or "val:K": K evenly spaced training views, each through its own colour transform."""
        data, trainer, comm = self.run.data, self.run.trainer, self.run.comm
        if views == "test":
            return evaluate_views(trainer.state, data.test, data.background, sh_degree, comm,
                                  compensated=trainer.cfg.heldout_protocol == "compensated") if data.test else None
        idx = subset(list(range(len(data.train))), int(views.split(":")[1]))
        return evaluate_views(trainer.state, [data.train[i] for i in idx], data.background, sh_degree, comm, idx)

    def weights(self) -> Tensor:  # [N]
        """Each Gaussian's blending weight summed over the training views."""
        p, comm = self.run.trainer.state.params, self.run.comm
        return comm.total(blending_weights(p["means"], p["quats"], p["log_scales"], p["opacity_logits"],
                                           ((v.viewmat, v.K, v.camera.width, v.camera.height)
                                            for v in comm.share(self.run.data.train))))


def _agreed_stop(comm: Comm, stop: threading.Event) -> bool:
    """Whether any rank was signalled (every rank learns the same answer)."""
    if comm.world == 1:
        return stop.is_set()
    return bool(comm.total(torch.tensor([float(stop.is_set())])) > 0)


def _out_of_memory_error(project: Project, cfg: TrainConfig, state: TrainState, step: int, exc: BaseException,
                         save: bool) -> SplatError:
    for opt in state.optimizers.values():
        opt.zero_grad(set_to_none=True)  # frees the gradients before writing
    path = None
    if save and state.counts.step > 0:
        try:
            path = save_state(project.checkpoint_path(state.counts.images), state, cfg)
        except (OSError, SplatError, RuntimeError, MemoryError):
            path = None
    path = path or project.latest_checkpoint()
    kept = f"the last good checkpoint is {path}" if path else "no checkpoint was written yet"
    return SplatError(f"out of memory at step {step * state.counts.world} with {len(state.splats):,} Gaussians "
                      f"({type(exc).__name__}); {kept}",
                      hint=f"lower --max-size or set --max-gaussians, then `splatcli train {project.root} --resume`")


def _measure(cfg: TrainConfig, data: TrainData, state: TrainState, step: int, total: int, comm: Comm,
             force: bool = False) -> tuple[float, float] | None:
    """Held-out PSNR / SSIM every `eval_every` steps (and when forced)."""
    if not data.test or not (force or (cfg.eval_every and step % cfg.eval_every == 0 and step < total)):
        return None
    return evaluate_views(state, data.test, data.background, state.active_sh_degree(step, cfg.sh_degree_interval),
                          comm, compensated=cfg.heldout_protocol == "compensated")


def _measure_fit(cfg: TrainConfig, data: TrainData, state: TrainState, step: int,
                 comm: Comm) -> tuple[float, float]:
    """PSNR / SSIM on as many evenly spaced training views as there are held-out ones,
    rendered as those are (through their colour transforms, with --appearance): logged
    beside the held-out figures, the gap shows overfitting."""
    idx = subset(list(range(len(data.train))), len(data.test))
    return evaluate_views(state, [data.train[i] for i in idx], data.background,
                          state.active_sh_degree(step, cfg.sh_degree_interval), comm, idx)


@torch.no_grad()
def evaluate_views(
    state: TrainState, views: list[TrainView], bg: Tensor, sh_degree: int,  # bg [3] in [0, 1]
    comm: Comm | None = None, train_index: list[int] | None = None, quantisation: str = REPORTED,
    compensated: bool = False,
) -> tuple[float, float]:
    """Mean PSNR (dB) and SSIM over `views`, scored as eval scores them (eval/score.py:
    renders quantised to 8 bits as saved, over the kept pixels of views with a mask), so
    the final held-out figure is eval's for the same views; each rank of a data-parallel
    run renders its share. `train_index`: the views are these training images, drawn
    through their colour transforms when the run learns them (--appearance); None: the
    scene alone."""
    comm = comm or Comm()
    ps, ss = [], []
    for v, i in comm.share(list(zip(views, train_index or [None] * len(views)))):
        img = render_view(state, v, bg, sh_degree).image
        if i is not None:
            img = state.image_model.shade(img, i)[0]
        sc = score_image(img, v.image, v.keep, quantisation=quantisation,  # the uint8 photograph, as eval reads it
                         compensated=compensated)
        ps.append(sc.compensated.psnr if sc.compensated is not None else sc.psnr)
        ss.append(sc.compensated.ssim if sc.compensated is not None else sc.ssim)
    p, s = comm.mean(torch.tensor([sum(ps), sum(ss), float(len(ps))], dtype=torch.float64)).tolist()
    return p, s


@contextlib.contextmanager
def _stop_on_signal() -> Iterator[threading.Event]:
    """SIGINT/SIGTERM set a flag the loop checks between steps (so the checkpoint
    is of a whole step); a second signal aborts at once."""
    stop = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}

    def handler(signum: int, frame: Any) -> None:
        if stop.is_set():
            raise KeyboardInterrupt
        stop.set()

    for s in previous:
        signal.signal(s, handler)
    try:
        yield stop
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
