"""The `render` command's core: a model (model.py) seen from a list of views,
written to PNGs and a video.

`plan_render` checks options, loads the model and picks the views; `render_views`
rasterizes every view, writes the images atomically and reports frames per second.
The frame rate counts rasterization only (with the device synchronised), not PNG
encoding or disk writes, so it is the figure a viewer would get from this renderer.
"""

from __future__ import annotations

import contextlib
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..device import describe_device, synchronize
from ..errors import SplatError
from ..events import EventSink, Note, Progress, Stage, StageDone, emit
from ..files.atomic import atomic_write_bytes
from ..gaussians import Gaussians
from ..model import LoadedModel, load_model
from ..project import Project
from ..render import Renderer, RenderOutput, render_camera, resolve_renderer
from .paths import PATHS, cameras_around_points, generate_path
from .sources import SPLITS, View, choose_antialias, dataset_views, resize_views, transforms_views, zoom_factor

VIDEO_CODECS = {".mp4": "mp4v", ".avi": "MJPG", ".mov": "mp4v", ".mkv": "mp4v"}


@dataclass(frozen=True)
class RenderConfig:
    # ---- cameras: one source ------------------------------------------------
    split: str | None = None  # test | train | all (default test, for a project)
    cameras: Path | None = None  # a nerfstudio / instant-ngp transforms.json
    path: str | None = None  # orbit | spiral | interpolate, around the cameras above
    frames: int = 120  # frames of a generated path
    project: Path | None = None  # cameras (and background) for a .ply source
    # ---- image size -----------------------------------------------------------
    width: int | None = None  # px; with only one of width/height the aspect is kept
    height: int | None = None
    downscale: float | None = None  # divide the cameras' size by this first (None: a project's cameras at the trained resolution)
    # ---- output ---------------------------------------------------------------
    out: Path | None = None  # default: PROJECT/renders/<name>/ (beside the .ply for a .ply)
    background: tuple[float, float, float] | None = None  # None: the scene's (project), else black
    depth: bool = False  # also write depth/<name>.png (turbo colour map, near..far of the first frame)
    alpha: bool = False  # also write alpha/<name>.png (8-bit accumulated opacity)
    video: Path | None = None  # also encode the frames into this video (.mp4, .avi)
    video_fps: float = 30.0
    write_images: bool = True  # False: only time the rendering (and the video)
    sh_degree: int | None = None  # None: every band the model holds
    antialias: str = "auto"  # auto | on | off: the 2D filter (views/sources.choose_antialias)
    renderer: str = "auto"  # auto | torch | gsplat (render/backends.resolve_renderer)
    appearance_of: str | None = None  # a training photo's light instead of the scene's (model.load_model)


@dataclass
class RenderResult:
    out_dir: Path | None
    num_frames: int
    width: int  # of the first frame, px
    height: int
    num_gaussians: int
    render_seconds: float  # rasterization only, device synchronised
    fps: float  # frames / render_seconds
    device: str
    background: tuple[float, float, float]
    images: list[Path] = field(default_factory=list)
    video: Path | None = None
    device_name: str = ""  # e.g. "cpu (2 threads)", "cuda:0 (NVIDIA H200)"
    source: str = ""  # what was rendered: "checkpoint step 7000", "scene.ply"
    cameras: str = ""  # where the views came from: "test split", "orbit path", ...
    antialiased: bool = False  # drawn with the 2D filter
    renderer: str = "torch"  # what drew: torch or gsplat


def to_uint8(img: Tensor) -> np.ndarray:  # [H, W, C] in [0, 1] -> [H, W, C] uint8
    return (img.detach().clamp(0, 1).mul(255).round().to(torch.uint8).cpu().numpy())


def encode_png(rgb: np.ndarray) -> bytes:  # [H, W, 3] or [H, W] uint8
    import cv2

    img = rgb[..., ::-1] if rgb.ndim == 3 else rgb  # OpenCV wants BGR
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img))
    if not ok:
        raise SplatError("cannot encode a PNG image")
    return buf.tobytes()


def depth_image(depth: Tensor, alpha: Tensor, near_far: tuple[float, float]) -> np.ndarray:  # [H,W],[H,W] -> [H,W,3]
    """Expected depth (depth / alpha) through the turbo colour map; empty pixels black."""
    import cv2

    d = (depth / alpha.clamp_min(1e-6)).cpu().numpy()
    lo, hi = near_far
    u8 = np.clip((d - lo) / max(hi - lo, 1e-9) * 255, 0, 255).astype(np.uint8)
    rgb = cv2.applyColorMap(u8, cv2.COLORMAP_TURBO)[..., ::-1]
    rgb[alpha.cpu().numpy() < 0.05] = 0
    return rgb


def _depth_range(depth: Tensor, alpha: Tensor) -> tuple[float, float]:
    m = alpha > 0.5
    if not bool(m.any()):
        return (0.0, 1.0)
    d = (depth[m] / alpha[m]).float().cpu().numpy()
    return float(np.percentile(d, 2)), float(np.percentile(d, 98))


class _VideoOut:
    """An OpenCV writer into a temporary name, renamed over the target on close."""

    def __init__(self, path: Path, fps: float, size: tuple[int, int]) -> None:
        import cv2

        codec = VIDEO_CODECS.get(path.suffix.lower())
        if codec is None:
            raise SplatError(f"--video {path}: unknown container {path.suffix!r}; allowed: {', '.join(VIDEO_CODECS)}")
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path = path
        self.tmp = path.with_name(f".{path.stem}.partial{path.suffix}")
        self.size = size
        self.writer = cv2.VideoWriter(str(self.tmp), cv2.VideoWriter_fourcc(*codec), float(fps), size)
        if not self.writer.isOpened():
            raise SplatError(f"--video {path}: OpenCV cannot write {path.suffix} videos here (codec {codec})")

    def write(self, rgb: np.ndarray) -> None:  # [H, W, 3] uint8
        import cv2

        if (rgb.shape[1], rgb.shape[0]) != self.size:  # a video has one size: resize odd frames
            rgb = cv2.resize(rgb, self.size, interpolation=cv2.INTER_AREA)
        self.writer.write(np.ascontiguousarray(rgb[..., ::-1]))

    def close(self, ok: bool) -> None:
        self.writer.release()
        if ok:
            os.replace(self.tmp, self.path)
        else:
            with contextlib.suppress(OSError):
                self.tmp.unlink()


def _finite(gaussians: Gaussians, on_event: EventSink | None) -> Gaussians:
    """The Gaussians without NaN or Inf (the rasterizer refuses them; a checkpoint should hold none)."""
    finite = gaussians.finite_mask()
    if bool(finite.all()):
        return gaussians
    emit(on_event, Note(f"skipping {int((~finite).sum())} Gaussians with NaN/Inf values", "warning"))
    return gaussians.select(finite)


def _write_view(out: RenderOutput, rgb: np.ndarray, out_dir: Path, name: str, config: RenderConfig,
                near_far: tuple[float, float] | None) -> tuple[float, float] | None:
    """One view's PNG, and its alpha/ and depth/ images when asked; the depth range (set by the
    first view: one range for the whole sequence, so no flicker)."""
    atomic_write_bytes(out_dir / name, encode_png(rgb))
    if config.alpha:
        atomic_write_bytes(out_dir / "alpha" / name, encode_png(to_uint8(out.alpha[..., None])[..., 0]))
    if config.depth:
        if near_far is None:
            near_far = _depth_range(out.depth, out.alpha)
        atomic_write_bytes(out_dir / "depth" / name, encode_png(depth_image(out.depth, out.alpha, near_far)))
    return near_far


def render_views(
    gaussians: Gaussians,
    views: Sequence[View],
    config: RenderConfig,
    out_dir: Path | None,
    *,
    on_event: EventSink | None = None,
    antialiased: bool = False,
    renderer: Renderer = Renderer("torch"),
) -> RenderResult:
    """Render `views` into `out_dir` (PNG per view; depth/ and alpha/ sub-folders
    when asked) and optionally a video, with the 2D filter when `antialiased`.
    `renderer` draws. Nothing is written when `out_dir` is None and no video is asked for."""
    if not views:
        raise SplatError("no views to render")
    device = gaussians.device
    bg_rgb = config.background if config.background is not None else (0.0, 0.0, 0.0)
    bg = torch.tensor(bg_rgb, dtype=gaussians.means.dtype, device=device)
    gaussians = _finite(gaussians, on_event)
    write = config.write_images and out_dir is not None
    c0 = views[0].camera
    video = _VideoOut(Path(config.video), config.video_fps, (c0.width, c0.height)) if config.video is not None else None
    images: list[Path] = []
    render_s = 0.0
    near_far: tuple[float, float] | None = None
    t_wall = time.perf_counter()
    emit(on_event, Stage("render", total=len(views)))
    render_camera(gaussians, views[0].camera, bg, sh_degree=config.sh_degree, antialiased=antialiased,
                  draw=renderer.draw)  # warm-up: first calls pay one-off set-up
    ok = False
    try:
        for i, view in enumerate(views):
            synchronize(device)
            t0 = time.perf_counter()
            out = render_camera(gaussians, view.camera, bg, sh_degree=config.sh_degree, antialiased=antialiased,
                                draw=renderer.draw)
            synchronize(device)
            render_s += time.perf_counter() - t0
            rgb = to_uint8(out.image)
            if write:
                assert out_dir is not None
                near_far = _write_view(out, rgb, out_dir, view.out_name, config, near_far)
                images.append(out_dir / view.out_name)
            if video is not None:
                video.write(rgb)
            emit(on_event, Progress("render", i + 1, len(views), {"fps": (i + 1) / max(render_s, 1e-9)}))
        ok = True
    finally:
        if video is not None:
            video.close(ok)
    emit(on_event, StageDone("render", time.perf_counter() - t_wall))
    return RenderResult(
        out_dir=out_dir if write else None, device_name=describe_device(device), num_frames=len(views),
        width=c0.width, height=c0.height, num_gaussians=len(gaussians), render_seconds=render_s,
        fps=len(views) / max(render_s, 1e-9), device=str(device),
        background=tuple(bg_rgb),  # type: ignore[arg-type]
        images=images, video=Path(config.video) if config.video is not None else None, antialiased=antialiased,
        renderer=renderer.name,
    )


# ---------------------------------------------------------------------------
# the command's core
# ---------------------------------------------------------------------------


def check_config(config: RenderConfig) -> None:
    """Refuse out-of-range options before any work, naming the allowed values."""
    if config.split is not None and config.split not in SPLITS:
        raise SplatError(f"--split {config.split!r} is not known; allowed values: {', '.join(SPLITS)}")
    if config.path is not None and config.path not in PATHS:
        raise SplatError(f"--path {config.path!r} is not known; allowed values: {', '.join(PATHS)}")
    if not 1 <= config.frames <= 100_000:
        raise SplatError(f"--frames {config.frames}: must be between 1 and 100000")
    if config.downscale is not None and not (math.isfinite(config.downscale) and 0 < config.downscale <= 64):
        raise SplatError(f"--downscale {config.downscale}: must be in (0, 64]")
    for opt, v in (("--width", config.width), ("--height", config.height)):
        if v is not None and not 1 <= v <= 16384:
            raise SplatError(f"{opt} {v}: must be between 1 and 16384 pixels")
    if not (math.isfinite(config.video_fps) and 0 < config.video_fps <= 1000):
        raise SplatError(f"--fps {config.video_fps}: must be in (0, 1000]")
    if config.video is not None and Path(config.video).suffix.lower() not in VIDEO_CODECS:
        raise SplatError(f"--video {config.video}: unknown container; allowed: {', '.join(VIDEO_CODECS)}")
    if config.cameras is not None and config.split is not None:
        raise SplatError("--cameras and --split both choose the cameras; give one")
    if config.sh_degree is not None and not 0 <= config.sh_degree <= 3:
        raise SplatError(f"--sh-degree {config.sh_degree}: must be 0..3")
    choose_antialias(config.antialias, None, None)  # refuses an unknown mode


def select_views(model: LoadedModel, config: RenderConfig, notes: list[str]) -> tuple[list[View], str, Project | None]:
    """The views of the request, the name of their folder, and the project that
    supplied cameras (if any)."""
    project = model.project
    if project is None and config.project is not None:
        project = Project.open(config.project)
    if config.cameras is not None:
        size = (config.width, config.height) if config.width and config.height else None
        base = transforms_views(config.cameras, notes=notes, default_size=size)
        name = Path(config.cameras).stem
    elif project is not None:
        split = config.split or ("all" if config.path else "test")  # a path is built around every camera
        base = dataset_views(project, split)
        if config.downscale is None and config.width is None and config.height is None:
            res = project.trained_resolution()  # the resolution eval scores at
            base = [replace(v, camera=v.camera.at_resolution(*res)) for v in base]
        name = split
    else:
        if config.split is not None:
            raise SplatError(f"{model.path}: --split needs a project; pass --project PROJ or --cameras transforms.json")
        base, name = [], "orbit"
    kind, views = config.path, base
    if not base and kind is None:
        kind = "orbit"
        notes.append(f"{model.path.name}: no cameras given; rendering an orbit around the Gaussians (world -y up)")
    if kind is not None:
        cams = [v.camera for v in base] or cameras_around_points(model.gaussians.means.detach().cpu().numpy().astype(np.float64))
        views, name = generate_path(kind, cams, config.frames), kind
    views = resize_views(views, width=config.width, height=config.height, downscale=config.downscale or 1.0)
    return views, name, project


def _zoom(project: Project | None, config: RenderConfig, views: Sequence[View]) -> float | None:
    """Drawn over trained resolution, for a project's cameras (None otherwise: unknown)."""
    if project is None or config.cameras is not None:
        return None
    return zoom_factor(project, views, dataset_views(project, "all"))


@dataclass
class RenderPlan:
    """Everything checked and loaded, nothing rendered yet (so that input errors
    surface before any progress display or output)."""

    model: LoadedModel
    views: list[View]
    out_dir: Path
    config: RenderConfig  # with the background resolved
    cameras: str  # where the views came from, in words
    notes: list[str] = field(default_factory=list)
    antialiased: bool = False  # draw with the 2D filter
    renderer: Renderer = Renderer("torch")


def plan_render(source: str | os.PathLike, config: RenderConfig, device: torch.device) -> RenderPlan:
    """Check options, load the model, choose the views and the output folder."""
    check_config(config)
    renderer = resolve_renderer(config.renderer, device)
    model = load_model(source, device, config.appearance_of)
    notes = list(model.notes)
    views, name, project = select_views(model, config, notes)
    background = config.background if config.background is not None else (project.background() if project else None)
    if model.light is not None:  # what shows through goes through the photo's light too
        background = model.lit(background or (0.0, 0.0, 0.0))
    if config.out is not None:
        out_dir = Path(config.out)
    elif model.project is not None:
        out_dir = model.project.render_dir(name)
    else:
        out_dir = model.path.parent / "renders" / f"{model.path.stem}_{name}"
    if out_dir.exists() and not out_dir.is_dir():
        raise SplatError(f"--out {out_dir}: exists and is not a directory")
    what = f"{name} path" if name in PATHS else Path(config.cameras).name if config.cameras else f"{name} split"
    antialiased, why = choose_antialias(config.antialias, model.antialiased, _zoom(project, config, views))
    notes += [n for n in (why, renderer.note) if n]
    return RenderPlan(model=model, views=views, out_dir=out_dir, config=replace(config, background=background),
                      cameras=what, notes=notes, antialiased=antialiased, renderer=renderer)


def run_render(plan: RenderPlan, *, on_event: EventSink | None = None) -> RenderResult:
    """Render a plan into its folder (and video)."""
    for n in plan.notes:
        emit(on_event, Note(n))
    result = render_views(plan.model.gaussians, plan.views, plan.config, plan.out_dir, on_event=on_event,
                          antialiased=plan.antialiased, renderer=plan.renderer)
    result.source, result.cameras = plan.model.name, plan.cameras
    return result


def render(source: str | os.PathLike, config: RenderConfig, device: torch.device, *,
           on_event: EventSink | None = None) -> RenderResult:
    """`splatcli render` in one call: plan, then run."""
    return run_render(plan_render(source, config, device), on_event=on_event)
