"""Image metrics: PSNR and SSIM on [0, 1] images, differentiable (SSIM is also the
training loss's D-SSIM term).

SSIM is Wang et al.'s: an 11x11 Gaussian window with sigma = 1.5, constants
K1 = 0.01, K2 = 0.03, data range 1, population (not sample) covariance, averaged
over channels and over the "valid" region (the border of 5 pixels that a
full-size filter would pad is excluded), which is exactly what
`skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5,
use_sample_covariance=False, data_range=1.0, channel_axis=-1)` computes.

With a mask `keep` ([H, W] bool, False = masked out) both scores ignore the masked
pixels entirely: PSNR is over the kept pixels; SSIM sets the masked pixels of both
images to 0 and averages the map over the windows centred on kept pixels, so
neither score, nor its gradient, depends on a masked pixel's value.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
_C1 = (0.01 * 1.0) ** 2
_C2 = (0.03 * 1.0) ** 2


def psnr(pred: Tensor, gt: Tensor, keep: Tensor | None = None) -> Tensor:  # [..., H, W, C] each, keep [H, W] -> dB
    """10 log10(1 / MSE) for images in [0, 1] (MSE over the kept pixels when `keep` is given)."""
    err = (pred.to(torch.float64) - gt.to(torch.float64)) ** 2
    if keep is None:
        mse = torch.mean(err)
    else:
        mse = (err * keep[..., None]).sum() / (keep.sum() * err.shape[-1]).clamp_min(1)
    return 10.0 * torch.log10(1.0 / mse.clamp_min(1e-20))


def _gauss_1d(dtype: torch.dtype, device: torch.device) -> Tensor:  # [11]
    r = SSIM_WINDOW // 2
    x = torch.arange(-r, r + 1, dtype=torch.float64)
    g = torch.exp(-0.5 * (x / SSIM_SIGMA) ** 2)
    return (g / g.sum()).to(dtype=dtype, device=device)


def _window(n: int, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:  # [n, 1, 1, 11], [n, 1, 11, 1]
    g = _gauss_1d(dtype, device)
    return (g.view(1, 1, 1, -1).expand(n, 1, 1, SSIM_WINDOW).contiguous(),
            g.view(1, 1, -1, 1).expand(n, 1, SSIM_WINDOW, 1).contiguous())


def _filter(maps: Tensor) -> Tensor:  # [n, H, W] -> [n, H-10, W-10]: the window over the valid region
    # On the CPU, the separable window as matrix products (`_Valid`); elsewhere (CUDA), two depthwise
    # convolutions.
    return _Valid.apply(maps) if maps.device.type == "cpu" else _conv(maps)


def _filter_t(maps: Tensor) -> Tensor:  # [n, H-10, W-10] -> [n, H, W]: the transpose of _filter
    # The window is symmetric, so the adjoint of its valid correlation is the same correlation over
    # the maps padded by its border on every side.
    if maps.device.type != "cpu":
        return _conv_t(maps)
    e = SSIM_WINDOW - 1
    return _Valid.apply(F.pad(maps, (e, e, e, e)))


# The CPU's window: each axis as products with a banded matrix of the 11 taps, a block of output rows
# (columns) at a time, each from its block plus the window's border. A GEMM does 2-4x the
# multiply-adds of 11 shifted adds per axis but runs them in cache: SSIM's forward filter on fox's
# 270x480 took 4.9 ms against 10.6 (lego's 480x480: 9.0 against 20.1; its transpose 3.6 against 6.2)
# on an Intel Xeon (family 6 model 207), one thread. Blocks of 16 rows and 32 columns measured best.
_ROWS, _COLS = 16, 32


def _band(b: int, dtype: torch.dtype, device: torch.device) -> Tensor:  # [b, b + 10]
    """Row i holds the window's taps at columns i..i+10: output i of a block from its b + 10 inputs."""
    idx = torch.arange(b, device=device)[:, None] + torch.arange(SSIM_WINDOW, device=device)
    band = torch.zeros(b, b + SSIM_WINDOW - 1, dtype=dtype, device=device)
    return band.scatter_(1, idx, _gauss_1d(dtype, device).expand(b, -1))


class _Valid(torch.autograd.Function):
    """The CPU's window over the valid region (`_products`), differentiable: it is linear, and its
    adjoint is `_filter_t`."""

    @staticmethod
    def forward(ctx, maps):
        return _products(maps)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g):
        return _filter_t(g)


def _products(maps: Tensor) -> Tensor:  # [n, H, W] -> [n, H-10, W-10]
    """The window as matrix products: down the columns, blocks of _ROWS output rows (overlapping
    windows of the map's rows, read in place), then along the rows, blocks of _COLS output columns."""
    e = SSIM_WINDOW - 1
    maps = maps.contiguous()
    n, H, W = maps.shape
    h, w = H - e, W - e
    a = maps.new_empty(n, h, W)
    rows = _band(_ROWS, maps.dtype, maps.device)  # [R, R + 10]
    full, tail = divmod(h, _ROWS)
    for i in range(n):
        m = maps[i]
        if full:
            windows = m.as_strided((full, _ROWS + e, W), (_ROWS * W, W, 1))  # [full, R + 10, W]
            torch.matmul(rows, windows, out=a[i, : full * _ROWS].view(full, _ROWS, W))
        if tail:
            torch.mm(rows[:tail, : tail + e], m[full * _ROWS :], out=a[i, full * _ROWS :])
    out = maps.new_empty(n, h, w)
    cols = _band(_COLS, maps.dtype, maps.device).T  # [C + 10, C]
    a2, o2 = a.view(n * h, W), out.view(n * h, w)
    for j in range(0, w, _COLS):
        b = min(_COLS, w - j)
        torch.mm(a2[:, j : j + b + e], cols[: b + e, :b], out=o2[:, j : j + b])
    return out


def _conv(maps: Tensor) -> Tensor:  # _filter as two depthwise convolutions (all maps as channels of one image)
    wx, wy = _window(maps.shape[0], maps.dtype, maps.device)
    return F.conv2d(F.conv2d(maps.unsqueeze(0), wx, groups=maps.shape[0]), wy, groups=maps.shape[0])[0]


def _conv_t(maps: Tensor) -> Tensor:  # _filter_t as two transposed depthwise convolutions
    wx, wy = _window(maps.shape[0], maps.dtype, maps.device)
    t = F.conv_transpose2d(maps.unsqueeze(0), wy, groups=maps.shape[0])
    return F.conv_transpose2d(t, wx, groups=maps.shape[0])[0]


def _parts(x: Tensor, y: Tensor) -> tuple[Tensor, ...]:  # [C, H, W] each -> each [C, H-10, W-10]
    """The filtered means and SSIM's four factors: S = (a1 a2) / (b1 b2)."""
    C = x.shape[0]
    mu_x, mu_y, e_xx, e_yy, e_xy = _filter(torch.cat([x, y, x * x, y * y, x * y], dim=0)).split(C, dim=0)
    var_x = e_xx - mu_x * mu_x
    var_y = e_yy - mu_y * mu_y
    cov = e_xy - mu_x * mu_y
    a1, a2 = 2 * mu_x * mu_y + _C1, 2 * cov + _C2
    b1, b2 = mu_x * mu_x + mu_y * mu_y + _C1, var_x + var_y + _C2
    return mu_x, mu_y, a1, a2, b1, b2


def _images(pred: Tensor, gt: Tensor) -> tuple[Tensor, Tensor]:  # [H, W, C] each -> [C, H, W] each
    if pred.shape != gt.shape or pred.dim() != 3:
        raise ValueError(f"ssim expects two [H, W, C] images of one shape, got {tuple(pred.shape)} and {tuple(gt.shape)}")
    H, W, _ = pred.shape
    if H < SSIM_WINDOW or W < SSIM_WINDOW:
        raise ValueError(f"ssim needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels, got {W}x{H}")
    return pred.permute(2, 0, 1), gt.permute(2, 0, 1).to(pred.dtype)


def ssim_map(pred: Tensor, gt: Tensor) -> Tensor:
    """pred, gt: [H, W, C] in [0, 1]. Returns the SSIM map [C, H-10, W-10]."""
    _, _, a1, a2, b1, b2 = _parts(*_images(pred, gt))
    return (a1 * a2) / (b1 * b2)


class _MeanSsim(torch.autograd.Function):
    """Mean SSIM (over `w` [H-10, W-10], the windows' weights, when given) with its gradient in closed
    form: d/dx = W^T(dS/dmu_x) + 2 x W^T(dS/de_xx) + y W^T(dS/de_xy), W the window filter, so the
    backward filters three maps per channel where autograd's filters all five moments."""

    @staticmethod
    def forward(ctx, pred, gt, w):
        x, y = _images(pred, gt)
        mu_x, mu_y, a1, a2, b1, b2 = _parts(x, y)
        S = (a1 * a2) / (b1 * b2)  # [C, h, w]
        if w is None:
            value, scale = S.mean(), torch.full((), 1.0 / S.numel(), dtype=S.dtype, device=S.device)
        else:
            denom = (w.sum() * S.shape[0]).clamp_min(1)
            value, scale = (S * w).sum() / denom, w / denom
        ctx.save_for_backward(x, y, mu_x, mu_y, a1, a2, b1, b2, S, scale)
        return value

    @staticmethod
    def backward(ctx, g):
        x, y, mu_x, mu_y, a1, a2, b1, b2, S, scale = ctx.saved_tensors
        gS = g * scale  # d loss / d S, per window
        q = gS / (b1 * b2)
        d_e_xy, d_e_uu = 2 * q * a1, -gS * S / b2  # (the same for x and y)
        out = []
        for need, u, v, mu_u, mu_v in ((ctx.needs_input_grad[0], x, y, mu_x, mu_y), (ctx.needs_input_grad[1], y, x, mu_y, mu_x)):
            if not need:
                out.append(None)
                continue
            d_mu = 2 * q * (mu_v * (a2 - a1) - S * mu_u * (b2 - b1))
            C = u.shape[0]
            t_mu, t_uu, t_uv = _filter_t(torch.cat([d_mu, d_e_uu, d_e_xy], dim=0)).split(C, dim=0)
            out.append((t_mu + 2 * u * t_uu + v * t_uv).permute(1, 2, 0))  # [H, W, C]
        return out[0], out[1], None


def ssim(pred: Tensor, gt: Tensor, keep: Tensor | None = None) -> Tensor:  # [H, W, C] each, keep [H, W] -> scalar
    """Mean SSIM over the valid region and the channels (and the kept pixels: module docstring)."""
    gt = gt.to(pred.dtype)
    if keep is None:
        return _MeanSsim.apply(pred, gt, None)
    k = keep[..., None].to(pred.dtype)
    r = SSIM_WINDOW // 2
    return _MeanSsim.apply(pred * k, gt * k, keep[r:-r, r:-r].to(pred.dtype))  # weights: the windows' centres


def _affine_fit(x: Tensor, y: Tensor) -> Tensor:  # [P, 3] float64 each -> [4, 3]
    """The affine colour transform (3x3 matrix and offset, as rows of [x, 1] @ w) that brings
    `x` closest to `y` in least squares (gelsd: the minimum-norm solution, also for a flat
    render, a rank-deficient system)."""
    a = torch.cat([x, torch.ones_like(x[:, :1])], dim=1)  # [P, 4]
    return torch.linalg.lstsq(a.cpu(), y.cpu(), driver="gelsd").solution.to(x.device)


def _apply_affine(x: Tensor, w: Tensor) -> Tensor:  # [..., 3] float64, [4, 3] -> [..., 3] in [0, 1]
    return (x @ w[:3] + w[3]).clamp(0, 1)


def color_fit(pred: Tensor, gt: Tensor, keep: Tensor | None = None) -> Tensor:  # [H, W, 3] each, keep [H, W]
    """`pred` through the affine colour transform (3x3 matrix and offset) that brings it
    closest to `gt` in least squares over the image's (kept) pixels (solved in float64),
    clamped to [0, 1]. It removes what train --appearance exposure models (exposure,
    white balance), so what error is left comes from the geometry and the colours."""
    x = pred.detach().to(torch.float64).reshape(-1, 3)
    y = gt.detach().to(torch.float64).reshape(-1, 3)
    rows = slice(None) if keep is None else keep.reshape(-1).to(x.device)
    return _apply_affine(x, _affine_fit(x[rows], y[rows])).reshape(pred.shape)


def half_fit(pred: Tensor, gt: Tensor, keep: Tensor | None = None
             ) -> tuple[Tensor, Tensor, Tensor | None]:  # [H, W, 3] each, keep [H, W] -> right halves
    """The appearance-compensated protocol for photo collections (NeRF-W's): the affine colour
    transform (what --appearance exposure learns per photo) is fitted on the view's left half
    (columns below W // 2; kept pixels only) and applied to its right half, which is scored:
    the fit sees none of the pixels it is judged on. Returns the fitted right half of `pred`
    (float64), and the right halves of `gt` and `keep`."""
    c = pred.shape[1] // 2
    x = pred.detach().to(torch.float64)
    y = gt.detach().to(torch.float64)
    xl, yl = x[:, :c].reshape(-1, 3), y[:, :c].reshape(-1, 3)
    if keep is not None:
        rows = keep[:, :c].reshape(-1).to(x.device)
        xl, yl = xl[rows], yl[rows]
    w = _affine_fit(xl, yl)
    return _apply_affine(x[:, c:], w), y[:, c:], None if keep is None else keep[:, c:]


def psnr_color_fit(pred: Tensor, gt: Tensor, keep: Tensor | None = None) -> float:  # [H, W, 3] each -> dB
    """PSNR after the per-view least-squares colour fit (`color_fit`), over the kept pixels
    when `keep` [H, W] is given: never below `psnr`."""
    return float(psnr(color_fit(pred, gt, keep), gt, keep))
