"""`splatcli eval`: held-out PSNR/SSIM/LPIPS, render speed and speed-against-error curves."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..device import resolve_device
from ..errors import SplatError
from ..eval.evaluate import EvalConfig, compare_folders, plan_eval, run_eval
from ..eval.report import EvalReport, FormatPoint
from ..mesh.measure import MeshReport, score_mesh
from .common import BackgroundOpt, DebugOpt, DeviceOpt, JsonOpt, QuietOpt, RendererOpt, Ui, parse_background, resolve

_D = EvalConfig()  # the defaults, written once in the config


def _budgets(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise SplatError(f"--budgets {text!r}: expected fractions in (0, 1] separated by commas, e.g. 1,0.5,0.25,0.1") from None


def _smaller(f: FormatPoint) -> str:  # the .ply is what the others are measured against
    return "" if f.format == "ply" else f"({f.ratio:4.1f}x smaller than .ply)"


def _lpips(v: float | None, sep: str = ", ") -> str:
    return "" if v is None else f"{sep}LPIPS {v:.4f}"


def _summary(r: EvalReport, geo: MeshReport | None) -> tuple[str, list[str]]:
    """The title line and the lines below it."""
    raw = f"PSNR {r.psnr:.2f} dB, SSIM {r.ssim:.4f}{_lpips(r.lpips)}"
    comp = f"PSNR {r.compensated_psnr:.2f} dB, SSIM {r.compensated_ssim:.4f}{_lpips(r.compensated_lpips)}"
    title = (f"{r.split} split, appearance compensated: {comp} over {len(r.per_image)} views (raw: {raw})"
             if r.headline == "compensated" else f"{r.split} split: {raw} over {len(r.per_image)} views")
    lines = [f"PSNR after a per-view colour fit (exposure and white balance removed): {r.psnr_color_fit:.2f} dB",
             ("appearance compensated: each view's colour fitted on its left half, scored on its right half; "
              "raw: every pixel as rendered" if r.headline == "compensated" else
              f"appearance compensated (colour fitted on each view's left half, scored on its right half): {comp}"),
             f"{r.num_gaussians:,} Gaussians (SH {r.sh_degree}, {r.ply_bytes / 1e6:.2f} MB): "
             f"{r.render_fps:.2f} frames/s at {r.width}x{r.height} on {r.device} ({r.renderer})"]
    lines += [f"masks: scored on {r.masks}"] if r.masks else []
    lines += [f"  {b.fraction:>4.0%}: {b.num_gaussians:>9,} Gaussians  {b.psnr:6.2f} dB  {b.ms_per_frame:8.1f} ms/frame"
              for b in r.budgets]
    lines += [f"  {f.format:>14}: {f.bytes / 1e6:8.2f} MB {_smaller(f):25}  {f.psnr:6.2f} dB ({-f.db_lost:+.2f})"
              for f in r.formats]
    lines += [f"  mesh {k}: Chamfer {s.chamfer:.4g}, F-score {s.fscore:.3f} (precision {s.precision:.3f}, recall "
              f"{s.recall:.3f}) at {s.tau:.3g}" for k, s in ((("fused", geo.fused), ("centres", geo.centres)) if geo else ())]
    lines += [f"report: {r.report_path}"] if r.report_path else []
    return title, lines


def _compare(ui: Ui, pred: Path, gt: Path, bg: tuple[float, float, float] | None, lpips_weights: Path | None,
             device: str) -> None:
    """--pred/--gt: two folders of images compared by file name."""
    with ui.progress() as sink:
        f = compare_folders(pred, gt, background=bg or (0.0, 0.0, 0.0), lpips_weights=lpips_weights,
                            device=resolve_device(device), on_event=sink)
    ui.summary(f.summary(), title=f"{len(f.per_image)} images compared",
               lines=[f"PSNR {f.psnr:.2f} dB   SSIM {f.ssim:.4f}" + _lpips(f.lpips, "   ")])


def evaluate(
    project: Optional[Path] = typer.Argument(None, help="The project directory (omit with --pred/--gt)."),
    split: str = typer.Option(_D.split, "--split", help="Views to score: test (held out), train or all."),
    background: Optional[str] = BackgroundOpt,
    downscale: Optional[float] = typer.Option(None, "--downscale", help="Score at the stored size divided by this (default: as trained)."),
    budgets: str = typer.Option(",".join(f"{b:g}" for b in _D.budgets), "--budgets", help="Fractions of the Gaussians for the render-time curve."),
    plots: bool = typer.Option(_D.plots, "--plots/--no-plots", help="Draw PNG plots beside eval.md (needs matplotlib)."),
    model: Optional[Path] = typer.Option(None, "--model", help="Score this splat file (.ply from any tool, .compressed.ply, .spz, .sog, .splat) instead of the latest checkpoint."),
    formats: str = typer.Option("", "--formats", help="Also write the model as each of these formats (ply, spz, sog, compressed-ply, splat), "
                                "read it back and score it: size against error, in eval.md and eval.json."),
    lpips_weights: Optional[Path] = typer.Option(None, "--lpips-weights", help="torchvision's AlexNet weights (alexnet-owt-7be5be79.pth) for LPIPS "
                                                 "(default: the torch hub cache, $TORCH_HOME/hub/checkpoints; never downloaded). "
                                                 "Without them, or without the lpips extra, LPIPS is left out."),
    antialias: str = typer.Option(_D.antialias, "--antialias", help="auto | on | off: draw with the 2D antialiasing filter. "
                                  "auto: on for a model trained with --mip-filter or drawn smaller than trained (zoomed in it only blurs)."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Folder for eval.json, eval.md and plots (default PROJECT/reports)."),
    pred: Optional[Path] = typer.Option(None, "--pred", help="Compare this folder of images ..."),
    gt: Optional[Path] = typer.Option(None, "--gt", help="... with this one, by file name (no project needed)."),
    mesh: Optional[Path] = typer.Option(None, "--mesh", help="Also score PROJECT/exports/mesh.ply (export --format mesh) "
                                        "and a naive mesh of the Gaussian centres against this reference surface (.ply: "
                                        "points or triangles, in the project's frame): Chamfer distance and F-score at 1% "
                                        "of its size; written to reports/mesh.json."),
    device: str = DeviceOpt,
    renderer: str = RendererOpt,
    quiet: bool = QuietOpt,
    json_out: bool = JsonOpt,
    debug: bool = DebugOpt,
) -> None:
    """Score renders against held-out photographs and write reports/eval.json and eval.md."""
    ui = Ui(quiet=quiet, json_out=json_out)
    bg = parse_background(background)
    if pred is not None or gt is not None:
        if pred is None or gt is None or project is not None:
            raise SplatError("--pred and --gt go together, without a project")
        _compare(ui, pred, gt, bg, lpips_weights, device)
        return
    if project is None:
        raise SplatError("give a PROJECT, or --pred DIR --gt DIR")
    cfg = EvalConfig(split=split, background=bg, downscale=downscale, budgets=_budgets(budgets), plots=plots,
                     model=model, out=out, formats=tuple(f.strip().lower() for f in formats.split(",") if f.strip()),
                     lpips_weights=lpips_weights, antialias=antialias.strip().lower(), renderer=renderer)
    plan = plan_eval(project, cfg, resolve(device, renderer, quiet)[0])  # input errors surface before any output
    with ui.progress() as sink:
        r = run_eval(plan, on_event=sink)
    geo = score_mesh(project, mesh) if mesh is not None else None  # mesh/measure.py
    title, lines = _summary(r, geo)
    ui.summary(r.summary() | ({"mesh": geo.to_json()} if geo else {}), title=title, lines=lines)
