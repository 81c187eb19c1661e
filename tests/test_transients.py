"""--transients ignore (splatcli/train/transients.py): a region of a photo that disagrees with the
render (a passer-by) leaves the loss; scattered errors (edges, texture, noise) and thin lines stay."""

from __future__ import annotations

import torch

from splatcli.train.loss import photometric_loss
from splatcli.train.transients import TransientsConfig, kept_pixels

CFG = TransientsConfig()


def _scene(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:  # image, target [96, 128, 3]
    g = torch.Generator().manual_seed(seed)
    image = torch.rand(96, 128, 3, generator=g)
    target = (image + 0.02 * torch.randn(96, 128, 3, generator=g)).clamp(0, 1)
    return image, target


def test_a_passer_by_leaves_the_loss_and_scattered_errors_stay():
    image, target = _scene()
    target[30:70, 40:60] = 1.0 - image[30:70, 40:60]  # a person: 800 px that no view agrees with
    target[10, :] = 1.0 - image[10, :]  # a thin bright line (a missed edge): one row
    g = torch.Generator().manual_seed(1)
    specks = torch.rand(96, 128, generator=g) < 0.03  # texture the model misses here and there
    specks[8:13] = False  # (not touching the line: a speck beside it makes a 3x3 of mostly outliers)
    target[specks] = 1.0 - image[specks]
    keep = kept_pixels(image, target, None, CFG)
    assert keep.shape == (96, 128) and keep.dtype == torch.bool
    person = keep[30:70, 40:60]
    assert person.float().mean() < 0.1, person.float().mean()  # nearly all of it left out
    assert keep[10].all() and keep[specks & ~_box(28, 72, 38, 62)].all()  # (beside the person: its neighbours)
    assert keep[~_box(28, 72, 38, 62)].float().mean() > 0.99  # little else goes


def _box(y0: int, y1: int, x0: int, x1: int) -> torch.Tensor:
    m = torch.zeros(96, 128, dtype=torch.bool)
    m[y0:y1, x0:x1] = True
    return m


def test_noise_alone_leaves_nothing_out_and_a_mask_stays_out():
    image, target = _scene(2)
    assert kept_pixels(image, target, None, CFG).float().mean() > 0.995
    mask = torch.ones(96, 128, dtype=torch.bool)
    mask[:, :20] = False  # a mask's pixels (--mask-mode ignore) stay out, and bound no quantile
    target[:, :20] = 1.0 - image[:, :20]
    keep = kept_pixels(image, target, mask, CFG)
    assert not keep[:, :20].any() and keep[:, 20:].float().mean() > 0.995
    assert not kept_pixels(image, target, torch.zeros(96, 128, dtype=torch.bool), CFG).any()


def test_left_out_pixels_get_no_gradient():
    image, target = _scene(3)
    target[30:70, 40:60] = 1.0 - image[30:70, 40:60]
    x = image.clone().requires_grad_(True)
    keep = kept_pixels(x, target, None, CFG)
    photometric_loss(x, target, 0.2, keep).backward()
    inner = ~keep  # SSIM's 11x11 windows reach 5 px: only pixels that far inside the region are untouched
    inner[:, :] &= torch.nn.functional.max_pool2d((keep[None, None]).float(), 11, 1, 5)[0, 0] == 0
    assert inner.sum() > 100 and x.grad[inner].abs().max() == 0
