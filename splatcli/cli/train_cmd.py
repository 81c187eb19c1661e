"""`splatcli train`: optimise Gaussians on a processed project; options from TrainConfig's fields (cli/options.py)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, Optional

import typer

from ..options import RUN
from ..project import Project
from ..train.config import TrainConfig
from ..train.distributed import in_worker, join
from ..train.launch import launch
from ..train.loop import train as run_train
from .common import DebugOpt, DeviceOpt, JsonOpt, QuietOpt, RendererOpt, Ui, resolve
from .options import GIVEN, config_options
from .planning import chosen_line
from .train_config import configure, preset_options
from .view_cmd import live_viewer


@config_options(TrainConfig, preset_options())
def train(
    project: Path = typer.Argument(..., help="The project directory made by `splatcli process`."),
    resume: bool = typer.Option(False, "--resume", rich_help_panel=RUN, help="Continue from the latest checkpoint (its settings; options given here override)."),
    nproc: Optional[int] = typer.Option(None, "--nproc", rich_help_panel=RUN, help="Train with this many processes on this machine (data-parallel over views, one torch thread each, through torch's elastic launcher): each step sees that many views, and the schedule is scaled so that the run sees as many images as one process (docs/guide.md)."),
    port: int = typer.Option(0, "--port", rich_help_panel=RUN, help="With --nproc: the loopback port the processes meet on (default: a free one)."),
    viewer: bool = typer.Option(False, "--viewer", rich_help_panel=RUN, help="Serve a live web viewer of the model while it trains (as `splatcli view`; refreshed every 3 s while a page is open, with the step, loss and held-out PSNR)."),
    viewer_host: str = typer.Option("127.0.0.1", "--viewer-host", rich_help_panel=RUN, help="With --viewer: the address to serve on."),
    viewer_port: Optional[int] = typer.Option(None, "--viewer-port", rich_help_panel=RUN, help="With --viewer: the port (default 7007, or the next free one)."),
    device: str = DeviceOpt,
    renderer: str = RendererOpt,
    quiet: bool = QuietOpt,
    json_out: bool = JsonOpt,
    debug: bool = DebugOpt,
    given: dict[str, Any] = GIVEN,
) -> None:
    """Fit 3D Gaussians to the training views; checkpoints go to PROJECT/checkpoints, the speed/error log to PROJECT/reports/train_log.jsonl. Ctrl-C saves a checkpoint (exit 130)."""
    dev, drawer = resolve(device, renderer, quiet)
    (proj := Project.open(project)).require_processed()  # input errors before the progress display starts
    cfg, chosen = configure(proj, given, nproc, dev, drawer.name, resume)  # cli/planning.py chooses; given options win
    for line, level in ((drawer.note, "warning"), (chosen_line(chosen, cfg, resume), "note")):
        if line and not in_worker():
            Ui(quiet=quiet).note(line, level)
    if chosen.nproc is not None and not in_worker():  # K copies of this command, sent the config; rank 0 reports
        return launch(sys.argv[1:], chosen.nproc, port, project, dev, chosen.env(cfg))
    comm = join(dev)  # under torchrun: this process's rank (else a single process)
    ui = Ui(quiet=quiet or not comm.main, json_out=json_out and comm.main)
    try:
        with ui.progress() as sink, live_viewer(ui, project, viewer and comm.main, viewer_host, viewer_port, sink) as sink:
            s = run_train(project, cfg, dev, resume=resume, on_event=sink,
                          comm=comm, chosen=chosen.record())
    finally:
        comm.close()  # on every path: gloo's threads must be gone before the interpreter exits
    how = " (appearance compensated)" if s.protocol == "compensated" else ""
    psnr = f", held-out PSNR {s.psnr:.2f} dB{how}" if s.psnr is not None else ""
    ui.summary(s.to_json(), title=f"trained {s.steps} steps in {s.train_seconds:.0f} s{psnr}",
               lines=[s.model_line(), f"checkpoint: {s.checkpoint}"])
