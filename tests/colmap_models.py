"""Small synthetic COLMAP models for tests, from `pycolmap.synthesize_dataset`.

pycolmap is imported when a model is made, not when this module is, as
splatcli.sfm.colmap does (its glog installs signal handlers on import).
"""

from __future__ import annotations

from splatcli.sfm.colmap import Model


def synthetic_model(num_images: int = 6, num_points: int = 50, camera_model: str = "SIMPLE_RADIAL",
                    width: int = 64, height: int = 48, num_cameras: int = 1, seed: int = 0) -> Model:
    """A small synthetic model: `num_images` images per camera, seeing random points."""
    import pycolmap

    pycolmap.logging.minloglevel = 3  # as splatcli.sfm.colmap does: COLMAP's own log stays quiet
    pycolmap.set_random_seed(seed)
    o = pycolmap.SyntheticDatasetOptions()
    o.num_rigs = num_cameras
    o.num_cameras_per_rig = 1
    o.num_frames_per_rig = num_images
    o.num_points3D = num_points
    o.camera_width = width
    o.camera_height = height
    o.camera_model_id = getattr(pycolmap.CameraModelId, camera_model)
    f = 1.2 * max(width, height)
    params = {"SIMPLE_PINHOLE": [f, width / 2, height / 2], "PINHOLE": [f, f, width / 2, height / 2],
              "SIMPLE_RADIAL": [f, width / 2, height / 2, 0.05],
              "OPENCV": [f, f, width / 2, height / 2, 0.05, -0.01, 0.001, 0.001]}[camera_model]
    o.camera_params = params
    o.num_points2D_without_point3D = 3
    return Model(pycolmap.synthesize_dataset(o))
