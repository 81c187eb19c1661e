"""What the tests share beyond fixtures (tests/conftest.py): the third-party data, the sample
scene's renderer, and modules beside this one: the tiny trained project (`tiny_project`),
seeded synthetic Gaussian scenes (`scenes`), pose alignment (`align`) and a headless
browser (`browser`). Tests import them as `support` (pyproject.toml's pytest `pythonpath`
names tests/); nothing here is part of the installed package, nor of bench/.
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path
from types import ModuleType

REPO = Path(__file__).resolve().parents[2]


def data_dir() -> Path:
    """The third-party scenes: $SPLATCLI_DATA, else ../shared/data beside the checkout. May not exist."""
    env = os.environ.get("SPLATCLI_DATA")
    return Path(env) if env else REPO.parent / "shared" / "data"


def make_scene() -> ModuleType:
    """sample_data/make_scene.py (the sample scene's renderer) as a module; it is a script, not a package."""
    spec = importlib.util.spec_from_file_location("make_scene", REPO / "sample_data" / "make_scene.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def zoom_about_centre(img, zoom: float):  # [H, W, C] uint8 -> the same size
    """The picture a `zoom` times longer lens on the same camera takes: zoomed about the image
    centre (pixel centres at i + 0.5), which stays the principal point."""
    import cv2
    import numpy as np

    h, w = img.shape[:2]
    t = (0.5 - w / 2) * zoom + w / 2 - 0.5, (0.5 - h / 2) * zoom + h / 2 - 0.5
    return cv2.warpAffine(img, np.array([[zoom, 0, t[0]], [0, zoom, t[1]]]), (w, h), flags=cv2.INTER_AREA)
