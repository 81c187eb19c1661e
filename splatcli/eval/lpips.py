"""LPIPS (Zhang et al. 2018), the AlexNet variant papers report, through the `lpips` package.

The package (the `lpips` extra) is the authors' reference implementation and ships
its linear layers (v0.1). The AlexNet trunk is torchvision's ImageNet weights,
`alexnet-owt-7be5be79.pth`, taken from `--lpips-weights PATH` or from the torch hub
cache (`torch.hub.get_dir()/checkpoints/`, i.e. $TORCH_HOME/hub/checkpoints), and
never downloaded: the file is looked for, and the trunk built without weights.

Unavailable LPIPS (no package, no weights) is not an error: the caller gets None
and a one-line hint. A `--lpips-weights` file the user named that cannot be used is
(`SplatError` naming it).
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path
from types import ModuleType

import torch
from torch import Tensor

from ..errors import SplatError

ALEXNET_FILE = "alexnet-owt-7be5be79.pth"  # torchvision's name for the ImageNet weights
MIN_SIZE = 31  # pixels: AlexNet's two 3x3/2 max-pools need this much after its 11x11/4 first layer
INSTALL = "pip install 'splatcli[lpips]'"

_torchvision_ops = None  # the operators declared by _import_package, kept alive with the process


def hub_weights_path() -> Path:
    """Where torchvision keeps the AlexNet weights (honours TORCH_HOME)."""
    return Path(torch.hub.get_dir()) / "checkpoints" / ALEXNET_FILE


def hint(reason: str) -> str:
    """The one line shown when LPIPS is left out."""
    return (f"LPIPS skipped: {reason}; to enable it, {INSTALL} and put torchvision's AlexNet weights "
            f"({ALEXNET_FILE}) in {hub_weights_path().parent}/ or pass --lpips-weights PATH")


def import_package() -> ModuleType | None:
    """The `lpips` module, or None when it (or torchvision) cannot be imported."""
    global _torchvision_ops
    try:
        import lpips
        return lpips
    except (ImportError, OSError):
        return None
    except RuntimeError as e:
        if "torchvision::nms" not in str(e) or _torchvision_ops is not None:
            return None
    # torchvision (up to 0.29 at least) registers fake kernels for nms and qnms at import
    # without checking that its C++ library loaded, and so fails to import where it did
    # not (a CPU-only torch beside a CUDA-built torchvision wheel: pytorch/vision#9085).
    # LPIPS uses none of its operators: declare those two, drop the half-imported
    # modules and import again.
    for name in [m for m in sys.modules if m.split(".")[0] in ("torchvision", "lpips")]:
        del sys.modules[name]
    _torchvision_ops = torch.library.Library("torchvision", "DEF")
    for op in ("nms", "qnms"):
        _torchvision_ops.define(f"{op}(Tensor dets, Tensor scores, float iou_threshold) -> Tensor")
    try:
        import lpips
        return lpips
    except (ImportError, RuntimeError, OSError):
        return None


class Lpips:
    """LPIPS v0.1 with the AlexNet trunk, on one device; build once per run (`load_lpips`)."""

    def __init__(self, net: torch.nn.Module, device: torch.device, weights: Path) -> None:
        self.net = net.to(device).eval()
        self.device = device
        self.weights = weights  # the trunk's file

    @torch.no_grad()
    def __call__(self, pred: Tensor, gt: Tensor) -> float | None:  # [H, W, 3] each, in [0, 1]
        """The distance (0 for identical images), or None below MIN_SIZE pixels a side."""
        if min(pred.shape[0], pred.shape[1]) < MIN_SIZE:
            return None
        # [1, 3, H, W] in [-1, 1], as LPIPS expects
        x, y = (t.to(self.device, torch.float32).permute(2, 0, 1)[None] * 2 - 1 for t in (pred, gt))
        return float(self.net(x, y))


def load_trunk(net: torch.nn.Module, path: Path) -> None:
    """Load torchvision's AlexNet `features.*` weights into an `lpips.LPIPS(net="alex")`;
    SplatError naming `path` when the file is not such a state dict."""
    try:
        sd = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # pickle, zip and I/O errors alike: the file is not usable weights
        raise SplatError(f"{path}: not a torch weights file (torch.load: {type(e).__name__})") from None
    if not isinstance(sd, dict):
        raise SplatError(f"{path}: holds a {type(sd).__name__}, not a state dict of torchvision's AlexNet")
    trunk = {}
    for key, p in net.net.state_dict().items():  # "slice2.3.weight" is torchvision's "features.3.weight"
        src = "features." + key.split(".", 1)[1]
        t = sd.get(src)
        if not isinstance(t, Tensor) or t.shape != p.shape:
            found = "missing" if t is None else f"shape {tuple(t.shape)}" if isinstance(t, Tensor) else type(t).__name__
            raise SplatError(f"{path}: not torchvision's AlexNet weights ({src}: {found}, "
                             f"expected shape {tuple(p.shape)})")
        trunk[key] = t.to(p.dtype)
    net.net.load_state_dict(trunk)


def load_lpips(weights: Path | None, device: torch.device) -> tuple[Lpips | None, str | None]:
    """(the scorer, None), or (None, the hint line) when LPIPS is unavailable.

    `weights`: the AlexNet file the user named (errors in it are SplatError); None
    looks in the torch hub cache, where a missing or unreadable file only skips LPIPS.
    """
    if weights is not None and not Path(weights).is_file():
        raise SplatError(f"--lpips-weights {weights}: no such file")
    path = Path(weights) if weights is not None else hub_weights_path()
    if not path.is_file():  # looked for before importing torchvision (seconds)
        return None, hint(f"no AlexNet weights at {path}")
    pkg = import_package()
    if pkg is None:
        if weights is not None:
            raise SplatError(f"--lpips-weights {weights}: the lpips package is not installed ({INSTALL})")
        return None, hint("the lpips package is not installed")
    with warnings.catch_warnings():  # torchvision's deprecation of `pretrained=`, which lpips passes
        warnings.simplefilter("ignore")
        net = pkg.LPIPS(net="alex", version="0.1", pnet_rand=True, verbose=False)  # trunk without weights: no download
    try:
        load_trunk(net, path)
    except SplatError as e:
        if weights is not None:
            raise SplatError(f"--lpips-weights {e}") from None
        return None, hint(str(e))
    return Lpips(net, device, path), None
