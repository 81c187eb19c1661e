"""The training loop: sample a view, render, loss, step, let the strategies refine.

`train()` sets up (fresh or `--resume`), runs `_loop`, and hands the result to
`log.finish`. Setup lives in state.py (parameters, optimisers, strategies,
checkpoints), data.py (cached images) and init.py (first Gaussians); density and
model control in strategy/.
"""

from __future__ import annotations

import contextlib
import signal
import threading
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..errors import Interrupted, SplatError, TrainingDiverged
from ..eval.score import REPORTED, score_image
from ..events import EventSink, Note, Progress, Snapshot, Stage, StageDone, emit
from ..io.checkpoint import load_checkpoint
from ..project import Project, writer_lock
from ..render import RenderOutput, kernels
from ..render.backends import rasterizer
from ..render.blocks import BlockTuner
from ..render.weights import blending_weights
from ..sfm.colmap import read_project_scene
from ..strategy import Context, StepInfo
from . import auto, log
from .config import TrainConfig, TrainSummary
from .data import TrainData, TrainView, load_train_data, subset, views_seeing
from .distributed import Comm
from .init import initial_gaussians
from .loss import photometric_loss
from .memory import check_memory, is_out_of_memory, plan_memory
from .profile import StepProfile
from .state import TrainState, make_strategies, means_lr, new_state, save_state, state_from_checkpoint, time_plan

STAGE = "train"


def train(
    project_dir: str | Path,
    cfg: TrainConfig,
    device: torch.device,
    *,
    resume: bool = False,
    overrides: dict[str, Any] | None = None,
    on_event: EventSink | None = None,
    comm: Comm | None = None,
    chosen: list[dict[str, Any]] | None = None,
) -> TrainSummary:
    """Train (or resume) the project's model; return the summary also recorded in
    the manifest. `overrides` are the options given explicitly (flat names, as
    `make_config` takes them), applied on top of a resumed run's stored config.
    `comm`: this process's rank in a data-parallel run (distributed.py); rank 0
    alone writes the project. `chosen`: what train/auto.py chose and why, for the record.
    SIGINT/SIGTERM: checkpoint, raise Interrupted."""
    project = Project.open(project_dir)
    comm = comm or Comm()
    with writer_lock(project.root, "train") if comm.main else contextlib.nullcontext():
        return _train(project, cfg, device, resume, overrides, on_event, comm, chosen)


def _train(project: Project, cfg: TrainConfig, device: torch.device, resume: bool,
           overrides: dict[str, Any] | None, on_event: EventSink | None, comm: Comm,
           chosen: list[dict[str, Any]] | None) -> TrainSummary:
    project.require_processed()
    resumed_from = None
    ck = None
    if resume:
        path = project.latest_checkpoint()
        if path is None:
            emit(on_event, Note("--resume: no checkpoint yet; starting a new run", "warning"))
        else:
            ck = load_checkpoint(path, device)
            stored = TrainConfig.from_dict(ck.config, where=f"{path}: stored train config")
            new = stored.with_options(overrides or {})
            if new.compact.enabled and not stored.compact.enabled:
                # --compact added on resume brings its own settings (this version's),
                # not the ones stored unused with the run.
                new = replace(new, compact=replace(cfg.compact, enabled=True))
            cfg = replace(new, device=str(device), renderer=cfg.renderer)  # either renderer resumes either's run
            resumed_from = ck.step
    run = cfg.for_world(comm.world)  # the schedule K ranks follow (config.py)
    # Reading the scene imports pycolmap, whose glog installs its own SIGTERM handler:
    # ours goes in after it.
    if device.type == "cpu":  # a run that cannot fit stops here, before loading anything
        cams = [c.at_resolution(cfg.downscale, cfg.max_size) for c in read_project_scene(project).cameras]
        facts = project.manifest().get("scene") or {}
        init = len(ck.gaussians) if ck is not None else int(facts.get("num_points") or cfg.init_random_points)
        check_memory(plan_memory(cams, init, cfg.refine.max_gaussians, copies=comm.local_world), cfg.max_size)
    data = load_train_data(project, cfg.downscale, cfg.max_size, device, cfg.eval_max_views, cfg.mask_mode)
    if cfg.mask_mode in ("ignore", "background") and data.mask_mode == "off":
        emit(on_event, Note(f"--mask-mode {cfg.mask_mode}: the project has no masks; training on whole images",
                            "warning"))
    box: list[TrainState] = []
    ctx = _context(data, box, on_event, comm)
    with _stop_on_signal() as stop:  # from here on a signal means: checkpoint, exit 130
        if ck is not None:
            state = state_from_checkpoint(ck, run, data.extent, device, len(data.train), ctx, comm.world)
            state.plan = time_plan(cfg, ck.extra.get("plan"))
            more = state.plan.extend(cfg, state.images, state.elapsed_s) if state.plan is not None else None
            if more is not None:  # a finished planned run given more time
                cfg, run = more, more.for_world(comm.world)
                state.strategies = make_strategies(run, data.extent, ctx)
                emit(on_event, Note(f"extending the run to {state.plan.budget_s:.0f} s of training: "
                                    f"{more.iterations} steps planned (from step {state.images})"))
            if comm.main:
                log.trim_log(project.train_log_path, ck.step)
        else:
            state = new_state(initial_gaussians(cfg, data, device), run, data.extent, device, len(data.train), ctx,
                              comm.world)
            state.plan = time_plan(cfg)
            if comm.main:
                log.start_fresh(project, on_event)
        state.draw = rasterizer(cfg.renderer)
        state.block = BlockTuner() if cfg.block == "auto" else ("auto" if cfg.block == "model" else int(cfg.block))
        state.compiled = _compile(cfg, device, on_event if comm.main else None)
        comm.broadcast_params(state.trainable())  # identical from the first step, whatever each rank computed
        box.append(state)
        cfg = _loop(project, cfg, run, data, state, ctx, stop, on_event, comm)
    return log.finish(project, cfg, state, resumed_from, comm, chosen)


def _compile(cfg: TrainConfig, device: torch.device, on_event: EventSink | None) -> dict[str, Any]:
    """--compile resolved and set for this process (render/kernels.py); the record train.json keeps."""
    mode, why = auto.compile_mode(cfg, device)
    status = kernels.set_mode(mode)
    if status.failed:
        emit(on_event, Note(status.failed, "warning"))
    elif mode == "on":
        first = "" if kernels.warm_cache() else " (the first run on this machine compiles, about 20 s, counted in the time)"
        emit(on_event, Note(f"compiling the rasterizer's planner for this CPU{first}; kernels kept in "
                            f"{kernels.cache_dir()}; --compile off to skip"))
    return {"mode": mode, "why": why}


def _compiled_record(state: TrainState, on_event: EventSink | None) -> None:
    """The compile's figures into the run's record; a fallback to eager said once."""
    rec, st = state.compiled, kernels.status()
    if rec is None or rec["mode"] != "on":
        return
    if st.failed and not rec.get("failed"):
        emit(on_event, Note(st.failed, "warning"))
    rec.update(failed=st.failed, seconds=round(st.compile_s, 2), graphs=st.graphs, kept=dict(st.chosen))


def render_view(state: TrainState, view: TrainView, bg: Tensor, sh_degree: int) -> RenderOutput:  # bg [3]
    """The current Gaussians seen from `view` at the training resolution."""
    g = state.drawn()
    return state.draw(g.means, g.quats, g.log_scales, g.opacity_logits, g.sh, view.viewmat, view.K,
                      view.camera.width, view.camera.height, bg, sh_degree=sh_degree, antialiased=state.antialiased,
                      block=state.block, check=False)  # the loop checks every gradient for non-finite values


def _loop(project: Project, base: TrainConfig, cfg: TrainConfig, data: TrainData, state: TrainState, ctx: Context,
          stop: threading.Event, on_event: EventSink | None, comm: Comm) -> TrainConfig:
    """Run the steps of `cfg` (`base` as given, scaled for the ranks: TrainConfig.for_world);
    returns the config in force at the end (a --time-budget plan changes it)."""
    total = cfg.total_steps
    k = comm.world
    emit(on_event, Stage(STAGE, total * k))
    writer = log.LogWriter(project.train_log_path, state, enabled=comm.main)
    eta = log.Eta(state, cfg)
    prof = StepProfile(cfg.profile)
    for strategy, st in zip(state.strategies, state.splats.states):  # a resumed run: what is due now
        writer.refined(strategy.catch_up(state.splats, st, state.step))
    if _agreed_stop(comm, stop):  # signalled during setup: keep what there is (a resume starts here)
        _interrupt(project, base, state, comm)
    # seconds of training spent compiling kernels (spent from a --time-budget, but not a step's speed)
    stalled = state.plan.history[-1].get("stalled_s", 0.0) if state.plan is not None and state.plan.history else 0.0
    while state.step < total:
        step = state.step + 1
        t0, c0 = time.perf_counter(), kernels.status().compile_s
        state.optimizers["means"].param_groups[0]["lr"] = means_lr(cfg, step, data.extent)
        views = [state.next_view(len(data.train)) for _ in range(k)]  # the one-process stream, dealt out
        with prof.stage("data"):
            view = data.train[views[comm.rank]].at_scale(cfg.train_scale(step))
            target = view.target()
        with _out_of_memory(project, base, state, step, save=True, comm=comm):  # nothing is updated yet: save this state
            with prof.stage("render"):
                out = render_view(state, view, data.background, state.active_sh_degree(step, cfg.sh_degree_interval))
            info = StepInfo(out, view.camera.width, view.camera.height, combine=comm.combine_rows)
            with prof.stage("densification"):
                for strategy, st in zip(state.strategies, state.splats.states):
                    strategy.step_pre_backward(state.splats, st, step, info)
            with prof.stage("loss"):
                image, penalty = state.image_model.shade(out.image, views[comm.rank], step, cfg.iterations)
                loss = photometric_loss(image, target, cfg.lambda_dssim, view.keep) + penalty
            with prof.stage("backward"):
                loss.backward()
        with prof.stage("optimiser"):
            loss, stopping = comm.reduce_step(state.trainable(), loss, stop.is_set())
            info.finite = _all_finite(loss, state)
            _optimise(state, info.finite)
        state.step = step
        state.elapsed_s += time.perf_counter() - t0
        stalled += kernels.status().compile_s - c0  # (not evaluation's compiles: evaluation is not training time)
        writer.add(loss.detach() if info.finite else None)
        _compiled_record(state, on_event if comm.main else None)
        if state.bad_run >= cfg.max_bad_steps:
            path = _save(project, base, state, comm)
            raise TrainingDiverged(
                f"training diverged: {state.bad_run} consecutive steps with a non-finite loss or gradient "
                f"(step {state.images}); the last good parameters are in {path}; try a lower learning rate or --resume"
            )
        # Measure what this step's update produced, before its refinement or opacity
        # reset (right after a reset every view is nearly transparent); the end of the
        # main schedule is measured before a fine-tune starts, the final model after
        # its last refinement. Evaluation is not training time.
        info.heldout = _measure(cfg, data, state, step, total, comm, force=step == cfg.iterations < total)
        fitted = _measure_fit(cfg, data, state, step, comm) if info.heldout is not None else None
        t1 = time.perf_counter()
        with _out_of_memory(project, base, state, step, save=False, comm=comm), prof.stage("densification"):
            for strategy, st in zip(state.strategies, state.splats.states):  # may be half edited: keep the last checkpoint
                writer.refined(strategy.step_post_backward(state.splats, st, step, info))
        state.elapsed_s += time.perf_counter() - t1
        prof.step_done()
        if state.plan is not None:
            if k > 1:  # every rank plans from the same clock
                state.elapsed_s, stalled = comm.mean(torch.tensor([state.elapsed_s, stalled, 1.0], dtype=torch.float64)).tolist()
            planned = (state.plan.replan(base, state.images, state.elapsed_s, stalled)
                       if state.plan.due(state.elapsed_s, stalled) else None)
            if planned is not None:  # the strategies' schedules follow the new plan
                base, cfg = planned, planned.for_world(k)
                state.strategies = make_strategies(cfg, data.extent, ctx)
                total = cfg.total_steps
        evaluated = info.heldout
        if step == total:
            evaluated = _measure(cfg, data, state, step, total, comm, force=True)
            fitted = _measure_fit(cfg, data, state, step, comm) if evaluated is not None else None
        writer.line(step, state, evaluated, fitted, cfg.log_every, force=step == total)
        emit(on_event, Progress(STAGE, state.images, total * k, writer.info(state)))
        if comm.main and state.plan is None:
            eta.tell(state, on_event)
        if comm.main:
            emit(on_event, Snapshot(state.images, state.model))  # for live displays (train --viewer)
        if stopping or (k == 1 and stop.is_set()):
            _interrupt(project, base, state, comm)
        if step % cfg.checkpoint_every == 0 or step == total:
            _save(project, base, state, comm)
    emit(on_event, StageDone(STAGE, state.elapsed_s))
    if comm.main:
        prof.write(project, {"nproc": k, "compile": (state.compiled or {}).get("mode", "off")})
    return base


def _optimise(state: TrainState, finite: bool) -> None:
    """Adam's step on every parameter when the loss and gradients are finite (else the step is
    skipped and counted: NaN or Inf never reaches the parameters or the moments), then no gradients."""
    if finite:
        for opt in state.all_optimizers():
            opt.step()
        state.bad_run = 0
    else:
        state.bad_steps += 1
        state.bad_run += 1
    for opt in state.all_optimizers():
        opt.zero_grad(set_to_none=True)


def _save(project: Project, cfg: TrainConfig, state: TrainState, comm: Comm) -> Path:
    """A checkpoint of the run as one process would have written it: every rank folds its
    accumulators into rank 0's and confirms its parameters equal rank 0's; rank 0 writes."""
    comm.fold_rows(state.splats.states)
    comm.check_agree(state.trainable())
    path = project.checkpoint_path(state.images)
    if comm.main:
        save_state(path, state, cfg)
        log.prune_checkpoints(project, cfg.keep_checkpoints)
    return path


def _agreed_stop(comm: Comm, stop: threading.Event) -> bool:
    """Whether any rank was signalled (every rank learns the same answer)."""
    if comm.world == 1:
        return stop.is_set()
    return bool(comm.total(torch.tensor([float(stop.is_set())])) > 0)


def _context(data: TrainData, box: list[TrainState], on_event: EventSink | None, comm: Comm) -> Context:
    """What the strategies may ask of this run (`box` holds the state once it exists);
    the ranks share the views and combine the answers, so every rank gets the same one."""

    def score(which: str, sh_degree: int) -> tuple[float, float] | None:
        if which == "test":
            return evaluate_views(box[0], data.test, data.background, sh_degree, comm) if data.test else None
        # "val:K": K evenly spaced training views, each through its own colour transform
        idx = subset(list(range(len(data.train))), int(which.split(":")[1]))
        return evaluate_views(box[0], [data.train[i] for i in idx], data.background, sh_degree, comm, idx)

    def weights() -> Tensor:  # [N]
        p = box[0].params
        return comm.total(blending_weights(p["means"], p["quats"], p["log_scales"], p["opacity_logits"],
                                           ((v.viewmat, v.K, v.camera.width, v.camera.height)
                                            for v in comm.share(data.train))))

    center = torch.as_tensor(data.center, dtype=torch.float32, device=data.background.device)
    return Context(score=score, weights=weights, note=lambda m: emit(on_event, Note(m)), center=center,
                   views_seeing=lambda means: views_seeing(data.train, means),
                   cameras=lambda: [(v.viewmat, v.K, v.camera.width, v.camera.height) for v in data.train],
                   centres=lambda: torch.from_numpy(np.stack([v.camera.center for v in data.train])))


def _interrupt(project: Project, cfg: TrainConfig, state: TrainState, comm: Comm) -> None:
    """Checkpoint the last whole step and stop (the CLI exits 130)."""
    path = _save(project, cfg, state, comm)
    raise Interrupted(f"interrupted at step {state.images}; saved {path}; "
                      f"continue with `splatcli train {project.root} --resume`")


@contextlib.contextmanager
def _out_of_memory(project: Project, cfg: TrainConfig, state: TrainState, step: int, save: bool,
                   comm: Comm) -> Iterator[None]:
    """An allocation failure inside becomes a one-line SplatError (exit 2) naming the last
    good checkpoint, written now from `state` when `save` (the state is a whole step;
    one process only: the other ranks are not at a point where they could agree)."""
    try:
        yield
    except Exception as exc:
        if not is_out_of_memory(exc):
            raise
        raise _out_of_memory_error(project, cfg, state, step, exc, save and comm.world == 1) from None


def _out_of_memory_error(project: Project, cfg: TrainConfig, state: TrainState, step: int, exc: BaseException,
                         save: bool) -> SplatError:
    for opt in state.optimizers.values():
        opt.zero_grad(set_to_none=True)  # frees the gradients before writing
    path = None
    if save and state.step > 0:
        try:
            path = save_state(project.checkpoint_path(state.images), state, cfg)
        except (OSError, SplatError, RuntimeError, MemoryError):
            path = None
    path = path or project.latest_checkpoint()
    kept = f"the last good checkpoint is {path}" if path else "no checkpoint was written yet"
    return SplatError(f"out of memory at step {step * state.world} with {len(state.splats):,} Gaussians "
                      f"({type(exc).__name__}); {kept}",
                      hint=f"lower --max-size or set --max-gaussians, then `splatcli train {project.root} --resume`")


def _all_finite(loss: Tensor, state: TrainState) -> bool:  # loss: [] scalar
    """One reduction over the loss and every gradient (a single host sync)."""
    checks = [torch.isfinite(loss).reshape(1)]
    checks += [torch.isfinite(p.grad).all().reshape(1) for p in state.trainable().values() if p.grad is not None]
    return bool(torch.cat(checks).all())


def _measure(cfg: TrainConfig, data: TrainData, state: TrainState, step: int, total: int, comm: Comm,
             force: bool = False) -> tuple[float, float] | None:
    """Held-out PSNR / SSIM every `eval_every` steps (and when forced)."""
    if not data.test or not (force or (cfg.eval_every and step % cfg.eval_every == 0 and step < total)):
        return None
    return evaluate_views(state, data.test, data.background, state.active_sh_degree(step, cfg.sh_degree_interval),
                          comm)


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
        sc = score_image(img, v.image, v.keep, quantisation=quantisation)  # the uint8 photograph, as eval reads it
        ps.append(sc.psnr)
        ss.append(sc.ssim)
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
