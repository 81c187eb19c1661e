"""The differentiable Gaussian rasterizer: one vectorised PyTorch path for CPU and CUDA.

    out = rasterize(means, quats, log_scales, opacity_logits, sh, viewmat, K, W, H)

Forward model (3DGS, exactly): see `projection.py` (per Gaussian) and `composite.py`
(per pixel). Gradients reach every raw parameter, the returned `means2d` (call
`out.means2d.retain_grad()` before backward to read it) and the background.
"""

from __future__ import annotations

import math
import time

import torch
from torch import Tensor

from . import timing
from .blocks import BlockTuner, Meter, choose_block, estimate_pairs, footprint_extents
from .composite import composite, make_plan, median_depth, weight_sums
from .output import RenderOutput
from .projection import NEAR, TILE, Projection, project

# Above this many (Gaussian, block) pairs the image is rendered in bands of tile rows,
# each planned on its own and re-planned in backward, so memory stays bounded
# (~40 bytes per pair while planning).
PAIR_BUDGET = 1 << 25


def _check(name: str, x: Tensor, shape: tuple, dtype: torch.dtype | None, device: torch.device | None,
           values: bool) -> None:
    if not isinstance(x, Tensor):
        raise ValueError(f"rasterize: {name} must be a tensor, got {type(x).__name__}")
    if x.dim() != len(shape) or any(s is not None and s != d for s, d in zip(shape, x.shape)):
        want = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
        raise ValueError(f"rasterize: {name} has shape {list(x.shape)}, expected {want}")
    if dtype is not None and x.dtype != dtype:
        raise ValueError(f"rasterize: {name} is {x.dtype}, expected {dtype} like means")
    if device is not None and x.device != device:
        raise ValueError(f"rasterize: {name} is on {x.device}, expected {device} like means")
    if values and not bool(torch.isfinite(x.detach()).all()):  # a host sync
        raise ValueError(f"rasterize: {name} contains non-finite values (NaN or inf)")


def validate(means: Tensor, quats: Tensor, log_scales: Tensor, opacity_logits: Tensor, sh: Tensor, viewmat: Tensor,
             K: Tensor, width: int, height: int, background: Tensor | None, sh_degree: int | None, near: float,
             check: bool) -> tuple[int, int, Tensor, int]:
    """rasterize's argument checks (every renderer's): width, height, the background
    (black when None) and the SH degree to draw, or ValueError naming the parameter."""
    if not isinstance(means, Tensor) or means.dim() != 2 or means.shape[1] != 3:
        raise ValueError(f"rasterize: means must be a [N, 3] tensor, got {getattr(means, 'shape', type(means))}")
    if not means.is_floating_point():
        raise ValueError(f"rasterize: means must be floating point, got {means.dtype}")
    dt, dev, N = means.dtype, means.device, means.shape[0]
    if int(width) != width or int(height) != height or width < 1 or height < 1:
        raise ValueError(f"rasterize: width and height must be positive integers, got {width} x {height}")
    width, height = int(width), int(height)
    if not (isinstance(near, (int, float)) and math.isfinite(near) and near > 0):
        raise ValueError(f"rasterize: near must be a positive finite number, got {near}")
    _check("means", means, (N, 3), dt, dev, check)
    _check("quats", quats, (N, 4), dt, dev, check)
    _check("log_scales", log_scales, (N, 3), dt, dev, check)
    _check("opacity_logits", opacity_logits, (N,), dt, dev, check)
    _check("sh", sh, (N, None, 3), dt, dev, check)
    _check("viewmat", viewmat, (4, 4), dt, dev, check)
    _check("K", K, (3, 3), dt, dev, check)
    if background is None:
        background = torch.zeros(3, dtype=dt, device=dev)
    _check("background", background, (3,), dt, dev, check)
    nb = sh.shape[1]
    d_have = int(round(math.sqrt(nb))) - 1
    if (d_have + 1) ** 2 != nb or d_have > 3:
        raise ValueError(f"rasterize: sh has {nb} coefficients per channel; expected (d+1)^2 for d in 0..3")
    if sh_degree is None:
        sh_degree = d_have
    if not 0 <= sh_degree <= d_have:
        raise ValueError(f"rasterize: sh_degree {sh_degree} is outside 0..{d_have} (what sh holds)")
    if check and not (float(K[0, 0].detach()) > 0 and float(K[1, 1].detach()) > 0):
        raise ValueError("rasterize: K must have positive focal lengths K[0,0], K[1,1]")
    return width, height, background, sh_degree


def rasterize(
    means: Tensor,  # [N, 3] world
    quats: Tensor,  # [N, 4] w, x, y, z, any norm
    log_scales: Tensor,  # [N, 3]
    opacity_logits: Tensor,  # [N]
    sh: Tensor,  # [N, (d+1)^2, 3] DC first
    viewmat: Tensor,  # [4, 4] world -> camera (OpenCV)
    K: Tensor,  # [3, 3] intrinsics, px
    width: int,
    height: int,
    background: Tensor | None = None,  # [3] or None (black)
    *,
    sh_degree: int | None = None,
    near: float = 0.2,
    antialiased: bool = False,
    block: int | str | BlockTuner = "auto",
    check: bool = True,
) -> RenderOutput:
    """Render N Gaussians into a width x height image.

    Returns image [H, W, 3] (C + T * background), alpha [H, W] (1 - T), depth [H, W]
    (sum of blending weight times view depth), and per Gaussian means2d [N, 2] px,
    radii [N] int32, visible [N] bool, depths [N] view z. `block` (4, 8, 16, "auto" for
    the cost model's pick, or a BlockTuner that measures the pick on this machine, render
    after render: render/blocks.py) is a speed knob only: the picture does not depend on it.
    Raises ValueError naming the parameter for bad shapes or non-finite values. A caller
    that has checked the values already (the training loop checks every gradient) passes
    check=False: shapes, dtypes and devices are still checked, but not the values (finite
    inputs, positive focal lengths), which costs a host sync per tensor.
    """
    width, height, background, sh_degree = validate(means, quats, log_scales, opacity_logits, sh, viewmat, K,
                                                    width, height, background, sh_degree, near, check)
    tuner = block if isinstance(block, BlockTuner) else None
    if tuner is None and block not in (4, 8, 16, "auto"):
        raise ValueError(f"rasterize: block must be 4, 8, 16, 'auto' or a BlockTuner, got {block!r}")

    t0 = time.perf_counter()
    pr = project(means, quats, log_scales, opacity_logits, sh, viewmat, K, width, height, sh_degree, near, antialiased)
    t1 = time.perf_counter()
    timing.add("projection", t1 - t0)
    meter, ext, chunk = None, footprint_extents(pr.footprint), None
    if tuner is not None and means.device.type == "cpu":  # timing CUDA work would need syncs
        timed = not tuner.backward or torch.is_grad_enabled()  # else nothing will report a backward
        (block, chunk), meter = tuner.choose(ext, width, height, measure=timed)
    elif not isinstance(block, int):
        block = choose_block(ext, width, height)
    bands = _bands(height, estimate_pairs(ext, block))
    if len(bands) == 1:
        backward = meter is not None and tuner is not None and tuner.backward
        image, alpha, depth = _whole(pr, width, height, block, chunk, background, meter, backward, t1)
    else:
        image, alpha, depth = _banded(pr, width, height, block, background, bands)
    return RenderOutput(image=image, alpha=alpha, depth=depth, means2d=pr.means2d, radii=pr.radii,
                        visible=pr.visible, depths=pr.depths)


def _whole(pr: Projection, width: int, height: int, block: int, chunk: int | None, background: Tensor,
           meter: Meter | None, backward: bool, t1: float) -> tuple[Tensor, Tensor, Tensor]:
    """The image in one plan: planned, then composited; the stage clock and the tuner's meter told
    (from `t1`, when projection ended; with `backward`, the meter's last reading is the backward's)."""
    plan = make_plan(pr.footprint, width, height, block, chunk_elems=chunk)
    t2 = time.perf_counter()
    timing.add("planning", t2 - t1)
    timing.add("pairs", plan.n_pairs)
    plan.meter = meter if backward else None
    image, alpha, depth = composite(plan, pr.means2d, pr.conics, pr.opacities, pr.colors, pr.depths, background)
    t3 = time.perf_counter()
    timing.add("compositing", t3 - t2)
    if meter is not None:
        meter.add(t3 - t1, last=not backward)
    return image, alpha, depth


def _bands(height: int, est: float) -> list[tuple[int, int]]:
    """The image rows [y0, y1) drawn one band after another: one band, or, when the plan
    would hold more than PAIR_BUDGET pairs, bands of whole tile rows (y0 a multiple of 16,
    so the tile rule is unchanged), each planned on its own so memory stays bounded."""
    nbands = min(math.ceil(est / PAIR_BUDGET), math.ceil(height / TILE)) if est > PAIR_BUDGET else 1
    band = math.ceil(math.ceil(height / nbands) / TILE) * TILE
    return [(y0, min(height, y0 + band)) for y0 in range(0, height, band)]


def _shift(pr, y0: int) -> Tensor:  # [N, 2] the projected means in the coordinates of the band from row y0
    return pr.means2d - torch.tensor([0.0, float(y0)], dtype=pr.means2d.dtype, device=pr.means2d.device)


def _banded(pr, width, height, block, background, bands):
    """Render the bands one after another, each planned on its own and re-planned in
    backward: the same model on the rows [y0, y1), means shifted by -y0."""
    outs = []
    for y0, y1 in bands:
        def planner(rows=(y0, y1)):
            return make_plan(pr.footprint, width, height, block, rows)

        outs.append(composite(planner, _shift(pr, y0), pr.conics, pr.opacities, pr.colors, pr.depths, background))
    return tuple(torch.cat([o[i] for o in outs], 0) for i in range(3))


def _planned_bands(pr: Projection, width: int, height: int):
    """A forward-only render's plans, one per band (rasterize's bands, the cost model's block), each
    with the projected means in its band's coordinates [N, 2]."""
    fp = pr.footprint
    ext = footprint_extents(fp)
    block = choose_block(ext, width, height)
    for y0, y1 in _bands(height, estimate_pairs(ext, block)):
        yield make_plan(fp, width, height, block, (y0, y1)), _shift(pr, y0)


@torch.no_grad()
def render_surface(
    means: Tensor,  # [N, 3] world
    quats: Tensor,  # [N, 4]
    log_scales: Tensor,  # [N, 3]
    opacity_logits: Tensor,  # [N]
    sh: Tensor,  # [N, (d+1)^2, 3], every band drawn
    viewmat: Tensor,  # [4, 4] world -> camera
    K: Tensor,  # [3, 3] px
    width: int,
    height: int,
    *,
    antialiased: bool = False,
) -> tuple[Tensor, Tensor, Tensor]:  # median depth [H, W] (0 where T never crosses 0.5), image [H, W, 3] over black, alpha [H, W]
    """What meshing fuses from one camera: the median depth (composite.median_depth) and the
    picture, from one projection and one plan per band (rasterize's bands)."""
    d = int(round(math.sqrt(sh.shape[1]))) - 1
    pr = project(means, quats, log_scales, opacity_logits, sh, viewmat, K, width, height, d, NEAR, antialiased)
    black = means.new_zeros(3)
    out = []
    for plan, m2 in _planned_bands(pr, width, height):
        image, alpha, _ = composite(plan, m2, pr.conics, pr.opacities, pr.colors, pr.depths, black)
        out.append((median_depth(plan, m2, pr.conics, pr.opacities, pr.depths), image, alpha))
    return tuple(torch.cat(x, 0) for x in zip(*out))  # type: ignore[return-value]


@torch.no_grad()
def render_weights(
    means: Tensor,  # [N, 3] world
    quats: Tensor,  # [N, 4]
    log_scales: Tensor,  # [N, 3]
    opacity_logits: Tensor,  # [N]
    viewmat: Tensor,  # [4, 4] world -> camera
    K: Tensor,  # [3, 3] px
    width: int,
    height: int,
) -> Tensor:  # [N] sum over the view's pixels of alpha_i T_i
    """Each Gaussian's blending weight over one view (render/weights.py), from a forward pass:
    one projection, and one plan per band (rasterize's bands)."""
    sh = means.new_zeros(means.shape[0], 1, 3)
    pr = project(means, quats, log_scales, opacity_logits, sh, viewmat, K, width, height, 0, NEAR)
    total = means.new_zeros(means.shape[0])
    for plan, m2 in _planned_bands(pr, width, height):
        total += weight_sums(plan, m2, pr.conics, pr.opacities)
    return total
