"""What eval reports: the typed report (eval.json), the model's statistics, and the
human report: reports/eval.md and the PNG plots beside it.

Plots need matplotlib (the `plots` extra). Without it the report is written
all the same, with a line saying how to get the plots. Figures are drawn with
the object-oriented API on an Agg canvas: no pyplot global state, no display.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..files.atomic import atomic_path
from ..gaussians import Gaussians, Histogram, histogram
from ..project import Project
from .curve import CurvePoint
from .score import REPORTED

QUANTISATION_WORDS = {  # eval.md's word for each quantisation (eval/score.py)
    "8-bit": "8-bit renders, as saved to PNG",
    "none": "unquantised renders (clamped to [0, 1])",
}
SH_USED_TOL = 0.01  # a band is "used" when some coefficient moves colour by > 1% (SH value x basis ~ coefficient)


@dataclass
class ImageScore:
    name: str
    psnr: float  # dB
    ssim: float
    lpips: float | None = None  # AlexNet LPIPS (eval/lpips.py); None when unavailable
    psnr_color_fit: float | None = None  # dB after the view's least-squares colour fit (metrics.color_fit)
    # the appearance-compensated protocol (COMPENSATED): the view's right half, its colours fitted on the left
    compensated_psnr: float | None = None
    compensated_ssim: float | None = None
    compensated_lpips: float | None = None


# The protocol of photo-collection papers (NeRF-W and the Gaussian methods after it), named in eval.json and eval.md
COMPENSATED = ("appearance compensated: each view's colour transform (3x3 and offset, what --appearance exposure "
               "learns) fitted on its left half, PSNR/SSIM/LPIPS on its right half")


@dataclass
class BudgetPoint:
    fraction: float  # of the Gaussians kept
    num_gaussians: int
    ply_bytes: int
    psnr: float
    ssim: float
    render_fps: float
    ms_per_frame: float
    lpips: float | None = None


@dataclass
class FormatPoint:
    """One file format: the model encoded, decoded by our reader, and scored (eval --formats)."""

    format: str
    bytes: int
    bytes_per_gaussian: float
    ratio: float  # .ply bytes / these bytes
    psnr: float
    ssim: float
    db_lost: float  # full precision's PSNR minus this one
    encode_s: float
    decode_s: float
    lpips: float | None = None


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
    lpips: float | None = None  # mean over the split; None when LPIPS is unavailable (a note says why)
    masks: str | None = None  # how the project's masks entered the scores (None: no masks)
    quantisation: str = REPORTED  # renders as scored (eval/score.py): "8-bit" as saved to PNG, or "none"
    renderer: str = "torch"  # what drew the renders: torch (the PyTorch path) or gsplat
    curve_quantisation: str | None = None  # the same for training_curve (train.json's summary; None: no curve)
    curve_protocol: str | None = None  # training_curve's protocol: raw, or compensated (train.json's summary)
    psnr_color_fit: float | None = None  # mean over views of the PSNR after each view's colour fit (metrics.color_fit)
    compensated_psnr: float | None = None  # means over views under COMPENSATED
    compensated_ssim: float | None = None
    compensated_lpips: float | None = None
    # which score leads: "raw", or "compensated" where training learnt each photo's appearance
    # (--appearance exposure: no model of the other photos can predict a held-out photo's light)
    headline: str = "raw"
    budgets: list[BudgetPoint] = field(default_factory=list)
    formats: list[FormatPoint] = field(default_factory=list)  # size against error, by file format
    training_curve: list[CurvePoint] = field(default_factory=list)
    stats: ModelStats | None = None
    plots: list[str] = field(default_factory=list)  # file names beside eval.md
    notes: list[str] = field(default_factory=list)
    report_path: Path | None = None  # eval.md, when written

    def worst(self, k: int = 5) -> list[ImageScore]:
        return sorted(self.per_image, key=lambda s: s.psnr)[:k]

    def summary(self) -> dict[str, Any]:
        """The headline numbers (what `--json` prints)."""
        return {k: getattr(self, k) for k in ("psnr", "ssim", "lpips", "num_gaussians", "sh_degree", "ply_bytes",
                                              "train_seconds", "train_steps", "render_fps", "device", "renderer", "split",
                                              "width", "height", "step", "model", "masks", "quantisation",
                                              "psnr_color_fit", "compensated_psnr", "compensated_ssim",
                                              "compensated_lpips", "headline")} | {
            "num_images": len(self.per_image), "compensated_protocol": COMPENSATED}

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        return {**self.summary(), **{k: d[k] for k in ("per_image", "budgets", "formats", "training_curve", "stats",
                                                       "plots", "notes", "curve_quantisation",
                                                       "curve_protocol")}}


def used_sh_degree(sh: Tensor) -> Tensor:  # [N, K, 3] -> [N] int
    """Highest band with a coefficient larger than SH_USED_TOL (0 when only DC)."""
    d = int(round(math.sqrt(sh.shape[1]))) - 1
    used = torch.zeros(sh.shape[0], dtype=torch.long, device=sh.device)
    for l in range(1, d + 1):
        band = sh[:, l * l:(l + 1) * (l + 1), :].abs().amax(dim=(1, 2))
        used = torch.where(band > SH_USED_TOL, torch.full_like(used, l), used)
    return used


def model_stats(g: Gaussians, bins: int = 40) -> ModelStats:
    ls = (g.log_scales.detach().to(torch.float64).cpu().numpy() / math.log(10)).ravel()
    op = torch.sigmoid(g.opacity_logits.detach().to(torch.float64)).cpu().numpy()
    ls = ls[np.isfinite(ls)]
    used = used_sh_degree(g.sh.detach()).cpu().numpy()
    counts = [int((used == l).sum()) for l in range(g.sh_degree + 1)]
    return ModelStats(
        log10_scale_hist=histogram(ls, bins),
        opacity_hist=histogram(op, bins, range_=(0.0, 1.0)),
        sh_degree_counts=counts,
        median_scale=float(10 ** np.median(ls)) if ls.size else float("nan"),
        median_opacity=float(np.median(op)) if op.size else float("nan"),
    )



NO_PLOTS_HINT = "plots skipped: matplotlib is not installed (pip install 'splatcli[plots]')"


def _figure(width: float = 6.0, height: float = 4.0):
    """A fresh figure on an Agg canvas; raises ImportError without matplotlib."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=100)
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path: Path) -> str:
    """Write `fig` as a PNG at `path`; returns the file's name."""
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return path.name


def _plot_speed(fig: Any, report: EvalReport) -> None:  # fig: a matplotlib Figure
    """Held-out PSNR against training time (left), and against render time at each budget (right)."""
    ax1, ax2 = fig.subplots(1, 2)
    curve = report.training_curve
    if curve:
        comp = " (compensated)" if report.curve_protocol == "compensated" else ""
        ax1.plot([p.elapsed_s for p in curve], [p.psnr for p in curve], "o-", label=f"held-out PSNR while training{comp}")
    if report.train_seconds is not None:
        final = report.compensated_psnr if report.curve_protocol == "compensated" else report.psnr
        ax1.plot([report.train_seconds], [final], "s", color="C3", label="final (eval)")
    ax1.set_xlabel("training time (s)")
    ax1.set_ylabel("PSNR (dB)")
    ax1.set_title("error against training time")
    ax1.grid(alpha=0.3)
    if curve or report.train_seconds is not None:
        ax1.legend(fontsize=8)
    b = sorted(report.budgets, key=lambda p: p.fraction)
    if b:
        ax2.plot([p.ms_per_frame for p in b], [p.psnr for p in b], "o-")
        right = max(p.ms_per_frame for p in b)
        for p in b:  # the rightmost label goes above-left of its point, inside the axes
            last = p.ms_per_frame == right
            ax2.annotate(f"{p.fraction:.0%} ({p.num_gaussians:,})", (p.ms_per_frame, p.psnr),
                         textcoords="offset points", xytext=(-4, 6) if last else (4, -10), fontsize=8,
                         ha="right" if last else "left")
    ax2.set_xlabel(f"render time per frame (ms, {report.device})")
    ax2.set_ylabel("PSNR (dB)")
    ax2.set_title("error against render time, by Gaussian budget")
    ax2.grid(alpha=0.3)


def _plot_formats(ax: Any, report: EvalReport) -> None:  # ax: a matplotlib Axes
    """Held-out PSNR against file size, by format."""
    for p in report.formats:
        ax.plot([p.bytes / 1e6], [p.psnr], "o")
        ax.annotate(f"{p.format} ({p.ratio:.1f}x)", (p.bytes / 1e6, p.psnr), textcoords="offset points",
                    xytext=(4, 4), fontsize=8)
    ax.set_xscale("log")
    ax.set_xlabel("file size (MB, log scale)")
    ax.set_ylabel("held-out PSNR (dB)")
    ax.set_title("size against error, by file format")
    ax.grid(alpha=0.3)


def _plot_stats(st: ModelStats, save: Callable[[Any, str], str]) -> list[str]:
    """Histograms of the scales and opacities, and the SH degrees used."""
    names = []
    for name, h, xlabel, title in (
        ("scales", st.log10_scale_hist, "log10 scale (world units, all three axes)",
         f"Gaussian scales (median {st.median_scale:.3g})"),
        ("opacities", st.opacity_hist, "opacity", f"Gaussian opacities (median {st.median_opacity:.2f})"),
    ):
        fig = _figure()
        ax = fig.subplots()
        ax.stairs(h.counts, h.edges, fill=True)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("count")
        ax.set_title(title)
        names.append(save(fig, name))
    fig = _figure(5, 3.5)
    ax = fig.subplots()
    ax.bar([str(d) for d in range(len(st.sh_degree_counts))], st.sh_degree_counts)
    ax.set_xlabel("highest SH degree used")
    ax.set_ylabel("Gaussians")
    ax.set_title("SH degree actually used")
    names.append(save(fig, "sh_degrees"))
    return names


def write_plots(report: EvalReport, project: Project, out_dir: Path) -> list[str] | None:
    """Draw the plots into `out_dir` (named as the project names them); returns
    their file names, or None when matplotlib is absent."""
    def save(fig: Any, name: str) -> str:
        return _save(fig, out_dir / project.plot_path(name).name)

    try:
        fig = _figure(11, 4)
    except ImportError:
        return None
    _plot_speed(fig, report)
    names = [save(fig, "speed_vs_error")]
    if report.formats:
        fig = _figure(6, 4)
        _plot_formats(fig.subplots(), report)
        names.append(save(fig, "formats"))
    if report.stats is not None:
        names += _plot_stats(report.stats, save)
    return names


def _mb(n: int) -> str:
    return f"{n / 1e6:.2f} MB"


def _opt(v, fmt: str) -> str:
    return "n/a" if v is None else format(v, fmt)


def _lp(v: float | None) -> str:
    return "—" if v is None else f"{v:.4f}"


def _md_summary(r: EvalReport, project: Project) -> list[str]:
    """The title, what was scored, and the summary table."""
    return [
        f"# Evaluation of `{project.root.name}`",
        "",
        f"Model: {r.model}. {r.split[0].upper() + r.split[1:]} split ({len(r.per_image)} views at {r.width}x{r.height}), "
        f"rendered on {r.device} by the {r.renderer} renderer.",
        "",
        f"Scores: {QUANTISATION_WORDS.get(r.quantisation, r.quantisation)}.",
        "",
        *([f"Masks: scored on {r.masks}.", ""] if r.masks else []),
        "## Summary",
        "",
        *([f"Headline: the appearance-compensated score ({COMPENSATED}), because training learnt each photo's "
           "appearance (--appearance exposure), which no model of the other photos can predict for a held-out "
           "photo; the raw score is beside it.", ""] if r.headline == "compensated" else []),
        "| metric | value |",
        "| --- | --- |",
        f"| PSNR (mean over views) | {r.psnr:.2f} dB |",
        f"| SSIM | {r.ssim:.4f} |",
        f"| LPIPS (AlexNet) | {_lp(r.lpips)} |",
        *([f"| PSNR after a per-view colour fit (exposure and white balance removed) | {r.psnr_color_fit:.2f} dB |"]
          if r.psnr_color_fit is not None else []),
        *([f"| PSNR / SSIM / LPIPS, {COMPENSATED} | {r.compensated_psnr:.2f} dB / {r.compensated_ssim:.4f} / "
           f"{_lp(r.compensated_lpips)} |"] if r.compensated_psnr is not None else []),
        f"| Gaussians | {r.num_gaussians:,} |",
        f"| SH degree | {r.sh_degree} |",
        f"| .ply size | {_mb(r.ply_bytes)} |",
        f"| training time | {_opt(r.train_seconds, '.1f')} s |",
        f"| training steps | {_opt(r.train_steps, 'd')} |",
        f"| render speed | {r.render_fps:.2f} frames/s |",
        "",
        "## Speed against error",
        "",
    ]


def _md_budgets(r: EvalReport) -> list[str]:
    """Speed against error: the model pruned to smaller budgets."""
    lines = ["![speed against error](speed_vs_error.png)", ""] if "speed_vs_error.png" in r.plots else []
    if r.budgets:
        lines += [
            "What a smaller model costs: the least-contributing Gaussians (smallest total blending weight over "
            "the training views) are pruned, without fine-tuning, and the held-out views rendered again.",
            "",
            "| budget | Gaussians | .ply size | PSNR (dB) | SSIM | LPIPS | ms/frame | frames/s |",
            "| --- | --- | --- | --- | --- | --- | --- | --- |",
            *(f"| {b.fraction:.0%} | {b.num_gaussians:,} | {_mb(b.ply_bytes)} | {b.psnr:.2f} | "
              f"{b.ssim:.4f} | {_lp(b.lpips)} | {b.ms_per_frame:.1f} | {b.render_fps:.2f} |"
              for b in sorted(r.budgets, key=lambda p: -p.fraction)),
            "",
        ]
    return lines


def _md_formats(r: EvalReport) -> list[str]:
    """Size against error, by file format."""
    if not r.formats:
        return []
    return ["## Size against error, by file format", "",
            *(["![size against error](formats.png)", ""] if "formats.png" in r.plots else []),
            "The model written in each format, read back by splatcli's reader and scored on the same views "
            "(*lost*: dB below full precision).", "",
            "| format | size | bytes/Gaussian | smaller than .ply | PSNR (dB) | SSIM | LPIPS | lost (dB) | encode s "
            "| decode s |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
            *(f"| {p.format} | {_mb(p.bytes)} | {p.bytes_per_gaussian:.1f} | {p.ratio:.1f}x | {p.psnr:.2f} | "
              f"{p.ssim:.4f} | {_lp(p.lpips)} | {p.db_lost:.2f} | {p.encode_s:.2f} | {p.decode_s:.2f} |"
              for p in r.formats),
            ""]


def _md_curve(r: EvalReport) -> list[str]:
    """Held-out PSNR while training, from the log."""
    if not r.training_curve:
        return ["No held-out PSNR was logged during training (reports/train_log.jsonl).", ""]
    q = QUANTISATION_WORDS.get(r.curve_quantisation or "", r.curve_quantisation)
    how = f"{q}; appearance compensated" if r.curve_protocol == "compensated" else q
    return [f"Held-out PSNR while training (reports/train_log.jsonl; {how}):", "",
            "| step | training time (s) | PSNR (dB) | SSIM | Gaussians |", "| --- | --- | --- | --- | --- |",
            *(f"| {p.step} | {p.elapsed_s:.1f} | {p.psnr:.2f} | {_opt(p.ssim, '.4f')} | {_opt(p.num_gaussians, ',')} |"
              for p in r.training_curve),
            ""]


def _md_views(r: EvalReport) -> list[str]:
    """The worst five views, the model's statistics, the notes, and every view."""
    lines = ["## Worst five views", "", "| view | PSNR (dB) | SSIM | LPIPS |", "| --- | --- | --- | --- |"]
    lines += [f"| {s.name} | {s.psnr:.2f} | {s.ssim:.4f} | {_lp(s.lpips)} |" for s in r.worst(5)] + [""]

    st = r.stats
    if st is not None:
        lines += ["## Model statistics", ""]
        for name, title in (("scales.png", "scales"), ("opacities.png", "opacities"), ("sh_degrees.png", "SH degrees")):
            if name in r.plots:
                lines += [f"![{title}]({name})", ""]
        lines += [f"Median scale {st.median_scale:.3g} world units, median opacity {st.median_opacity:.2f}.", "",
                  f"Highest SH degree actually used (a coefficient above {SH_USED_TOL}):", "",
                  "| degree | Gaussians |", "| --- | --- |"]
        lines += [f"| {d} | {c:,} |" for d, c in enumerate(st.sh_degree_counts)]
        lines.append("")
    for n in r.notes:
        lines += [f"Note: {n}", ""]
    lines += ["## All views", "", "| view | PSNR (dB) | SSIM | LPIPS | PSNR after colour fit (dB) | "
              "compensated PSNR (dB) |", "| --- | --- | --- | --- | --- | --- |"]
    lines += [f"| {s.name} | {s.psnr:.2f} | {s.ssim:.4f} | {_lp(s.lpips)} | {_opt(s.psnr_color_fit, '.2f')} | "
              f"{_opt(s.compensated_psnr, '.2f')} |" for s in r.per_image]
    lines.append("")
    return lines


def write_report_md(report: EvalReport, project: Project) -> str:
    """The Markdown report (returned; the caller writes it atomically)."""
    r = report
    parts = [_md_summary(r, project), _md_budgets(r), _md_formats(r), _md_curve(r), _md_views(r)]
    return "\n".join(line for part in parts for line in part)
