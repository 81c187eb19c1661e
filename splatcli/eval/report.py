"""The human eval report: reports/eval.md and the PNG plots beside it.

Plots need matplotlib (the `plots` extra). Without it the report is written
all the same, with a line saying how to get the plots. Figures are drawn with
the object-oriented API on an Agg canvas: no pyplot global state, no display.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from ..io.atomic import atomic_path

if TYPE_CHECKING:
    from .evaluate import EvalReport
    from ..project import Project

PLOTS = ("speed_vs_error", "scales", "opacities", "sh_degrees")
NO_PLOTS_HINT = "plots skipped: matplotlib is not installed (pip install 'splatcli[plots]')"


def _figure(width: float = 6.0, height: float = 4.0):
    """A fresh figure on an Agg canvas; raises ImportError without matplotlib."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=100)
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path: Path) -> None:
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")


def write_plots(report: "EvalReport", project: "Project", out_dir: Path) -> list[str] | None:
    """Draw the plots into `out_dir` (named as the project names them); returns
    their file names, or None when matplotlib is absent."""
    path = lambda name: out_dir / project.plot_path(name).name  # noqa: E731
    try:
        fig = _figure(11, 4)
    except ImportError:
        return None
    names = []

    # ---- speed against error ---------------------------------------------------
    ax1, ax2 = fig.subplots(1, 2)
    curve = report.training_curve
    if curve:
        ax1.plot([p.elapsed_s for p in curve], [p.psnr for p in curve], "o-", label="held-out PSNR while training")
    if report.train_seconds is not None:
        ax1.plot([report.train_seconds], [report.psnr], "s", color="C3", label="final (eval)")
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
    _save(fig, path("speed_vs_error"))
    names.append(path("speed_vs_error").name)

    st = report.stats
    if st is not None:
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
            _save(fig, path(name))
            names.append(path(name).name)

        fig = _figure(5, 3.5)
        ax = fig.subplots()
        ax.bar([str(d) for d in range(len(st.sh_degree_counts))], st.sh_degree_counts)
        ax.set_xlabel("highest SH degree used")
        ax.set_ylabel("Gaussians")
        ax.set_title("SH degree actually used")
        _save(fig, path("sh_degrees"))
        names.append(path("sh_degrees").name)
    return names


def _mb(n: int) -> str:
    return f"{n / 1e6:.2f} MB"


def _opt(v, fmt: str) -> str:
    return "n/a" if v is None else format(v, fmt)


def write_report_md(report: "EvalReport", project: "Project") -> str:
    """The Markdown report (returned; the caller writes it atomically)."""
    from .evaluate import SH_USED_TOL

    r = report
    lines = [
        f"# Evaluation of `{project.root.name}`",
        "",
        f"Model: {r.model}. {r.split[0].upper() + r.split[1:]} split ({len(r.per_image)} views at {r.width}x{r.height}), "
        f"rendered on {r.device}.",
        "",
        "## Summary",
        "",
        "| metric | value |",
        "| --- | --- |",
        f"| PSNR (mean over views) | {r.psnr:.2f} dB |",
        f"| SSIM | {r.ssim:.4f} |",
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
    if "speed_vs_error.png" in r.plots:
        lines += ["![speed against error](speed_vs_error.png)", ""]
    if r.budgets:
        lines += [
            "What a smaller model costs: the least-contributing Gaussians (smallest total blending weight over "
            "the training views) are pruned, without fine-tuning, and the held-out views rendered again.",
            "",
            "| budget | Gaussians | .ply size | PSNR (dB) | SSIM | ms/frame | frames/s |",
            "| --- | --- | --- | --- | --- | --- | --- |",
        ]
        for b in sorted(r.budgets, key=lambda p: -p.fraction):
            lines.append(f"| {b.fraction:.0%} | {b.num_gaussians:,} | {_mb(b.ply_bytes)} | {b.psnr:.2f} | "
                         f"{b.ssim:.4f} | {b.ms_per_frame:.1f} | {b.render_fps:.2f} |")
        lines.append("")
    if r.training_curve:
        lines += ["Held-out PSNR while training (reports/train_log.jsonl):", "",
                  "| step | training time (s) | PSNR (dB) | SSIM | Gaussians |", "| --- | --- | --- | --- | --- |"]
        for p in r.training_curve:
            lines.append(f"| {p.step} | {p.elapsed_s:.1f} | {p.psnr:.2f} | {_opt(p.ssim, '.4f')} | "
                         f"{_opt(p.num_gaussians, ',')} |")
        lines.append("")
    else:
        lines += ["No held-out PSNR was logged during training (reports/train_log.jsonl).", ""]

    lines += ["## Worst five views", "", "| view | PSNR (dB) | SSIM |", "| --- | --- | --- |"]
    for s in r.worst(5):
        lines.append(f"| {s.name} | {s.psnr:.2f} | {s.ssim:.4f} |")
    lines.append("")

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
    lines += ["## All views", "", "| view | PSNR (dB) | SSIM |", "| --- | --- | --- |"]
    lines += [f"| {s.name} | {s.psnr:.2f} | {s.ssim:.4f} |" for s in r.per_image]
    lines.append("")
    return "\n".join(lines)
