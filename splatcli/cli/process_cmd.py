"""`splatcli process`: photos, a video, a COLMAP workspace, a transforms.json or an LLFF capture -> a posed dataset."""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Optional

import typer

from ..errors import SplatError
from ..process.cameras import CAMERA_MODELS
from ..process.config import POSED_MAX_SIZE, SFM_MAX_SIZE
from ..process.run import ProcessConfig, process as run_process
from ..sfm import colmap
from .common import DebugOpt, JsonOpt, QuietOpt, SeedOpt, Ui, parse_background

_D = ProcessConfig()  # the defaults, written once in the config


def process(
    input: Path = typer.Argument(..., help="Folder of photos, video file, COLMAP workspace, transforms.json or LLFF poses_bounds.npy (or its folder)."),
    output: Path = typer.Option(..., "--output", "-o", help="The project directory to create."),
    input_type: str = typer.Option(_D.input_type, "--input-type", help="auto, images, video, colmap, transforms or llff."),
    max_size: Optional[int] = typer.Option(_D.max_size, "--max-size", help="Longest side, pixels, of the images SIFT sees (the dataset keeps full resolution; "
                                           f"default {SFM_MAX_SIZE} for photos and video, {POSED_MAX_SIZE} for the points of posed captures)."),
    matcher: str = typer.Option(_D.matcher, "--matcher", help="auto, exhaustive (all pairs), sequential (ordered captures) or retrieval (each photo with the 20 most alike; auto takes it above 40 photos whose names give no order)."),
    fps: Optional[float] = typer.Option(_D.fps, "--fps", help="Video: frames to extract per second of video."),
    num_frames: int = typer.Option(_D.num_frames, "--num-frames", help="Video: frames to extract, evenly spaced (without --fps)."),
    background: str = typer.Option("auto", "--background", help="auto (white for RGBA inputs, else black), white, black, gray or R,G,B in [0, 1]."),
    overwrite: bool = typer.Option(_D.overwrite, "--overwrite", help="Replace an existing project (or use a non-empty folder)."),
    strict: bool = typer.Option(_D.strict, "--strict", help="Fail on an unreadable, truncated or empty image or video frame (default: skip it with a warning; the manifest lists it)."),
    invert_masks: bool = typer.Option(_D.invert_masks, "--invert-masks", help="The mask files (masks/ beside the images, or transforms.json's mask_path) are white where masked out; "
                                      "flip them (the default reads black = masked out, white = keep, as COLMAP and nerfstudio do)."),
    single_camera: bool = typer.Option(False, "--single-camera", help="SfM: one camera for every image (photos of one camera at one zoom; they must share a size)."),
    per_image_cameras: bool = typer.Option(False, "--per-image-cameras", help="SfM: one camera per image (default: grouped by EXIF make, model, focal length and size; "
                                           "same-size photos without EXIF share one)."),
    camera_model: str = typer.Option(_D.camera_model, "--camera-model", help=f"SfM: the COLMAP camera model fitted ({', '.join(CAMERA_MODELS)}); "
                                     "the dataset is undistorted to PINHOLE."),
    triangulate: bool = typer.Option(_D.triangulate, "--triangulate/--no-triangulate",
                                     help="Posed captures (transforms.json, LLFF): triangulate points from the photos with the poses held fixed, "
                                     "for training to start from (too few: random points, as with --no-triangulate)."),
    seed: int = SeedOpt,
    quiet: bool = QuietOpt,
    json_out: bool = JsonOpt,
    debug: bool = DebugOpt,
) -> None:
    """Turn a capture into a posed dataset (SfM with pycolmap, or import of existing poses)."""
    ui = Ui(quiet=quiet, json_out=json_out)
    colmap.set_verbose(debug)
    if single_camera and per_image_cameras:
        raise SplatError("--single-camera and --per-image-cameras: choose one")
    cameras = "single" if single_camera else "per-image" if per_image_cameras else _D.cameras
    cfg = ProcessConfig(input_type=input_type, max_size=max_size, matcher=matcher, fps=fps, num_frames=num_frames,
                        background=parse_background(background, auto=True), overwrite=overwrite, seed=seed,
                        strict=strict, invert_masks=invert_masks, triangulate=triangulate,
                        cameras=cameras, camera_model=camera_model.upper())
    with ui.progress() as sink:
        r = run_process(input, output, cfg, on_event=sink)
    lines = [f"{r.train} train / {r.test} test images, {r.points} points"
             + (f", reprojection error {r.mean_reprojection_error:.2f} px" if r.mean_reprojection_error else ""),
             "stages: " + ", ".join(f"{k} {v:.1f}s" for k, v in r.seconds.items())]
    if r.consistency is not None:
        lines.append(f"poses checked: {r.consistency['line']}")
    if r.cameras:
        lines.append(f"cameras: {len(r.cameras)} ({_camera_kinds(r.cameras)})")
    if r.mask_source:
        src = "the images' alpha channel" if r.mask_source == "alpha" else "mask files"
        lines.append(f"masks: from {src}, in {r.project / 'masks'}")
    ui.summary(r.summary(), title=f"{r.input_kind}: {r.registered}/{r.total} images posed -> {r.project}", lines=lines)


_KINDS = {"exif": "from EXIF", "size": "shared by same-size photos without EXIF", "image": "one per photo",
          "video": "the video's", "single": "shared (--single-camera)"}


def _camera_kinds(cameras: list[dict]) -> str:
    """'2 from EXIF, 3 one per photo': how the cameras in the manifest were made."""
    return ", ".join(f"{k} {_KINDS.get(s, s)}" for s, k in Counter(c["source"] for c in cameras).items())
