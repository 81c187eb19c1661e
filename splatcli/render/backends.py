"""Which rasterizer draws (`--renderer auto|torch|gsplat`), and gsplat's CUDA kernels
behind the same call as `rasterize`.

`torch` is rasterize.py: every device, and the reference every other path is tested
against. `gsplat` is nerfstudio's CUDA rasterizer (the `cuda` extra), imported only
when asked for. `auto` is gsplat on a CUDA device when it is installed and its kernels
load, else torch. gsplat compiles its kernels the first time; when that fails (or finds
no CUDA toolkit) it only warns and leaves its `_C` unset, so that is checked here, and
the run falls back to torch with one line saying why.

The model is the same: means, quaternions (w, x, y, z), exp(log_scales),
sigmoid(opacity_logits), SH (DC first) at the active degree, world-to-camera view
matrices and K, the near plane, the 0.3 px^2 blur (eps2d), the antialiased mode for the
2D filter, and RGB+D for the depth (sum of w z). Where gsplat's kernels differ (alpha
clamped at 0.999 instead of 0.99, opacity-aware footprints, float32 only; the guide,
"GPUs") a picture differs slightly; checkpoints and exports do not depend on the renderer.
"""

from __future__ import annotations

import contextlib
import functools
import importlib.util
import io
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from ..camera import Camera
from ..errors import SplatError
from ..gaussians import Gaussians
from .output import RenderOutput
from .projection import BLUR
from .rasterize import rasterize, validate

RENDERERS = ("auto", "torch", "gsplat")
INSTALL = "pip install 'splatcli[cuda]'"

Rasterizer = Callable[..., RenderOutput]  # rasterize's signature


@dataclass(frozen=True)
class Renderer:
    name: str  # "torch" or "gsplat": the one that draws
    note: str | None = None  # one line: why the one asked for (or auto's first choice) does not draw

    @property
    def draw(self) -> Rasterizer:
        return rasterizer(self.name)


def rasterizer(name: str) -> Rasterizer:
    """The function behind a resolved renderer name (a stored config's, for instance)."""
    return rasterize_gsplat if name == "gsplat" else rasterize


@functools.cache
def gsplat_problem() -> str | None:
    """None when gsplat imports and its CUDA kernels load; else why not, with the fix,
    in one line. Loading may build the kernels (minutes, once); what gsplat and torch's
    builder print meanwhile is kept off stdout (--json) and out of the user's way."""
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return f"gsplat is not installed ({INSTALL} for its CUDA kernels)"
    except Exception as e:  # a broken install: say so, never a traceback
        return f"gsplat does not import ({type(e).__name__}: {_first_line(e)}); reinstall it ({INSTALL})"
    quiet = io.StringIO()
    cpp = logging.getLogger("torch.utils.cpp_extension")
    level = cpp.level
    cpp.setLevel(logging.ERROR)
    try:
        with contextlib.redirect_stdout(quiet), contextlib.redirect_stderr(quiet):
            from gsplat.cuda._backend import _C
    except Exception as e:
        return (f"gsplat's CUDA kernels did not build ({type(e).__name__}: {_first_line(e)}); they need nvcc "
                "from a CUDA toolkit matching torch's CUDA (set CUDA_HOME), see docs/guide.md, \"GPUs\"")
    finally:
        cpp.setLevel(level)
    if _C is None:
        return "gsplat found no CUDA toolkit to build its kernels (install nvcc, or set CUDA_HOME)"
    return None


def gsplat_will_compile() -> bool:
    """Whether loading gsplat's kernels will compile them first (minutes): it is installed
    without prebuilt kernels, and torch's extension cache holds no build of them yet."""
    try:
        if importlib.util.find_spec("gsplat") is None or importlib.util.find_spec("gsplat.csrc") is not None:
            return False
        from torch.utils.cpp_extension import _get_build_directory

        return not (Path(_get_build_directory("gsplat_cuda", False)) / "gsplat_cuda.so").exists()
    except Exception:  # torch's private helper moved: no hint rather than a wrong one
        return False


def _first_line(e: BaseException) -> str:
    return (str(e).strip().splitlines() or [""])[0][:160]


def resolve_renderer(name: str, device: torch.device) -> Renderer:
    """The `--renderer` option for a run on `device`. gsplat off CUDA is a user error;
    gsplat on CUDA that cannot load falls back to torch with a note."""
    name = (name or "auto").strip().lower()
    if name not in RENDERERS:
        raise SplatError(f"--renderer {name!r} is not known; allowed values: {', '.join(RENDERERS)}")
    if name == "torch":
        return Renderer("torch")
    if device.type != "cuda":
        if name == "gsplat":
            raise SplatError(f"--renderer gsplat needs a CUDA device; this run is on {device.type} "
                             "(use --device cuda on a GPU machine, or --renderer torch)")
        return Renderer("torch")
    why = gsplat_problem()
    if why is None:
        return Renderer("gsplat")
    return Renderer("torch", f"{why}; drawing with the PyTorch path instead")


def gsplat_inputs(
    means: Tensor,  # [N, 3] world
    quats: Tensor,  # [N, 4] w, x, y, z, any norm
    log_scales: Tensor,  # [N, 3]
    opacity_logits: Tensor,  # [N]
    sh: Tensor,  # [N, (d+1)^2, 3] DC first
    viewmat: Tensor,  # [4, 4] world -> camera (OpenCV)
    K: Tensor,  # [3, 3] px
    width: int,
    height: int,
    background: Tensor,  # [3]
    *,
    sh_degree: int,
    near: float,
    antialiased: bool,
) -> dict[str, Any]:
    """splatcli's parameters and conventions as keyword arguments of gsplat's
    `rasterization()` for one camera (both use OpenCV frames and sample pixel (u, v) at
    (u + 0.5, v + 0.5) in K's coordinates)."""
    return dict(
        means=means, quats=quats, scales=log_scales.exp(), opacities=torch.sigmoid(opacity_logits), colors=sh,
        viewmats=viewmat[None], Ks=K[None], width=width, height=height, near_plane=near, eps2d=BLUR,
        sh_degree=sh_degree, packed=False, backgrounds=background[None], render_mode="RGB+D",
        rasterize_mode="antialiased" if antialiased else "classic",
    )


def gsplat_output(
    colors: Tensor,  # [1, H, W, 4] RGB + depth (sum of w z)
    alphas: Tensor,  # [1, H, W, 1]
    meta: dict[str, Any],  # gsplat's: means2d [1, N, 2], radii [1, N, 2] (or [1, N]), depths [1, N]
) -> RenderOutput:
    """gsplat's results as a RenderOutput. means2d stays gsplat's own [1, N, 2] tensor,
    the one the image depends on, so that `retain_grad()` on it gives densification its
    screen-space gradient (RenderOutput.screen_grad); the radius is the larger axis's."""
    radii = meta["radii"][0]
    if radii.dim() == 2:
        radii = radii.amax(-1)
    radii = radii.to(torch.int32)
    return RenderOutput(image=colors[0, ..., :3], alpha=alphas[0, ..., 0], depth=colors[0, ..., 3],
                        means2d=meta["means2d"], radii=radii, visible=radii > 0, depths=meta["depths"][0])


def rasterize_gsplat(
    means: Tensor, quats: Tensor, log_scales: Tensor, opacity_logits: Tensor, sh: Tensor,
    viewmat: Tensor, K: Tensor, width: int, height: int, background: Tensor | None = None, *,
    sh_degree: int | None = None, near: float = 0.2, antialiased: bool = False,
    block: int | str = "auto", check: bool = True,
) -> RenderOutput:
    """`rasterize` (same arguments, shapes and result) drawn by gsplat's CUDA kernels.
    `block` is the PyTorch path's speed knob and is ignored here. float32 only; an empty
    model is drawn by the PyTorch path (nothing for the kernels to do)."""
    del block
    width, height, background, sh_degree = validate(means, quats, log_scales, opacity_logits, sh, viewmat, K,
                                                    width, height, background, sh_degree, near, check)
    if means.dtype != torch.float32:
        raise ValueError(f"rasterize: gsplat draws float32 only, got {means.dtype} (use --renderer torch)")
    if means.shape[0] == 0:
        return rasterize(means, quats, log_scales, opacity_logits, sh, viewmat, K, width, height, background,
                         sh_degree=sh_degree, near=near, antialiased=antialiased, check=False)
    from gsplat import rasterization

    colors, alphas, meta = rasterization(**gsplat_inputs(
        means, quats, log_scales, opacity_logits, sh, viewmat, K, width, height, background,
        sh_degree=sh_degree, near=near, antialiased=antialiased))
    return gsplat_output(colors, alphas, meta)


def render_camera(g: Gaussians, camera: Camera, background: Tensor, *, sh_degree: int | None = None,
                  antialiased: bool = False, draw: Rasterizer = rasterize) -> RenderOutput:
    """A model seen from a camera, without gradients (render, eval), drawn by `draw`
    (a Renderer's). background: [3] on the model's device."""
    vm, K = camera.torch(g.device, g.means.dtype)
    with torch.no_grad():
        return draw(g.means, g.quats, g.log_scales, g.opacity_logits, g.sh, vm, K,
                    camera.width, camera.height, background, sh_degree=sh_degree, antialiased=antialiased)
