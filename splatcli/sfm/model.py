"""Read a project's PINHOLE COLMAP model back as `SceneData`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import Camera, SceneData
from ..errors import SplatError


def _cam_from_world(image) -> np.ndarray:  # [3, 4]
    pose = image.cam_from_world
    pose = pose() if callable(pose) else pose  # a method in pycolmap >= 3.12 frames API
    return np.asarray(pose.matrix(), dtype=np.float64)


def read_scene(sparse_dir: str | Path, *, pinhole_only: bool = True) -> SceneData:
    """Cameras sorted by image name, plus the SfM points and colours.

    Only PINHOLE / SIMPLE_PINHOLE cameras are accepted: `process` undistorts
    everything else before writing the model. `pinhole_only=False` reads any
    model (K then ignores the distortion), for comparing raw SfM output.
    """
    from .colmap import _pc
    from .colmap_files import check_model

    sparse_dir = Path(sparse_dir)
    # pycolmap trusts the counts in .bin files: a damaged file can abort the
    # interpreter. Walk the files first (about half pycolmap's own read time).
    check_model(sparse_dir)
    pycolmap = _pc()  # imported with COLMAP's log silenced
    try:
        rec = pycolmap.Reconstruction(str(sparse_dir))
    except Exception as exc:  # pycolmap raises plain RuntimeError/ValueError on bad files
        raise SplatError(f"{sparse_dir}: cannot read the COLMAP model ({' '.join(str(exc).split())[:200]})") from None
    cams: list[Camera] = []
    for image in rec.images.values():
        if hasattr(image, "has_pose") and not image.has_pose:
            continue
        cam = rec.cameras[image.camera_id]
        model = str(cam.model_name if hasattr(cam, "model_name") else cam.model).split(".")[-1]
        if pinhole_only and model not in ("PINHOLE", "SIMPLE_PINHOLE"):
            raise SplatError(f"{sparse_dir}: camera {image.camera_id} is {model}, expected PINHOLE (undistorted)")
        K = np.asarray(cam.calibration_matrix(), dtype=np.float64)
        view = np.eye(4)
        view[:3, :4] = _cam_from_world(image)
        cams.append(Camera(name=image.name, width=int(cam.width), height=int(cam.height), K=K, viewmat=view))
    cams.sort(key=lambda c: c.name)
    if rec.num_points3D() > 0:
        pts = rec.points3D
        points = np.stack([p.xyz for p in pts.values()]).astype(np.float64)
        colors = np.stack([p.color for p in pts.values()]).astype(np.uint8)
    else:
        points = np.zeros((0, 3), np.float64)
        colors = np.zeros((0, 3), np.uint8)
    return SceneData(cameras=cams, points=points, colors=colors)
