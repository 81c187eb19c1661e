"""What every command shares: options, the console, progress display, summaries.

Human output (progress, notes, tables) goes to stderr; stdout carries only the
`--json` summary object, so scripts can pipe it.
"""

from __future__ import annotations

import contextlib
import json
import math
import sys
import time
from collections.abc import Callable, Iterator
from typing import Any

import torch
import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress as RichProgress,
    SpinnerColumn,
    TaskID,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.text import Text

from ..device import resolve_device
from ..errors import SplatError
from ..events import Event, EventSink, Note, Progress, Stage, StageDone
from ..files.atomic import json_default
from ..render import Renderer, resolve_renderer
from ..render.backends import gsplat_will_compile

DeviceOpt = typer.Option("auto", "--device", help="Where to compute: auto (CUDA if available, else CPU), cpu or cuda.")
RendererOpt = typer.Option("auto", "--renderer", help="What draws: auto (gsplat's CUDA kernels on a GPU when installed, "
                           "pip install 'splatcli\\[cuda]'; else torch), torch (the PyTorch rasterizer, any device) or gsplat.")
SeedOpt = typer.Option(0, "--seed", help="Random seed; the same seed on CPU gives the same result.")
QuietOpt = typer.Option(False, "--quiet", "-q", help="Print nothing but errors (and the --json object).")
JsonOpt = typer.Option(False, "--json", help="Print one JSON summary object on stdout, for scripts and Makefiles.")
DebugOpt = typer.Option(False, "--debug", help="Show full tracebacks on errors.")
BackgroundOpt = typer.Option(None, "--background", help="white, black, gray or R,G,B in [0, 1] (default: the scene's).")  # render, eval (process allows auto)


def resolve(device: str, renderer: str, quiet: bool = False) -> tuple[torch.device, Renderer]:
    """--device and --renderer, resolved together (the renderer depends on the device)."""
    dev = resolve_device(device)
    if dev.type == "cuda" and renderer.strip().lower() != "torch" and not quiet and gsplat_will_compile():
        Console(stderr=True).print("[dim]note:[/dim] gsplat compiles its CUDA kernels on first use "
                                   "(a few minutes, once); the PyTorch path draws if that fails")
    return dev, resolve_renderer(renderer, dev)


BACKGROUNDS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0), "gray": (0.5, 0.5, 0.5), "grey": (0.5, 0.5, 0.5)}


def parse_background(text: str | None, *, auto: bool = False) -> tuple[float, float, float] | None:
    """The one --background parser: white, black, gray, or R,G,B in [0, 1]; `auto`
    (None) where the command allows it, and None when the option is not given."""
    if text is None:
        return None
    t = text.strip().lower()
    if auto and t == "auto":
        return None
    if t in BACKGROUNDS:
        return BACKGROUNDS[t]
    allowed = f"expected {'auto, ' if auto else ''}white, black, gray or R,G,B in [0, 1]"
    try:
        rgb = tuple(float(p) for p in t.split(","))
    except ValueError:
        rgb = ()
    if len(rgb) != 3 or not all(math.isfinite(v) for v in rgb):
        raise SplatError(f"--background {text!r}: {allowed}")
    if not all(0.0 <= v <= 1.0 for v in rgb):
        raise SplatError(f"--background {text!r}: each of R,G,B must be in [0, 1] (divide 0-255 values by 255)")
    return rgb  # type: ignore[return-value]


class _Remaining(TimeRemainingColumn):
    """Time left: the stage's own estimate where its events carry one (Progress.eta_s), none while
    a stage that gives its own has not measured it yet (Progress.eta_own), else rich's extrapolation
    from the count."""

    def render(self, task: Any) -> Any:
        eta = task.fields.get("eta")
        if eta is None and task.fields.get("eta_own") and not task.finished:
            return Text("-:--:--", style="progress.remaining")
        if eta is None or task.finished:
            return super().render(task)
        return Text(_clock(eta), style="progress.remaining")


class _Count(MofNCompleteColumn):
    """`done/total`, left blank for a stage that has no count (a spinner and a time); `done/~total`
    where the total is an estimate (Progress.share)."""

    def render(self, task: Any) -> Any:
        if not task.fields.get("counted", True):
            return Text("")
        if task.fields.get("share") is None or task.finished or task.total is None:
            return super().render(task)
        total = int(task.total)
        return Text(f"{int(task.completed):{len(str(total))}d}/~{total}", style="progress.download")


class _Bar(BarColumn):
    """The bar filled to the stage's own share where its events carry one (Progress.share: a planned
    run fills with its clock, not with a step total that moves as it plans again)."""

    def render(self, task: Any) -> Any:
        bar = super().render(task)
        share = task.fields.get("share")
        if share is not None and not task.finished:
            bar.total, bar.completed = 1.0, min(max(share, 0.0), 1.0)
        return bar


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, (list, tuple)) and len(v) > 6:
        return f"[{len(v)} items]"
    return str(v)


# Off a terminal (CI, Make, a log file) the bars are drawn once, at the end; until then a long stage
# prints one plain line at most this often, with its count, elapsed time and ETA.
LOG_PERIOD_S = 10.0


def _clock(seconds: float) -> str:
    s = int(round(seconds))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"


class _LogLines:
    """The plain progress lines printed off a terminal: a stage's first after LOG_PERIOD_S, then
    one every LOG_PERIOD_S (a quick stage prints none)."""

    def __init__(self, console: Console) -> None:
        self.console = console
        self.started: dict[str, float] = {}
        self.last: dict[str, float] = {}

    def __call__(self, ev: Event) -> None:
        now = time.monotonic()
        if isinstance(ev, Stage):
            self.started[ev.name] = self.last[ev.name] = now
        elif isinstance(ev, Progress):
            t0 = self.started.setdefault(ev.name, now)
            if now - self.last.setdefault(ev.name, t0) < LOG_PERIOD_S:
                return
            self.last[ev.name] = now
            elapsed = now - t0
            if ev.total and ev.share is not None:  # the total is an estimate; the share is the stage's own
                count = f"{ev.done:,}/~{ev.total:,} ({100 * ev.share:.0f}%)"
            else:
                count = f"{ev.done:,}" + (f"/{ev.total:,} ({100 * ev.done / ev.total:.0f}%)" if ev.total else "")
            eta = ""
            if ev.eta_s is not None and (not ev.total or ev.done < ev.total):
                eta = f", ETA {_clock(ev.eta_s)}"
            elif ev.total and 0 < ev.done < ev.total and not ev.eta_own:
                eta = f", ETA {_clock(elapsed / ev.done * (ev.total - ev.done))}"
            info = "  ".join(f"{k} {_fmt(v)}" for k, v in ev.info.items())
            self.console.print(escape(f"{ev.name}: {count}, {_clock(elapsed)} elapsed{eta}" + (f"  {info}" if info else "")))


class _BarSink:
    """An EventSink drawing rich progress bars, and a log line per event off a terminal."""

    def __init__(self, bars: RichProgress, note: Callable[[str, str], None], lines: _LogLines | None) -> None:
        self.bars, self.note, self.lines = bars, note, lines
        self.tasks: dict[str, TaskID] = {}
        self.started = False

    def start(self) -> None:
        # Lazily: a command that fails on its input before any progress must
        # print nothing but its one `error:` line (no blank live-display line).
        if not self.started:
            self.bars.start()
            self.started = True

    def __call__(self, ev: Event) -> None:
        bars, tasks = self.bars, self.tasks
        if isinstance(ev, (Stage, Progress)):
            self.start()
            if self.lines is not None:
                self.lines(ev)
        if isinstance(ev, Stage):
            tasks[ev.name] = bars.add_task(ev.name, total=ev.total, info="", counted=ev.total is not None)
        elif isinstance(ev, Progress):
            if ev.name not in tasks:
                tasks[ev.name] = bars.add_task(ev.name, total=ev.total, info="")
            info = "  ".join(f"{k} {_fmt(v)}" for k, v in ev.info.items())
            bars.update(tasks[ev.name], completed=ev.done, total=ev.total, info=info, counted=True, eta=ev.eta_s,
                        eta_own=ev.eta_own, share=ev.share)
        elif isinstance(ev, StageDone):
            tid = tasks.get(ev.name)
            if tid is not None:
                t = bars.tasks[tid] if tid < len(bars.tasks) else None
                total = t.total if t is not None and t.total is not None else (t.completed if t else 1)
                bars.update(tid, total=total, completed=total)
        elif isinstance(ev, Note):
            self.note(ev.message, ev.level)


class Ui:
    """The console of one command run."""

    def __init__(self, *, quiet: bool = False, json_out: bool = False) -> None:
        self.quiet = quiet
        self.json_out = json_out
        self.err = Console(stderr=True, highlight=False, quiet=quiet, soft_wrap=True)
        if not self.err.is_terminal:
            # Logs of Makefiles and CI: rich assumes 80 columns there, which truncates
            # the progress columns (loss, PSNR, count) to ellipses.
            self.err.width = 140

    def note(self, message: str, level: str = "note") -> None:
        head = "[yellow]warning:[/yellow]" if level == "warning" else "[dim]note:[/dim]"
        self.err.print(f"{head} {escape(message)}")  # a message's [brackets] are text, not markup

    @contextlib.contextmanager
    def progress(self) -> Iterator[EventSink]:
        """An EventSink that draws rich progress bars (spinners when the total is unknown)."""
        bars = RichProgress(SpinnerColumn(), TextColumn("[bold]{task.description}"), _Bar(), _Count(),
                            TimeElapsedColumn(), _Remaining(), TextColumn("{task.fields[info]}"),
                            console=self.err, disable=self.quiet)
        sink = _BarSink(bars, self.note, _LogLines(self.err) if not self.err.is_terminal and not self.quiet else None)
        erase = False
        try:
            yield sink
        except SplatError:
            # A user error found mid-way: erase the bars (on a terminal; elsewhere they
            # are never printed), so the one `error:` line is all that is left to read.
            erase = True
            raise
        finally:
            if sink.started and erase:
                bars.live.transient = True
                bars.live.stop()  # not bars.stop(), which prints an empty line off a terminal
            elif sink.started:
                bars.stop()

    def summary(self, data: dict[str, Any], title: str = "", lines: list[str] | None = None) -> None:
        """Print the command's result: the JSON object on stdout with --json, else
        a few human lines."""
        if self.json_out:
            sys.stdout.write(json.dumps(data, default=json_default) + "\n")
            sys.stdout.flush()
            return
        if self.quiet:
            return
        out = Console(highlight=False, soft_wrap=True)  # summary lines stay whole in logs
        if title:
            out.print(f"[bold green]{title}[/bold green]")
        for line in lines or []:
            out.print(line)
