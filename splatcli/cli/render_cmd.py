"""`splatcli render`: images (and a video) of a trained project or any 3DGS .ply."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..views.output import RenderConfig, plan_render, run_render
from .common import BackgroundOpt, DebugOpt, DeviceOpt, JsonOpt, QuietOpt, RendererOpt, Ui, parse_background, resolve

_D = RenderConfig()  # the defaults, written once in the config


def render(
    source: Path = typer.Argument(..., help="A project directory (latest checkpoint) or a 3DGS .ply file."),
    split: Optional[str] = typer.Option(None, "--split", help="Dataset cameras: test (default), train or all."),
    cameras: Optional[Path] = typer.Option(None, "--cameras", help="Cameras from a nerfstudio / instant-ngp transforms.json."),
    path: Optional[str] = typer.Option(None, "--path", help="A generated path around the cameras: orbit, spiral or interpolate."),
    frames: int = typer.Option(_D.frames, "--frames", help="Frames of a generated --path."),
    project: Optional[Path] = typer.Option(None, "--project", help="For a .ply: take cameras and background from this project."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Output folder (default PROJECT/renders/<split|path>/)."),
    width: Optional[int] = typer.Option(None, "--width", help="Image width in pixels (alone: keeps the aspect)."),
    height: Optional[int] = typer.Option(None, "--height", help="Image height in pixels (alone: keeps the aspect)."),
    downscale: Optional[float] = typer.Option(None, "--downscale", help="Divide the cameras' stored resolution by this (default: a project's cameras at the resolution trained)."),
    background: Optional[str] = BackgroundOpt,
    antialias: str = typer.Option(_D.antialias, "--antialias", help="auto | on | off: draw with the 2D antialiasing filter "
                                  "against aliasing). auto: on for a model trained with --mip-filter "
                                  "or drawn smaller than trained (zoomed in it only blurs)."),
    appearance_of: Optional[str] = typer.Option(None, "--appearance-of", help="A training photo's name: render with "
                                                "its light (what --appearance exposure learnt for it) instead of the "
                                                "scene's, the average of the training photos'."),
    depth: bool = typer.Option(False, "--depth", help="Also write depth/<name>.png (colour-mapped)."),
    alpha: bool = typer.Option(False, "--alpha", help="Also write alpha/<name>.png."),
    video: Optional[Path] = typer.Option(None, "--video", help="Also encode the frames into this video (.mp4, .avi)."),
    fps: float = typer.Option(_D.video_fps, "--fps", help="Frame rate of the --video."),
    device: str = DeviceOpt,
    renderer: str = RendererOpt,
    quiet: bool = QuietOpt,
    json_out: bool = JsonOpt,
    debug: bool = DebugOpt,
) -> None:
    """Render views to PNGs (and a video) and report frames per second.

    Cameras: the project's --split (test by default), a --cameras transforms.json,
    or a generated --path around them (around every camera of a project). A .ply
    from another tool renders too: its cameras come from --project or --cameras,
    else an orbit around it is made. Rows of a .ply with NaN/Inf values are
    dropped with a note; a file with no valid row is refused.
    """
    ui = Ui(quiet=quiet, json_out=json_out)
    cfg = RenderConfig(
        split=split, cameras=cameras, path=path, frames=frames, project=project, width=width, height=height,
        downscale=downscale, out=out, background=parse_background(background),
        depth=depth, alpha=alpha, video=video, video_fps=fps, antialias=antialias.strip().lower(), renderer=renderer,
        appearance_of=appearance_of,
    )
    plan = plan_render(source, cfg, resolve(device, renderer, quiet)[0])  # input errors surface before any output
    with ui.progress() as sink:
        r = run_render(plan, on_event=sink)
    ui.summary(
        {"out_dir": r.out_dir, "frames": r.num_frames, "width": r.width, "height": r.height, "fps": r.fps,
         "render_seconds": r.render_seconds, "num_gaussians": r.num_gaussians, "device": r.device_name, "renderer": r.renderer,
         "video": r.video, "source": r.source, "cameras": r.cameras, "antialiased": r.antialiased},
        title=f"rendered {r.num_frames} frames ({r.cameras}) of {r.source}",
        lines=[f"{r.width}x{r.height}, {r.num_gaussians} Gaussians: {r.fps:.2f} frames/s on {r.device_name} ({r.renderer})",
               f"images: {r.out_dir}/"] + ([f"video: {r.video}"] if r.video else []),
    )
