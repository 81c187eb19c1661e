"""Names vulture (`make check`) reports as unused that are used, where it cannot see it.
Each entry says who uses it. Add one only for such a false positive: a name nothing
uses is deleted instead. Patterns are in pyproject.toml ([tool.vulture]: the Typer
callback and pytest fixtures by decorator, `pytestmark` by name)."""
# ruff: noqa: B018, F821

# Python's own hooks
__getattr__  # splatcli/__init__.py: the package's lazy attributes (PEP 562)
_.__signature__  # cli/options.py: read by inspect, hence Typer, to see the generated options
_.__annotations__  # cli/options.py: the same
_.forward  # render/composite.py: torch.autograd.Function's forward, called by apply()
closure  # train/appearance.py: torch.optim.Optimizer.step's signature
signum  # process/run.py, train/loop.py: signal handlers' signature

# pytest calls its hooks by name
pytest_collection_modifyitems  # tests/conftest.py: the longest tests first

# http.server and socketserver call these by name (viewer/server.py)
_.server_version
_.sys_version
_.log_message
_.do_GET
_.do_HEAD
_.do_POST
_.do_PUT
_.do_DELETE
_.do_PATCH
_.do_OPTIONS
_.daemon_threads
_.allow_reuse_address
_.handle_error
client_address  # handle_error's signature

# attributes of third-party objects, read by their owners
_.transient  # cli/common.py: rich's Live, read when it stops
_.minloglevel  # sfm/colmap.py, tests/colmap_models.py: pycolmap's logging
_.match_list_path  # sfm/colmap.py: pycolmap's matching options
_.random_seed  # sfm/colmap.py: pycolmap's options
_.blank_pixels  # sfm/colmap.py: pycolmap's undistortion options
_.binary_location  # tests/support/browser.py: selenium's Chromium options
_.num_rigs  # tests/colmap_models.py: pycolmap's synthetic dataset options, the next seven too
_.num_cameras_per_rig
_.num_frames_per_rig
_.camera_width
_.camera_height
_.camera_model_id
_.camera_params
_.num_points2D_without_point3D

# dataclass fields written out whole (asdict to JSON), never read by name in Python
_.train_psnr  # eval/curve.py TrainLogLine: train_log.jsonl
_.train_ssim
_.final_loss  # train/config.py TrainSummary: the manifest's and `train --json`'s summary
_.sh_auto_psnr
_.comm_seconds
_.rank_checks
_.scale_hist  # train/config.py TrainReport: reports/train.json
_.has_prior_focal_length  # sfm/colmap.py: a pycolmap camera's flag, read by COLMAP's two-view verification
_.external_attr  # formats/sog.py: a zip member's permissions, read by unzip
# render/kernels.py sets torch's own config flag (read inside torch.compile)
_.use_duck_shape
# sfm/colmap.py sets pycolmap's mapper options (read inside COLMAP's incremental mapper)
_.ba_min_num_residuals_for_cpu_multi_threading
_.ba_global_ignore_redundant_points3D
_.use_gpu  # sfm/worker.py: pycolmap's global mapper options (read inside COLMAP)
