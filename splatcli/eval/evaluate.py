"""`splatcli eval`: held-out error, render speed, and what a smaller model costs.

For a project: render every view of the held-out split at the resolution
training used, compare with the photographs (PSNR, SSIM, and LPIPS where its
weights are found: lpips.py; per image and mean), time the rendering, and trace
two speed-against-error curves:

* held-out PSNR against training seconds (from reports/train_log.jsonl);
* render time against PSNR at several Gaussian budgets (100%, 50%, 25%, 10%),
  keeping the Gaussians that contribute most: the largest total blending weight
  over the training views (budgets.py).

Views are scored by score.py, as training's held-out log scores them: renders
quantised to 8 bits by default, as the PNGs a user sees (and the original 3DGS
metrics script) are (`EvalConfig.quantisation`; the report says which:
`quantisation`), against the photographs as training fitted them
(score.load_target).

Masks are scored as training used them (`mask_mode` in the train summary;
Project.mask_mode("auto") for a model from elsewhere): "ignore" scores the
unmasked pixels only; "background" scores whole images, with mask files' masked
pixels painted in the background colour (alpha masks: the composited image, the
Blender benchmark's convention). The report says which (`masks`).

`compare_folders` scores two folders of images matched by name.
"""

from __future__ import annotations

import contextlib
import math
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..device import describe_device, synchronize
from ..errors import SplatError
from ..events import EventSink, Note, Progress, Stage, StageDone, emit
from ..files.atomic import atomic_write_json, atomic_write_text
from ..formats.ply import ply_bytes
from ..formats.registry import check_format, default_name, read_format, write_format
from ..gaussians import Gaussians
from ..inputs.images import load_rgb
from ..model import load_model
from ..project import Project, writer_lock
from ..render import Renderer, render_camera, resolve_renderer
from ..views.sources import SPLITS, View, choose_antialias, dataset_views, zoom_factor
from .budgets import contributions, prune_to
from .curve import read_curve
from .lpips import MIN_SIZE as LPIPS_MIN_SIZE, Lpips, load_lpips
from .report import (
    NO_PLOTS_HINT,
    BudgetPoint,
    EvalReport,
    FormatPoint,
    ImageScore,
    model_stats,
    write_plots,
    write_report_md,
)
from .score import QUANTISATIONS, REPORTED, load_target, score_image

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp")
DEFAULT_BUDGETS = (1.0, 0.5, 0.25, 0.1)


@dataclass(frozen=True)
class EvalConfig:
    split: str = "test"  # test | train | all
    background: tuple[float, float, float] | None = None  # None: the scene's
    downscale: float | None = None  # None: the resolution training used
    budgets: tuple[float, ...] = DEFAULT_BUDGETS  # fractions of the Gaussians kept for the speed curve
    contribution_views: int = 16  # training views that rank the Gaussians (evenly spaced)
    plots: bool = True  # PNG plots beside eval.md (needs matplotlib)
    write: bool = True  # write eval.json and eval.md
    model: Path | None = None  # score this 3DGS .ply (any tool's) instead of the latest checkpoint
    out: Path | None = None  # folder for eval.json, eval.md, plots (default PROJECT/reports)
    formats: tuple[str, ...] = ()  # file formats to encode, decode and score (size against error)
    lpips_weights: Path | None = None  # torchvision's AlexNet weights for LPIPS (None: the torch hub cache)
    antialias: str = "auto"  # auto | on | off: the 2D filter (views/sources.choose_antialias)
    renderer: str = "auto"  # auto | torch | gsplat (render/backends.resolve_renderer)
    quantisation: str = REPORTED  # renders as scored: "8-bit" (as PNG, training's held-out log too) | "none"


@dataclass
class FolderReport:
    """`eval --pred DIR --gt DIR`."""

    psnr: float
    ssim: float
    lpips: float | None
    per_image: list[ImageScore]
    pred_dir: Path
    gt_dir: Path
    missing: list[str]  # predictions with no ground truth of the same name
    quantisation: str = REPORTED  # the files are 8-bit as read (inputs/images.load_rgb), so this changes nothing

    def summary(self) -> dict[str, Any]:
        return {"psnr": self.psnr, "ssim": self.ssim, "lpips": self.lpips, "num_images": len(self.per_image),
                "pred": self.pred_dir, "gt": self.gt_dir, "missing": self.missing, "quantisation": self.quantisation,
                "per_image": [asdict(s) for s in self.per_image]}


def load_image(path: Path, background: Sequence[float] = (0.0, 0.0, 0.0),
               size: tuple[int, int] | None = None) -> Tensor:  # -> [H, W, 3] float64 in [0, 1]
    """A photograph or render to score, through the one image loader (inputs/images.py)."""
    return torch.from_numpy(load_rgb(path, size, tuple(background))).to(torch.float64) / 255.0


def score(name: str, pred: Tensor, gt: Tensor, lp: Lpips | None = None, keep: Tensor | None = None,
          quantisation: str = REPORTED) -> ImageScore:  # [H, W, 3] each, keep [H, W]
    """PSNR, SSIM, the colour-fit PSNR (and LPIPS) of one view (score.score_image)."""
    s = score_image(pred, gt, keep, quantisation=quantisation, color_fit=True, compensated=True, lpips=lp)
    c = s.compensated
    return ImageScore(name=name, psnr=s.psnr, ssim=s.ssim, lpips=s.lpips, psnr_color_fit=s.psnr_color_fit,
                      compensated_psnr=c.psnr if c else None, compensated_ssim=c.ssim if c else None,
                      compensated_lpips=c.lpips if c else None)


MASKED_SCORING = {  # eval's `masks` line, by the mode training used
    "ignore": "unmasked pixels only (trained with --mask-mode ignore)",
    "background": "whole images, masked pixels against the background colour (--mask-mode background)",
}


def _ground_truth(project: Project, views: Sequence[View], bg_rgb: tuple[float, float, float], mode: str,
                  on_event: EventSink | None) -> tuple[list[Tensor], list[Tensor | None]]:
    """Each view's photograph ([H, W, 3] float64) and its kept pixels ([H, W] bool) or
    None, as training fitted them (score.load_target)."""
    gts, keeps = [], []
    emit(on_event, Stage("load images", total=len(views)))
    for i, v in enumerate(views):
        rgb, keep = load_target(project, v.camera.name, (v.camera.width, v.camera.height), bg_rgb, mode)
        gts.append(torch.from_numpy(rgb).to(torch.float64) / 255.0)
        keeps.append(torch.from_numpy(keep) if keep is not None else None)
        emit(on_event, Progress("load images", i + 1, len(views)))
    emit(on_event, StageDone("load images", 0.0))
    return gts, keeps


def _score_views(g: Gaussians, *, stage: str, views: Sequence[View], gts: Sequence[Tensor],
                 keeps: Sequence[Tensor | None], bg: Tensor, lp: Lpips | None, on_event: EventSink | None,
                 antialiased: bool, quantisation: str, renderer: Renderer) -> tuple[list[ImageScore], float]:
    """Render and score every view (quantised: score.py); returns scores and the median
    render seconds per frame (the median: other processes sharing the CPU make
    single frames slow, and the first call of a process pays one-off set-up, so
    one warm-up render comes first)."""
    scores, times = [], []
    emit(on_event, Stage(stage, total=len(views)))
    t_all = time.perf_counter()
    render_camera(g, views[0].camera, bg, antialiased=antialiased, draw=renderer.draw)  # warm-up, untimed
    for i, (v, gt, keep) in enumerate(zip(views, gts, keeps)):
        synchronize(g.device)
        t0 = time.perf_counter()
        out = render_camera(g, v.camera, bg, antialiased=antialiased, draw=renderer.draw)
        synchronize(g.device)
        times.append(time.perf_counter() - t0)
        scores.append(score(v.camera.name, out.image, gt, lp, keep, quantisation))
        emit(on_event, Progress(stage, i + 1, len(views), {"psnr": _mean(scores, "psnr")}))
    emit(on_event, StageDone(stage, time.perf_counter() - t_all))
    return scores, float(np.median(times))


ScoreViews = Callable[..., tuple[list[ImageScore], float]]  # _score_views with all but the model and stage bound


def _score_formats(g: Gaussians, formats: Sequence[str], score_views: ScoreViews,
                   full_psnr: float) -> list[FormatPoint]:
    """Each format: write the model, read it back through our reader, score the views."""
    out = []
    ply_size = ply_bytes(len(g), g.sh_degree)
    with tempfile.TemporaryDirectory(prefix="splatcli-formats-") as tmp:
        for fmt in formats:
            path = Path(tmp) / default_name("model", fmt)
            t0 = time.perf_counter()
            w = write_format(fmt, path, g.to("cpu"))
            t1 = time.perf_counter()
            back = read_format(path, g.device, fmt).gaussians
            t2 = time.perf_counter()
            sc, _ = score_views(back, stage=f"format {fmt}")
            p = _mean(sc, "psnr")
            out.append(FormatPoint(format=fmt, bytes=w.bytes, bytes_per_gaussian=w.bytes / max(len(g), 1),
                                   ratio=ply_size / max(w.bytes, 1), psnr=p, ssim=_mean(sc, "ssim"),
                                   db_lost=full_psnr - p, encode_s=t1 - t0, decode_s=t2 - t1, lpips=_mean(sc, "lpips")))
            path.unlink(missing_ok=True)
    return out


def _mean(scores: Sequence[ImageScore], key: str) -> Any:  # -> float, or None when some image has none (LPIPS)
    """Mean over the images of one score (PSNR: of per-image dB, the 3DGS convention)."""
    values = [getattr(s, key) for s in scores]
    return None if any(v is None for v in values) else float(np.mean(values))


def _budget_point(fraction: float, g: Gaussians, scores: Sequence[ImageScore], secs: float) -> BudgetPoint:
    return BudgetPoint(fraction=fraction, num_gaussians=len(g), ply_bytes=ply_bytes(len(g), g.sh_degree),
                       psnr=_mean(scores, "psnr"), ssim=_mean(scores, "ssim"), render_fps=1.0 / max(secs, 1e-9),
                       ms_per_frame=1000 * secs, lpips=_mean(scores, "lpips"))




# ---------------------------------------------------------------------------
# the command's core
# ---------------------------------------------------------------------------


def check_eval_config(config: EvalConfig) -> None:
    if config.split not in SPLITS:
        raise SplatError(f"--split {config.split!r} is not known; allowed values: {', '.join(SPLITS)}")
    if config.downscale is not None and not (math.isfinite(config.downscale) and 0 < config.downscale <= 64):
        raise SplatError(f"--downscale {config.downscale}: must be in (0, 64]")
    if not config.budgets or any(not (0 < b <= 1) for b in config.budgets):
        raise SplatError("--budgets: each fraction must be in (0, 1], e.g. 1,0.5,0.25,0.1")
    if config.model is not None and not Path(config.model).is_file():
        what = "is a directory, not a .ply file" if Path(config.model).is_dir() else "no such .ply file"
        raise SplatError(f"--model {config.model}: {what}")
    if config.out is not None and Path(config.out).exists() and not Path(config.out).is_dir():
        raise SplatError(f"--out {config.out}: exists and is not a directory")
    for f in config.formats:
        check_format(f, "--formats")
    if config.contribution_views < 1:
        raise SplatError(f"contribution_views {config.contribution_views}: must be at least 1")
    choose_antialias(config.antialias, None, None)  # refuses an unknown mode
    if config.quantisation not in QUANTISATIONS:
        raise SplatError(f"quantisation {config.quantisation!r} is not known; allowed values: {', '.join(QUANTISATIONS)}")


@dataclass
class EvalPlan:
    """Everything checked and loaded, nothing scored yet (input errors surface
    before any progress display or output)."""

    project: Project
    config: EvalConfig
    gaussians: Gaussians
    step: int | None  # checkpoint step (None for a .ply)
    model_name: str
    views: list[View]  # at eval resolution, with their photographs
    background: tuple[float, float, float]
    downscale: float
    max_size: int | None
    train_summary: dict[str, Any]
    notes: list[str]
    lpips: Lpips | None  # None: LPIPS unavailable (the reason is in notes)
    antialiased: bool = False  # draw with the 2D filter
    renderer: Renderer = Renderer("torch")


def plan_eval(root: str | Path, config: EvalConfig, device: torch.device) -> EvalPlan:
    """Check options, open the project, load the model (latest checkpoint or
    `config.model`) and choose the views at the resolution trained."""
    check_eval_config(config)
    renderer = resolve_renderer(config.renderer, device)
    project = Project.open(root)
    if config.model is not None:
        project.require_processed()
    m = load_model(root if config.model is None else config.model, device)
    g, step, model_name, notes = m.gaussians, m.step, m.name, list(m.notes)
    views = dataset_views(project, config.split)
    absent = [v.image for v in views if v.image is not None and not v.image.is_file()]
    if absent:
        raise SplatError(f"{absent[0]}: missing ({len(absent)} of the {len(views)} {config.split} photographs are "
                         "gone); restore them or run `splatcli process` again")
    finite = g.finite_mask()
    if not bool(finite.all()):
        notes.append(f"{int((~finite).sum())} Gaussians with NaN/Inf values were left out")
        g = g.select(finite)

    tsum = ((project.step("train") or {}).get("summary") or {}) if config.model is None else {}
    # else the resolution trained, also for a .ply scored against this project
    downscale, max_size = (config.downscale, None) if config.downscale is not None else project.trained_resolution()
    base, views = views, [replace(v, camera=v.camera.at_resolution(downscale, max_size)) for v in views]
    antialiased, why = choose_antialias(config.antialias, m.antialiased, zoom_factor(project, views, base))
    small = [v.camera for v in views if min(v.camera.width, v.camera.height) < 11]
    if small:
        raise SplatError(f"{small[0].name}: {small[0].width}x{small[0].height} at eval resolution is too small "
                         "for SSIM (at least 11x11 pixels); lower --downscale")
    bg_rgb = config.background if config.background is not None else (project.background() or (0.0, 0.0, 0.0))
    lp, why_not = load_lpips(config.lpips_weights, device)
    c = views[0].camera
    if lp is not None and min(c.width, c.height) < LPIPS_MIN_SIZE:
        lp, why_not = None, f"LPIPS skipped: {c.width}x{c.height} views are smaller than AlexNet's {LPIPS_MIN_SIZE} pixels"
    notes += [n for n in (why, why_not, renderer.note) if n]
    return EvalPlan(project=project, config=config, gaussians=g, step=step, model_name=model_name, views=views,
                    background=tuple(bg_rgb), downscale=downscale,  # type: ignore[arg-type]
                    max_size=max_size, train_summary=tsum, notes=notes, lpips=lp, antialiased=antialiased,
                    renderer=renderer)



def run_eval(plan: EvalPlan, *, on_event: EventSink | None = None) -> EvalReport:
    """Score a plan (see module docstring) and write eval.json, eval.md and the
    plots into `config.out` (default the project's reports/, under the project's
    writer lock)."""
    own = plan.config.write and plan.config.out is None
    with writer_lock(plan.project.root, "eval", shared=True) if own else contextlib.nullcontext():
        return _run_eval(plan, on_event)


def _mask_mode(project: Project, tsum: dict[str, Any]) -> tuple[str, str | None]:
    """The mask mode training used (else the project's), and what the report says of it (None: off)."""
    mode = tsum.get("mask_mode") if tsum.get("mask_mode") in ("ignore", "background", "off") else None
    mode = project.mask_mode(mode or "auto")
    if mode == "off":
        return mode, None
    return mode, (MASKED_SCORING[mode] if project.mask_source() == "files" or mode == "ignore" else
                  "whole images, composited over the background (the masks are the images' alpha)")


def _run_eval(plan: EvalPlan, on_event: EventSink | None) -> EvalReport:
    project, config, g, views = plan.project, plan.config, plan.gaussians, plan.views
    step, model_name, notes, tsum = plan.step, plan.model_name, list(plan.notes), plan.train_summary
    bg = torch.tensor(plan.background, dtype=g.means.dtype, device=g.device)

    mode, masks = _mask_mode(project, tsum)
    gts, keeps = _ground_truth(project, views, plan.background, mode, on_event)
    score_views = partial(_score_views, views=views, gts=gts, keeps=keeps, bg=bg, lp=plan.lpips, on_event=on_event,
                          antialiased=plan.antialiased, quantisation=config.quantisation, renderer=plan.renderer)
    per_image, secs = score_views(g, stage="eval")
    first = _budget_point(1.0, g, per_image, secs)
    budgets = _budget_points(plan, first, score_views, on_event)
    formats = _score_formats(g, config.formats, score_views, first.psnr)
    curve = read_curve(project.train_log_path) if config.model is None else []
    # the log's scores: 8-bit since train recorded its quantisation, unquantised before
    curve_q = str(tsum.get("quantisation", "none")) if curve else None
    curve_p = str(tsum.get("protocol", "raw")) if curve else None
    # whether training learnt each photo's appearance (an image model): then the compensated score leads
    learnt = ((project.step("train") or {}).get("config") or {}).get("appearance", "none") != "none"
    report = EvalReport(
        psnr=first.psnr, ssim=first.ssim, lpips=first.lpips, per_image=per_image, num_gaussians=len(g),
        sh_degree=g.sh_degree, ply_bytes=first.ply_bytes,
        train_seconds=float(tsum["train_seconds"]) if isinstance(tsum.get("train_seconds"), (int, float)) else None,
        train_steps=int(tsum["steps"]) if isinstance(tsum.get("steps"), int) else step, render_fps=first.render_fps,
        device=describe_device(g.device), renderer=plan.renderer.name, split=config.split,
        width=views[0].camera.width, height=views[0].camera.height, step=step, model=model_name,
        **{k: _mean(per_image, k) for k in ("psnr_color_fit", "compensated_psnr", "compensated_ssim",
                                            "compensated_lpips")},
        headline="compensated" if learnt and config.model is None else "raw", budgets=budgets, formats=formats,
        training_curve=curve, masks=masks, quantisation=config.quantisation, curve_quantisation=curve_q,
        curve_protocol=curve_p, stats=model_stats(g), notes=notes,
    )
    for n in notes:
        emit(on_event, Note(n))
    if config.write:
        _write(plan, report, on_event)
    return report


def _budget_points(plan: EvalPlan, first: BudgetPoint, score_views: ScoreViews,
                   on_event: EventSink | None) -> list[BudgetPoint]:
    """Speed against error at smaller budgets: the model pruned to each fraction of --budgets by
    its contribution to the training views, scored on the same views as the whole (`first`)."""
    project, config, g = plan.project, plan.config, plan.gaussians
    budgets = [first]
    fractions = sorted({float(b) for b in config.budgets if b < 1.0}, reverse=True)
    if fractions:
        rank_views = [v.camera for v in dataset_views(project, "train" if project.splits()["train"] else "all")]
        stride = max(1, len(rank_views) // config.contribution_views)
        rank_cams = [c.at_resolution(plan.downscale, plan.max_size)
                     for c in rank_views[::stride][: config.contribution_views]]
        emit(on_event, Stage("rank Gaussians", total=None))
        t0 = time.perf_counter()
        weight = contributions(g, rank_cams)
        emit(on_event, StageDone("rank Gaussians", time.perf_counter() - t0))
        for f in fractions:
            gp = prune_to(g, weight, f)
            budgets.append(_budget_point(f, gp, *score_views(gp, stage=f"budget {f:.0%}")))
    return budgets if 1.0 in config.budgets else budgets[1:]


def _write(plan: EvalPlan, report: EvalReport, on_event: EventSink | None) -> None:
    """The report's JSON, Markdown and plots; the project's own model's scores in its manifest."""
    project, config = plan.project, plan.config
    out = Path(config.out) if config.out is not None else project.reports_dir
    if config.plots:
        plots = write_plots(report, project, out)
        if plots is None:
            report.notes.append(NO_PLOTS_HINT)
            emit(on_event, Note(NO_PLOTS_HINT))
        report.plots = plots or []
    atomic_write_json(out / project.eval_json_path.name, report.to_json())
    report.report_path = out / project.eval_md_path.name
    atomic_write_text(report.report_path, write_report_md(report, project))
    if config.model is None and config.out is None:  # the project's own model, in its own reports
        project.record_step("eval", config={"split": config.split, "background": list(plan.background),
                                            "downscale": plan.downscale, "max_size": plan.max_size,
                                            "budgets": list(config.budgets), "formats": list(config.formats),
                                            "antialiased": plan.antialiased, "quantisation": config.quantisation},
                            summary=report.summary())




def compare_folders(pred_dir: str | Path, gt_dir: str | Path, *, background: Sequence[float] = (0.0, 0.0, 0.0),
                    lpips_weights: Path | None = None, device: torch.device = torch.device("cpu"),
                    on_event: EventSink | None = None) -> FolderReport:
    """PSNR/SSIM/LPIPS of every image in `pred_dir` against the image of the same name
    (any extension) in `gt_dir`, as 3DGS's metrics.py does with renders/ and gt/."""
    pred_dir, gt_dir = Path(pred_dir), Path(gt_dir)
    for d, opt in ((pred_dir, "--pred"), (gt_dir, "--gt")):
        if not d.is_dir():
            raise SplatError(f"{opt} {d}: not a directory")
    gts = {p.stem: p for p in sorted(gt_dir.iterdir()) if p.suffix.lower() in IMAGE_SUFFIXES}
    preds = [p for p in sorted(pred_dir.iterdir()) if p.suffix.lower() in IMAGE_SUFFIXES]
    if not preds:
        raise SplatError(f"--pred {pred_dir}: holds no images ({', '.join(IMAGE_SUFFIXES)})")
    pairs = [(p, gts[p.stem]) for p in preds if p.stem in gts]
    missing = [p.name for p in preds if p.stem not in gts]
    if not pairs:
        raise SplatError(f"--gt {gt_dir}: no image has the name of one in {pred_dir}")
    lp, why_not = load_lpips(lpips_weights, device)
    if missing:
        emit(on_event, Note(f"{len(missing)} predictions have no ground truth of the same name: {', '.join(missing[:5])}",
                            "warning"))
    scores = []
    emit(on_event, Stage("compare", total=len(pairs)))
    for i, (p, q) in enumerate(pairs):
        a, b = load_image(p, background), load_image(q, background)
        if a.shape != b.shape:
            raise SplatError(f"{p}: size {a.shape[1]}x{a.shape[0]} differs from {q} ({b.shape[1]}x{b.shape[0]})")
        if min(a.shape[0], a.shape[1]) < 11:
            raise SplatError(f"{p}: {a.shape[1]}x{a.shape[0]} is too small for SSIM (at least 11x11)")
        scores.append(score(p.name, a, b, lp))
        emit(on_event, Progress("compare", i + 1, len(pairs)))
    emit(on_event, StageDone("compare", 0.0))
    if lp is not None and _mean(scores, "lpips") is None:
        why_not = f"LPIPS skipped: some images are smaller than AlexNet's {LPIPS_MIN_SIZE} pixels a side"
    if why_not:
        emit(on_event, Note(why_not))
    return FolderReport(psnr=_mean(scores, "psnr"), ssim=_mean(scores, "ssim"), lpips=_mean(scores, "lpips"),
                        per_image=scores, pred_dir=pred_dir, gt_dir=gt_dir, missing=missing)
