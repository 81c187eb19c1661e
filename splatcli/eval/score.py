"""The one way a render is scored against its photograph, for training's held-out log
(train/loop.py) and `splatcli eval` alike.

`load_target` gives a view's photograph as training fits it and both scores compare
against it (the masks applied as the run used them); `score_image` scores a render
against it: PSNR and SSIM (metrics.py) over the kept pixels, optionally the PSNR
after a per-view colour fit and LPIPS, everything in float64.

Quantisation is an explicit argument of `score_image`:

* "8-bit": the render clamped to [0, 1] and rounded to steps of 1/255, as a PNG
  stores it (and as the original 3DGS metrics script scores saved renders). Both
  reports use it (`REPORTED`), so train.json's held-out PSNR and eval.json's are
  one figure: equal for the same model and views.
* "none": clamped to [0, 1] only. The held-out log used this before
  `quantisation` was recorded (an old train summary without the field).

8-bit rounding adds error of at most half a step per channel: it matters only at
high PSNR (its own noise alone scores 58.9 dB).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..inputs.images import load_mask, load_rgb, paint_masked
from ..project import Project
from .metrics import half_fit, psnr, psnr_color_fit, ssim

QUANTISATIONS = ("8-bit", "none")
REPORTED = "8-bit"  # what train.json (held-out log) and eval.json score


@dataclass(frozen=True)
class Scores:
    psnr: float  # dB
    ssim: float
    lpips: float | None = None  # when an LPIPS scorer was given (None also below its size)
    psnr_color_fit: float | None = None  # dB after the view's least-squares colour fit (metrics.color_fit)
    compensated: HalfScores | None = None  # appearance fitted on the left half, scored on the right (metrics.half_fit)


@dataclass(frozen=True)
class HalfScores:
    """A view's scores under the appearance-compensated protocol (metrics.half_fit): its right half."""

    psnr: float  # dB
    ssim: float
    lpips: float | None = None


def check_quantisation(quantisation: str) -> None:
    if quantisation not in QUANTISATIONS:
        raise ValueError(f"quantisation {quantisation!r} is not one of {', '.join(QUANTISATIONS)}")


def quantise(img: Tensor, quantisation: str) -> Tensor:  # [H, W, C] -> [H, W, C] float64 in [0, 1]
    """A render as it is scored: clamped to [0, 1], and for "8-bit" rounded to 1/255 steps."""
    check_quantisation(quantisation)
    img = img.detach().clamp(0, 1)
    if quantisation == "8-bit":
        return (img * 255).round().to(torch.float64) / 255.0
    return img.to(torch.float64)


def unit(target: Tensor) -> Tensor:  # [H, W, C] uint8 or float -> float64 in [0, 1]
    """A photograph as float64: uint8 values divided by 255 (exactly as eval's loader does)."""
    if target.dtype == torch.uint8:
        return target.to(torch.float64) / 255.0
    return target.detach().to(torch.float64)


def score_image(pred: Tensor, target: Tensor, keep: Tensor | None = None, *, quantisation: str,
                color_fit: bool = False, compensated: bool = False,
                lpips: Callable[[Tensor, Tensor], float | None] | None = None) -> Scores:
    """Score one render. pred [H, W, 3] in [0, 1] (any float dtype, any device); target
    [H, W, 3], uint8 or in [0, 1]; keep [H, W] bool, False = masked out (None: every pixel).
    The render is quantised (`quantisation`, module docstring) and moved to the target's
    device. PSNR and SSIM are over the kept pixels (metrics.py); LPIPS sees the photograph's
    own pixels where masked, so they add nothing."""
    t = unit(target)
    p = quantise(pred, quantisation).to(t.device)
    if keep is not None:
        keep = keep.to(t.device)
    lp = _lpips_kept(lpips, p, t, keep) if lpips is not None else None
    half = None
    if compensated:  # (its 8-bit render fitted in float64: the fit is part of the protocol, not of the image)
        hp, ht, hk = half_fit(p, t, keep)
        hl = _lpips_kept(lpips, hp, ht, hk) if lpips is not None else None
        half = HalfScores(psnr=float(psnr(hp, ht, hk)), ssim=float(ssim(hp, ht, hk)), lpips=hl)
    return Scores(psnr=float(psnr(p, t, keep)), ssim=float(ssim(p, t, keep)), lpips=lp,
                  psnr_color_fit=psnr_color_fit(p, t, keep) if color_fit else None, compensated=half)


def _lpips_kept(lpips: Callable[[Tensor, Tensor], float | None], pred: Tensor, target: Tensor,
                keep: Tensor | None) -> float | None:  # [H, W, 3] each, keep [H, W]
    """LPIPS with the photograph's own pixels where masked, so they add nothing."""
    return lpips(torch.where(keep[..., None], pred, target) if keep is not None else pred, target)


def load_target(project: Project, name: str, size: tuple[int, int], background: tuple[float, float, float],
                mask_mode: str) -> tuple[np.ndarray, np.ndarray | None]:  # -> [H, W, 3] uint8, [H, W] bool
    """Image `name` as training fits it and the scores compare against it: the photograph
    (inputs/images.load_rgb) at `size` = (width, height) and its kept pixels, by `mask_mode`
    (resolved: Project.mask_mode): "ignore": the mask beside it; "background": mask files'
    masked pixels painted in `background` (inputs/images.paint_masked; with alpha masks the
    photograph already is composited over it) and no mask; "off": the photograph alone."""
    rgb = load_rgb(project.images_dir / name, size, background)
    if mask_mode == "ignore" or (mask_mode == "background" and project.mask_source() == "files"):
        keep = load_mask(project.mask_path(name), size)
        if mask_mode == "background":
            return paint_masked(rgb, keep, background), None
        return rgb, keep
    return rgb, None
