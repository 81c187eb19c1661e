"""`splatcli view`: look at a project or a splat file in the browser, served from this machine."""

from __future__ import annotations

import contextlib
import signal
import time
import webbrowser
from collections.abc import Iterator
from pathlib import Path
from typing import Optional

import typer

from ..events import EventSink
from ..project import Project
from ..viewer import LiveSink, ViewerServer, is_loopback, open_scene, project_scene
from .common import DebugOpt, JsonOpt, QuietOpt, Ui

HostOpt = typer.Option("127.0.0.1", "--host", help="Address to serve on. The default is this machine only (reach it "
                       "from elsewhere through an SSH tunnel); any other address lets other machines look.")
PortOpt = typer.Option(None, "--port", help="Port to serve on (default 7007, or the next free one).")


@contextlib.contextmanager
def live_viewer(ui: Ui, project: Path, on: bool, host: str, port: int | None, sink: EventSink) -> Iterator[EventSink]:
    """`train --viewer`: serve the project's scene, kept current from the training events."""
    if not on:
        yield sink
        return
    store = project_scene(Project.open(project), str(project))
    warn_host(ui, host)
    with ViewerServer(store, host, port) as server:
        ui.note(f"live viewer at {server.url}")
        yield LiveSink(store, sink)


def warn_host(ui: Ui, host: str) -> None:
    if not is_loopback(host):
        ui.note(f"--host {host}: the viewer is reachable from other machines on this network", "warning")


def view(
    source: Path = typer.Argument(..., help="A project directory (its latest checkpoint), or a splat file "
                                  "(.ply, .compressed.ply, .spz, .sog, .splat)."),
    host: str = HostOpt,
    port: Optional[int] = PortOpt,
    open_browser: bool = typer.Option(False, "--open", help="Open the viewer in this machine's web browser."),
    appearance_of: Optional[str] = typer.Option(None, "--appearance-of", help="A training photo's name: show the "
                                                "scene in its light (what --appearance exposure learnt for it) "
                                                "instead of the scene's, the average of the training photos'."),
    quiet: bool = QuietOpt,
    json_out: bool = JsonOpt,
    debug: bool = DebugOpt,
) -> None:
    """Serve a web viewer of the scene (orbit, pan, zoom, the project's cameras) until Ctrl-C.
    Everything it loads ships with splatcli: it works offline."""
    ui = Ui(quiet=quiet, json_out=json_out)
    store = open_scene(source, appearance_of)
    warn_host(ui, host)
    with ViewerServer(store, host, port) as server:
        # The try opens before the URL is printed: whoever reads it may press Ctrl-C at once.
        try:
            s = store.state()
            ui.summary({"url": server.url, "num_gaussians": s["num_gaussians"], "sh_degree": s["sh_degree"],
                        "cameras": len(s["cameras"])},
                       title=f"viewer at {server.url}",
                       lines=[f"{s['num_gaussians']} Gaussians, SH degree {s['sh_degree']}, "
                              f"{len(s['cameras'])} cameras; Ctrl-C stops it"])
            if open_browser:
                webbrowser.open(server.url)
            while True:
                time.sleep(0.5)
        except KeyboardInterrupt:  # Ctrl-C is how a viewer ends: exit 0, also when pressed again while it closes
            signal.signal(signal.SIGINT, signal.SIG_IGN)
