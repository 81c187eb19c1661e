"""`splatcli eval`: held-out error, render speed, and what a smaller model costs.

For a project: render every view of the held-out split at the resolution
training used, compare with the photographs (PSNR, SSIM per image and mean),
time the rendering, and trace two speed-against-error curves:

* held-out PSNR against training seconds (from reports/train_log.jsonl);
* render time against PSNR at several Gaussian budgets (100%, 50%, 25%, 10%),
  keeping the Gaussians that contribute most. A Gaussian's contribution is its
  total blending weight sum_pixels alpha_i T_i over the training views, obtained
  exactly by autograd: with every colour at 0.5 (DC = 0, degree 0, so the
  clamp at 0 is inactive) the image is sum_i w_i c_i + T bg, linear in c_i, so
  d(sum image_R) / d(dc_i,R) = SH_C0 * sum_pixels w_i.

Rendered images are quantised to 8 bits before scoring, as the PNGs a user
sees (and the original 3DGS metrics script) are.

`compare_folders` scores two folders of images matched by name.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from torch import Tensor

from ..camera import Camera
from ..errors import SplatError
from ..events import EventSink, Note, Progress, Stage, StageDone, emit
from ..gaussians import Gaussians
from ..io.atomic import atomic_write_json, atomic_write_text
from ..io.ply import ply_bytes
from .metrics import psnr, ssim
from ..project import Project
from ..render.weights import blending_weights
from ..views.output import _sync, describe_device, project_background, render_camera
from ..views.sources import SPLITS, View, dataset_views

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp", ".exr")
DEFAULT_BUDGETS = (1.0, 0.5, 0.25, 0.1)
SH_USED_TOL = 0.01  # a band is "used" when some coefficient moves colour by > 1% (SH value x basis ~ coefficient)


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


@dataclass
class ImageScore:
    name: str
    psnr: float  # dB
    ssim: float


@dataclass
class BudgetPoint:
    fraction: float  # of the Gaussians kept
    num_gaussians: int
    ply_bytes: int
    psnr: float
    ssim: float
    render_fps: float
    ms_per_frame: float


@dataclass
class CurvePoint:
    step: int
    elapsed_s: float  # training seconds
    psnr: float
    ssim: float | None = None
    num_gaussians: int | None = None


@dataclass
class Histogram:
    edges: list[float]  # len(counts) + 1
    counts: list[int]


@dataclass
class ModelStats:
    log10_scale_hist: Histogram  # all three axes, log10 world units
    opacity_hist: Histogram  # sigmoid(logit)
    sh_degree_counts: list[int]  # Gaussians whose highest used band is 0, 1, ..., d
    median_scale: float
    median_opacity: float


@dataclass
class EvalReport:
    psnr: float  # mean over the split, dB
    ssim: float
    per_image: list[ImageScore]
    num_gaussians: int
    sh_degree: int
    ply_bytes: int
    train_seconds: float | None
    train_steps: int | None
    render_fps: float  # 1 / median frame time, held-out views at eval resolution, rasterization only
    device: str
    split: str
    width: int
    height: int
    step: int | None  # checkpoint step (None for a .ply)
    model: str = ""  # what was scored: "checkpoint step 7000" or the .ply path
    budgets: list[BudgetPoint] = field(default_factory=list)
    training_curve: list[CurvePoint] = field(default_factory=list)
    stats: ModelStats | None = None
    plots: list[str] = field(default_factory=list)  # file names beside eval.md
    notes: list[str] = field(default_factory=list)
    report_path: Path | None = None  # eval.md, when written

    def worst(self, k: int = 5) -> list[ImageScore]:
        return sorted(self.per_image, key=lambda s: s.psnr)[:k]

    def summary(self) -> dict[str, Any]:
        """The headline numbers (what `--json` prints)."""
        return {k: getattr(self, k) for k in ("psnr", "ssim", "num_gaussians", "sh_degree", "ply_bytes",
                                              "train_seconds", "train_steps", "render_fps", "device", "split",
                                              "width", "height", "step", "model")} | {"num_images": len(self.per_image)}

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        return {**self.summary(), **{k: d[k] for k in ("per_image", "budgets", "training_curve", "stats", "plots",
                                                       "notes")}}


@dataclass
class FolderReport:
    """`eval --pred DIR --gt DIR`."""

    psnr: float
    ssim: float
    per_image: list[ImageScore]
    pred_dir: Path
    gt_dir: Path
    missing: list[str]  # predictions with no ground truth of the same name

    def summary(self) -> dict[str, Any]:
        return {"psnr": self.psnr, "ssim": self.ssim, "num_images": len(self.per_image), "pred": self.pred_dir,
                "gt": self.gt_dir, "missing": self.missing, "per_image": [asdict(s) for s in self.per_image]}


# ---------------------------------------------------------------------------
# images
# ---------------------------------------------------------------------------


def load_image(path: Path, background: Sequence[float] = (0.0, 0.0, 0.0),
               size: tuple[int, int] | None = None) -> Tensor:
    """An image file as [H, W, 3] float64 in [0, 1]; RGBA composited over
    `background`; resized (area) to `size` = (width, height) when given."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED) if path.is_file() else None
    if img is None:
        raise SplatError(f"{path}: cannot read this image")
    if size is not None and (img.ndim == 2 or img.shape[2] == 3) and (img.shape[1], img.shape[0]) != tuple(size):
        # resize in the file's own type, as training's loader does, so both score one target
        shrink = size[0] < img.shape[1]
        img = cv2.resize(img, tuple(size), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    scale = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(img.dtype, 1.0)
    a = img.astype(np.float64) / scale
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=2)
    if a.shape[2] == 4:
        rgb, alpha = a[..., 2::-1], a[..., 3:4]
        a = rgb * alpha + np.asarray(background, dtype=np.float64) * (1 - alpha)
    else:
        a = a[..., 2::-1]
    if size is not None and (a.shape[1], a.shape[0]) != tuple(size):  # RGBA: composited first, then resized
        a = cv2.resize(a, tuple(size), interpolation=cv2.INTER_AREA if size[0] < a.shape[1] else cv2.INTER_LINEAR)
    return torch.from_numpy(np.ascontiguousarray(np.clip(a, 0.0, 1.0)))


def quantise(img: Tensor) -> Tensor:  # [H, W, 3] -> [H, W, 3] float64 in 1/255 steps
    return (img.detach().clamp(0, 1) * 255).round().to(torch.float64).cpu() / 255.0


def score(pred: Tensor, gt: Tensor) -> tuple[float, float]:  # [H, W, 3] each
    return float(psnr(pred, gt)), float(ssim(pred.to(torch.float64), gt.to(torch.float64)))


# ---------------------------------------------------------------------------
# the model's pieces
# ---------------------------------------------------------------------------


def eval_size(cam: Camera, downscale: float, max_size: int | None) -> Camera:
    """The camera at the resolution training used: divide by `downscale`, then cap
    the longest side at `max_size`."""
    c = cam.scaled(1.0 / downscale) if downscale != 1.0 else cam
    if max_size and max(c.width, c.height) > max_size:
        c = c.scaled(max_size / max(c.width, c.height))
    return c


def contributions(g: Gaussians, cams: Sequence[Camera]) -> Tensor:  # -> [N] total blending weight, pixels
    """sum over views and pixels of alpha_i T_i, exactly (render.weights)."""
    return blending_weights(g.means, g.quats, g.log_scales, g.opacity_logits,
                            (cam.torch(g.device, g.means.dtype) + (cam.width, cam.height) for cam in cams))


def prune_to(g: Gaussians, weight: Tensor, fraction: float) -> Gaussians:  # weight [N]
    """The `fraction` of the Gaussians with the largest weight (ties: lower index first)."""
    k = max(1, int(math.ceil(fraction * len(g))))
    if k >= len(g):
        return g
    order = torch.argsort(-weight, stable=True)[:k]
    keep, _ = torch.sort(order)  # keep the original order (depth sorting does not care, files diff better)
    return g.select(keep)


def used_sh_degree(sh: Tensor) -> Tensor:  # [N, K, 3] -> [N] int
    """Highest band with a coefficient larger than SH_USED_TOL (0 when only DC)."""
    k = sh.shape[1]
    d = int(round(math.sqrt(k))) - 1
    used = torch.zeros(sh.shape[0], dtype=torch.long, device=sh.device)
    for l in range(1, d + 1):
        band = sh[:, l * l:(l + 1) * (l + 1), :].abs().amax(dim=(1, 2))
        used = torch.where(band > SH_USED_TOL, torch.full_like(used, l), used)
    return used


def model_stats(g: Gaussians, bins: int = 40) -> ModelStats:
    ls = (g.log_scales.detach().to(torch.float64).cpu().numpy() / math.log(10)).ravel()
    op = torch.sigmoid(g.opacity_logits.detach().to(torch.float64)).cpu().numpy()
    ls = ls[np.isfinite(ls)]
    h1, e1 = np.histogram(ls, bins=bins) if ls.size else (np.zeros(bins, int), np.linspace(-1, 0, bins + 1))
    h2, e2 = np.histogram(op, bins=bins, range=(0.0, 1.0))
    used = used_sh_degree(g.sh.detach()).cpu().numpy()
    counts = [int((used == l).sum()) for l in range(g.sh_degree + 1)]
    return ModelStats(
        log10_scale_hist=Histogram(edges=[float(x) for x in e1], counts=[int(x) for x in h1]),
        opacity_hist=Histogram(edges=[float(x) for x in e2], counts=[int(x) for x in h2]),
        sh_degree_counts=counts,
        median_scale=float(10 ** np.median(ls)) if ls.size else float("nan"),
        median_opacity=float(np.median(op)) if op.size else float("nan"),
    )


def read_training_curve(path: Path) -> list[CurvePoint]:
    """Held-out PSNR against training seconds from train_log.jsonl. Partial or
    malformed lines (a crash can leave one) are skipped."""
    if not path.is_file():
        return []
    points = []
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError:
        return []
    for line in text.splitlines():
        try:
            d = json.loads(line)
        except json.JSONDecodeError:
            continue
        if not isinstance(d, dict):
            continue
        p, t, s = d.get("psnr"), d.get("elapsed_s"), d.get("step")
        if isinstance(p, (int, float)) and isinstance(t, (int, float)) and isinstance(s, int) and math.isfinite(p):
            ss = d.get("ssim")
            n = d.get("num_gaussians")
            points.append(CurvePoint(step=s, elapsed_s=float(t), psnr=float(p),
                                     ssim=float(ss) if isinstance(ss, (int, float)) else None,
                                     num_gaussians=int(n) if isinstance(n, int) else None))
    return points


def _score_views(g: Gaussians, views: Sequence[View], gts: Sequence[Tensor], bg: Tensor,
                 on_event: EventSink | None, stage: str) -> tuple[list[ImageScore], float]:
    """Render, quantise and score every view; returns scores and the median
    render seconds per frame (the median: other processes sharing the CPU make
    single frames slow, and the first call of a process pays one-off set-up, so
    one warm-up render comes first)."""
    scores, times = [], []
    emit(on_event, Stage(stage, total=len(views)))
    t_all = time.perf_counter()
    render_camera(g, views[0], bg)  # warm-up, untimed
    for i, (v, gt) in enumerate(zip(views, gts)):
        _sync(g.device)
        t0 = time.perf_counter()
        out = render_camera(g, v, bg)
        _sync(g.device)
        times.append(time.perf_counter() - t0)
        p, s = score(quantise(out.image), gt)
        scores.append(ImageScore(name=v.camera.name, psnr=p, ssim=s))
        emit(on_event, Progress(stage, i + 1, len(views), {"psnr": float(np.mean([x.psnr for x in scores]))}))
    emit(on_event, StageDone(stage, time.perf_counter() - t_all))
    return scores, float(np.median(times))


def _mean_psnr(scores: Sequence[ImageScore]) -> float:
    """Mean of per-image PSNR (the 3DGS convention), dB."""
    return float(np.mean([s.psnr for s in scores]))


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
    if config.contribution_views < 1:
        raise SplatError(f"contribution_views {config.contribution_views}: must be at least 1")


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


def plan_eval(root: str | Path, config: EvalConfig, device: torch.device) -> EvalPlan:
    """Check options, open the project, load the model (latest checkpoint or
    `config.model`) and choose the views at the resolution trained."""
    from ..io.checkpoint import load_checkpoint
    from ..io.ply import read_ply

    check_eval_config(config)
    project = Project.open(root)
    notes: list[str] = []
    if config.model is None:
        ck = load_checkpoint(project.require_trained(), device)
        g, step, model_name = ck.model(), ck.step, f"checkpoint step {ck.step}"
    else:
        project.require_processed()
        r = read_ply(config.model, device)
        g, step, model_name = r.gaussians, None, str(config.model)
        notes += r.notes
    views = dataset_views(project, config.split)
    absent = [v.image for v in views if v.image is not None and not v.image.is_file()]
    if absent:
        raise SplatError(f"{absent[0]}: missing ({len(absent)} of the {len(views)} {config.split} photographs are "
                         "gone); restore them or run `splatcli process` again")
    finite = g.finite_mask()
    if not bool(finite.all()):
        notes.append(f"{int((~finite).sum())} Gaussians with NaN/Inf values were left out")
        g = g.select(finite)

    train_step = project.step("train") or {}
    tcfg = train_step.get("config") or {}  # the resolution trained, also for a .ply scored against this project
    tsum = (train_step.get("summary") or {}) if config.model is None else {}
    if config.downscale is not None:
        downscale, max_size = config.downscale, None
    else:
        downscale, max_size = _trained_resolution(project, tcfg)
    views = [View(camera=eval_size(v.camera, downscale, max_size),
                  out_name=v.out_name, image=v.image) for v in views]
    small = [v.camera for v in views if min(v.camera.width, v.camera.height) < 11]
    if small:
        raise SplatError(f"{small[0].name}: {small[0].width}x{small[0].height} at eval resolution is too small "
                         "for SSIM (at least 11x11 pixels); lower --downscale")
    bg_rgb = config.background if config.background is not None else (project_background(project) or (0.0, 0.0, 0.0))
    return EvalPlan(project=project, config=config, gaussians=g, step=step, model_name=model_name, views=views,
                    background=tuple(bg_rgb), downscale=downscale,  # type: ignore[arg-type]
                    max_size=max_size, train_summary=tsum, notes=notes)


def _trained_resolution(project: Project, tcfg: dict[str, Any]) -> tuple[float, int | None]:
    """(downscale, max_size) that `train` recorded; a hand-edited value is named, not guessed."""
    where = f"{project.manifest_path}: steps.train.config"
    d = tcfg.get("downscale")
    if d is None:
        d = 1.0
    if isinstance(d, bool) or not isinstance(d, (int, float)) or not (math.isfinite(d) and 0 < d <= 64):
        raise SplatError(f"{where}.downscale is {d!r}, not a number in (0, 64]; pass --downscale")
    m = tcfg.get("max_size")
    if m is not None and (isinstance(m, bool) or not isinstance(m, int) or m < 16):
        raise SplatError(f"{where}.max_size is {m!r}, not a whole number of pixels >= 16; pass --downscale")
    return float(d), m


def run_eval(plan: EvalPlan, *, on_event: EventSink | None = None) -> EvalReport:
    """Score a plan (see module docstring) and write eval.json, eval.md and the
    plots into `config.out` (default the project's reports/)."""
    project, config, g, views = plan.project, plan.config, plan.gaussians, plan.views
    step, model_name, notes, tsum = plan.step, plan.model_name, list(plan.notes), plan.train_summary
    downscale, max_size, bg_rgb = plan.downscale, plan.max_size, plan.background
    bg = torch.tensor(bg_rgb, dtype=g.means.dtype, device=g.device)
    device = g.device

    emit(on_event, Stage("load images", total=len(views)))
    gts = []
    for i, v in enumerate(views):
        assert v.image is not None
        gts.append(load_image(v.image, bg_rgb, (v.camera.width, v.camera.height)))
        emit(on_event, Progress("load images", i + 1, len(views)))
    emit(on_event, StageDone("load images", 0.0))

    per_image, secs = _score_views(g, views, gts, bg, on_event, "eval")
    fps = 1.0 / max(secs, 1e-9)
    mean_psnr = _mean_psnr(per_image)
    mean_ssim = float(np.mean([s.ssim for s in per_image]))

    # ---- speed against error at smaller budgets --------------------------------
    budgets = [BudgetPoint(fraction=1.0, num_gaussians=len(g), ply_bytes=ply_bytes(len(g), g.sh_degree),
                           psnr=mean_psnr, ssim=mean_ssim, render_fps=fps, ms_per_frame=1000 * secs)]
    fractions = sorted({float(b) for b in config.budgets if b < 1.0}, reverse=True)
    if fractions:
        rank_views = [v.camera for v in dataset_views(project, "train" if project.splits()["train"] else "all")]
        step = max(1, len(rank_views) // config.contribution_views)
        rank_cams = [eval_size(c, downscale, max_size)
                     for c in rank_views[::step][: config.contribution_views]]
        emit(on_event, Stage("rank Gaussians", total=None))
        t0 = time.perf_counter()
        weight = contributions(g, rank_cams)
        emit(on_event, StageDone("rank Gaussians", time.perf_counter() - t0))
        for f in fractions:
            gp = prune_to(g, weight, f)
            sc, s = _score_views(gp, views, gts, bg, on_event, f"budget {f:.0%}")
            budgets.append(BudgetPoint(fraction=f, num_gaussians=len(gp), ply_bytes=ply_bytes(len(gp), gp.sh_degree),
                                       psnr=_mean_psnr(sc), ssim=float(np.mean([x.ssim for x in sc])),
                                       render_fps=1.0 / max(s, 1e-9), ms_per_frame=1000 * s))
    if 1.0 not in config.budgets:
        budgets = budgets[1:]

    curve = read_training_curve(project.train_log_path) if config.model is None else []
    report = EvalReport(
        psnr=mean_psnr,
        ssim=mean_ssim,
        per_image=per_image,
        num_gaussians=len(g),
        sh_degree=g.sh_degree,
        ply_bytes=ply_bytes(len(g), g.sh_degree),
        train_seconds=float(tsum["train_seconds"]) if isinstance(tsum.get("train_seconds"), (int, float)) else None,
        train_steps=int(tsum["steps"]) if isinstance(tsum.get("steps"), int) else step,
        render_fps=fps,
        device=describe_device(device),
        split=config.split,
        width=views[0].camera.width,
        height=views[0].camera.height,
        step=step,
        model=model_name,
        budgets=budgets,
        training_curve=curve,
        stats=model_stats(g),
        notes=notes,
    )
    for n in notes:
        emit(on_event, Note(n))
    if config.write:
        from .report import NO_PLOTS_HINT, write_plots, write_report_md

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
            project.record_step("eval", config={"split": config.split, "background": list(bg_rgb),
                                                "downscale": downscale, "max_size": max_size,
                                                "budgets": list(config.budgets)},
                                summary=report.summary())
    return report




def evaluate_project(root: str | Path, config: EvalConfig, device: torch.device, *,
                     on_event: EventSink | None = None) -> EvalReport:
    """`splatcli eval PROJECT` in one call: plan, then run."""
    return run_eval(plan_eval(root, config, device), on_event=on_event)


def compare_folders(pred_dir: str | Path, gt_dir: str | Path, *, background: Sequence[float] = (0.0, 0.0, 0.0),
                    on_event: EventSink | None = None) -> FolderReport:
    """PSNR/SSIM of every image in `pred_dir` against the image of the same name
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
    if missing:
        emit(on_event, Note(f"{len(missing)} predictions have no ground truth of the same name: {', '.join(missing[:5])}",
                            "warning"))
    scores = []
    emit(on_event, Stage("compare", total=len(pairs)))
    for i, (p, q) in enumerate(pairs):
        a = load_image(p, background)
        b = load_image(q, background)
        if a.shape != b.shape:
            raise SplatError(f"{p}: size {a.shape[1]}x{a.shape[0]} differs from {q} ({b.shape[1]}x{b.shape[0]})")
        if min(a.shape[0], a.shape[1]) < 11:
            raise SplatError(f"{p}: {a.shape[1]}x{a.shape[0]} is too small for SSIM (at least 11x11)")
        ps, ss = score(a, b)
        scores.append(ImageScore(name=p.name, psnr=ps, ssim=ss))
        emit(on_event, Progress("compare", i + 1, len(pairs)))
    emit(on_event, StageDone("compare", 0.0))
    return FolderReport(psnr=_mean_psnr(scores), ssim=float(np.mean([s.ssim for s in scores])), per_image=scores,
                        pred_dir=pred_dir, gt_dir=gt_dir, missing=missing)
