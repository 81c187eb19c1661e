"""`splatcli train`: optimise Gaussians on a processed project (3DGS recipe)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

import typer

from ..device import resolve_device
from ..project import Project
from ..train.distributed import in_worker, join
from ..train.launch import launch
from ..train.loop import train as run_train
from ..train.config import PRESETS, TrainConfig, make_config, option
from .common import DebugOpt, DeviceOpt, JsonOpt, QuietOpt, SeedOpt, Ui
from .view_cmd import live_viewer

_D = TrainConfig()  # the defaults, written once in the config


def train(
    project: Path = typer.Argument(..., help="The project directory made by `splatcli process`."),
    preset: str = typer.Option(_D.preset, "--preset", help=f"{' | '.join(PRESETS)}: default = the paper's 30k steps; "
                               "fast = 7k steps, densify to 4k with no opacity reset, the first half at a resolution rising from 1/4 (CPU: less time per step early, "
                               "at the cost of fine detail learnt later); demo = a few minutes (make demo)."),
    iterations: Optional[int] = typer.Option(None, "--iterations", "-n", help=f"Optimiser steps (default {_D.iterations}; the preset may change it)."),
    sh_degree: Optional[str] = typer.Option(None, "--sh-degree", help=f"0-3, or auto: the lowest degree within {_D.sh_auto.tol_db} dB of 3 on training views (default {_D.sh_degree})."),
    max_gaussians: Optional[int] = typer.Option(None, "--max-gaussians", help="Hard budget; growth goes to the highest gradients first (with --strategy mcmc: the count it grows to)."),
    strategy: Optional[str] = typer.Option(None, "--strategy", help=f"Density control: default = 3DGS's clone/split/prune; mcmc = a fixed budget "
                                           f"(--max-gaussians), grown at least {_D.mcmc.growth:.0%} per refinement and to the cap by {_D.mcmc.grow_until:.0%} of the refinement window, dead Gaussians moved onto live ones, "
                                           "noise on nearly transparent ones, opacity and scale penalties (Kheradmand et al. 2024)."),
    init_far: Optional[int] = typer.Option(None, "--init-far", help=f"Also start with Gaussians on a sphere {_D.init_far_radius:g}x the cameras' extent away, this many over the whole sphere (those a training view sees are kept, coloured from it): a backdrop that structure from motion left empty gets a far depth instead of floaters (default {_D.init_far}: off)."),
    prune_views: Optional[int] = typer.Option(None, "--prune-views", help=f"While densifying, prune Gaussians that fewer than this many training views see (they can only explain those photos: floaters elsewhere; default {_D.support.prune_views}: off)."),
    opacity_reset: Optional[int] = typer.Option(None, "--opacity-reset", help=f"While densifying, lower every opacity to {_D.strategy.reset_opacity} every this many steps, as 3DGS does against floaters near the cameras; Gaussians that are too large are pruned only after the first (default {_D.strategy.reset_every}, the preset may change it; 0: never, and no size pruning)."),
    opacity_reg: Optional[float] = typer.Option(None, "--opacity-reg", help=f"Add this x the mean opacity to the loss: unneeded Gaussians fade and are pruned (default {_D.reg.opacity_reg}: off; mcmc has its own {_D.mcmc.opacity_reg})."),
    scale_reg: Optional[float] = typer.Option(None, "--scale-reg", help=f"Add this x the mean scale (world units) to the loss: Gaussians stay small (default {_D.reg.scale_reg}: off; mcmc has its own {_D.mcmc.scale_reg})."),
    mask_mode: Optional[str] = typer.Option(None, "--mask-mode", help=f"What the project's masks do (default {_D.mask_mode}): ignore = masked pixels take no part in the "
                                            "loss (people, moving objects); background = they are trained to the background colour (object captures); "
                                            "off = masks unused; auto = background for masks from an alpha channel, ignore for mask files."),
    appearance: Optional[str] = typer.Option(None, "--appearance", help=f"none | exposure: exposure learns one colour transform "
                                             "(a 3x3 matrix and an offset) per training photo, pulled towards the identity, for captures whose "
                                             "exposure or white balance varies; what varies smoothly from camera to camera is left to the scene "
                                             "(held-out views between them see it); held-out views, eval and exported files use the scene alone "
                                             f"(default {_D.appearance})."),
    compact: bool = typer.Option(False, "--compact", help=f"After training, keep {_D.compact.keep:.0%} of the Gaussians, those with the most blending weight (cut in {_D.compact.rounds} rounds), while fine-tuning {_D.compact.finetune} more steps."),
    mip_filter: bool = typer.Option(_D.mip_filter, "--mip-filter", help="Mip-Splatting's filters (Yu et al. 2024): no Gaussian "
                                    "finer than the training views sample it (a 3D filter, folded into the exported scales and "
                                    "opacities), drawn with the 2D antialiasing filter: renders at other resolutions keep their look."),
    downscale: Optional[float] = typer.Option(None, "--downscale", help="Train at the image size divided by this."),
    max_size: Optional[int] = typer.Option(None, "--max-size", help=f"Cap the longest image side at this (pixels; default {_D.max_size})."),
    checkpoint_every: Optional[int] = typer.Option(None, "--checkpoint-every", help=f"Write a checkpoint every this many steps (default {_D.checkpoint_every}; also at the end and on Ctrl-C)."),
    keep_checkpoints: Optional[int] = typer.Option(None, "--keep-checkpoints", help=f"Keep the newest this many checkpoints (default {_D.keep_checkpoints})."),
    eval_every: Optional[int] = typer.Option(None, "--eval-every", help="Held-out PSNR/SSIM every this many steps (0: at the end)."),
    time_budget: Optional[float] = typer.Option(None, "--time-budget", help="Training seconds to fit in: the run measures its speed and plans the preset's schedule, compressed, to end within them (evaluation not counted)."),
    resume: bool = typer.Option(False, "--resume", help="Continue from the latest checkpoint (its settings; options given here override)."),
    init_ply: Optional[Path] = typer.Option(None, "--init-ply", help="Start from a splat file (.ply, .spz, .sog, .compressed.ply, .splat) instead of the SfM/random points."),
    nproc: Optional[int] = typer.Option(None, "--nproc", help="Train with this many processes on this machine (data-parallel over views, "
                                        "one torch thread each, through torch's elastic launcher): each step sees that many views, and the "
                                        "schedule is scaled so that the run sees as many images as one process (docs/guide.md)."),
    port: int = typer.Option(0, "--port", help="With --nproc: the loopback port the processes meet on (default: a free one)."),
    viewer: bool = typer.Option(False, "--viewer", help="Serve a live web viewer of the model while it trains (as `splatcli "
                                "view`; refreshed every 3 s while a page is open, with the step, loss and held-out PSNR)."),
    viewer_host: str = typer.Option("127.0.0.1", "--viewer-host", help="With --viewer: the address to serve on."),
    viewer_port: Optional[int] = typer.Option(None, "--viewer-port", help="With --viewer: the port (default 7007, or the next free one)."),
    device: str = DeviceOpt,
    seed: int = SeedOpt,
    quiet: bool = QuietOpt,
    json_out: bool = JsonOpt,
    debug: bool = DebugOpt,
) -> None:
    """Fit 3D Gaussians to the training views; checkpoints go to PROJECT/checkpoints, the
    speed/error log to PROJECT/reports/train_log.jsonl. Ctrl-C saves a checkpoint (exit 130)."""
    ui = Ui(quiet=quiet, json_out=json_out)
    dev = resolve_device(device)
    given = dict(iterations=iterations, sh_degree=sh_degree, max_gaussians=max_gaussians, compact=compact or None,
                 density=strategy.strip().lower() if strategy else None, opacity_reg=opacity_reg, scale_reg=scale_reg,
                 init_far=init_far, prune_views=prune_views, reset_every=opacity_reset, checkpoint_every=checkpoint_every,
                 keep_checkpoints=keep_checkpoints,
                 mip_filter=mip_filter or None,
                 mask_mode=mask_mode.strip().lower() if mask_mode else None,
                 appearance=appearance.strip().lower() if appearance else None,
                 downscale=downscale, max_size=max_size, eval_every=eval_every, time_budget=time_budget,
                 init_ply=str(init_ply) if init_ply else None)
    cfg = make_config(preset, seed=seed, device=str(dev), **given)
    overrides = {k: option(cfg, k) for k, v in given.items() if v is not None}
    Project.open(project).require_processed()  # input errors before the progress display starts
    if nproc is not None and not in_worker():
        return launch(sys.argv[1:], nproc, port, project, dev)  # K copies of this command; rank 0 reports
    comm = join(dev)  # under torchrun: this process's rank (else a single process)
    ui = Ui(quiet=quiet or not comm.main, json_out=json_out and comm.main)
    try:
        with ui.progress() as sink, live_viewer(ui, project, viewer and comm.main, viewer_host, viewer_port, sink) as sink:
            s = run_train(project, cfg, dev, resume=resume, overrides=overrides, on_event=sink, comm=comm)
    finally:
        comm.close()  # on every path: gloo's threads must be gone before the interpreter exits
    psnr = f", held-out PSNR {s.psnr:.2f} dB" if s.psnr is not None else ""
    ui.summary(s.to_json(), title=f"trained {s.steps} steps in {s.train_seconds:.0f} s{psnr}",
               lines=[f"{s.num_gaussians} Gaussians, SH degree {s.sh_degree}, .ply {s.ply_bytes / 1e6:.2f} MB",
                      f"checkpoint: {s.checkpoint}"])
