"""Image models: what lies between the rendered scene and a training photo, learnt per
photo. The loop calls one at a single point, where a render meets its photo
(`ImageModel.shade`); TrainState keeps its parameters beside the Gaussians (trained and
all-reduced with them), its optimiser and its checkpoint state. A new one (a bilateral
grid, as gsplat and brush ship) is a subclass made in `make_image_model`: the loop and
TrainState do not change. Held-out views, eval and every exported file see the scene
alone. `ImageModel` itself is the identity (`--appearance none`).

`train --appearance exposure`: one learned affine colour transform per training image.

Photographs of one scene often differ in exposure and white balance. Fitting them
all with one set of Gaussians, training bends the geometry and the view-dependent
colour to explain the differences. Here each training image i gets a transform
[A_i | b_i] (A_i [3, 3], b_i [3]) that the rendered image passes through before the
loss: `image @ A_i^T + b_i`, as the exposure option of the original 3DGS code does.
The transforms start at [I | 0] and learn with their own Adam (learning rate decaying
exponentially, 3DGS's 0.01 -> 0.001) that steps only the transforms of the views trained
(`_CentredAdam`). Two more things keep them honest; 3DGS has none of the three:

* after every step, the part of their deviations from [I | 0] that varies smoothly over
  the camera positions (the `smooth` x n smoothest modes of the cameras' graph, the first
  being the constant) is taken out. The scene's colours and the transforms' common part
  are interchangeable (a brighter scene seen through darker transforms renders the same
  training images), so without this the scene drifts away from the photos' average
  exposure, which is what a held-out view, rendered with the identity, needs (early in
  training the transforms learn faster than the Gaussians' colours and take up any common
  error). Beyond the mean, an exposure that drifts slowly along the capture path (a phone
  sweep) is left to the scene's view-dependent colour, which carries it to the held-out
  views between the training ones; the transforms keep what changes from shot to shot
  (on fox, taking out the mean alone scored below no transforms, the smoothest few modes above:
  docs/guide.md, "Photos whose exposure varies: `--appearance exposure`");
* each step adds `reg * mean((T_i - [I | 0])^2)` for the view seen: a pull towards the
  identity, so a transform explains a photo's colour shift, not its view-dependent
  content.

The transforms are not Gaussians: they live beside the parameters in TrainState
(never in `Splats.params`, whose tensors strategy/ops.py edits row by row), in the
checkpoint, and nowhere else: held-out measurement, render, eval and every exported
file see the scene alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from torch import Tensor, nn

from ..errors import SplatError
from ..options import opt

APPEARANCE = ("none", "exposure")  # --appearance


@dataclass(frozen=True)
class ExposureConfig:
    lr: float = opt(0.01, "Adam learning rate of the transforms at step 0 (3DGS's exposure_lr_init) ...", more_than=0)
    lr_final: float = opt(0.001, "... decaying exponentially to this over `iterations` (3DGS's exposure_lr_final).",
                          more_than=0)
    reg: float = opt(0.01, "Weight of the mean squared distance of the view's [A | b] from [I | 0].", at_least=0)
    smooth: float = opt(0.15, "The smoothest round(this x n_train) modes over the cameras (at least 1, their mean) "
                        "are kept out of the transforms (fox at 2,000 steps: 0 -1.97 dB against no --appearance, 6 of "
                        "43 modes +0.57).", at_least=0, at_most=1)


def identity(n: int, device: torch.device) -> Tensor:  # -> [n, 3, 4]
    """n transforms [I | 0]."""
    return torch.eye(3, 4, device=device).expand(n, 3, 4).contiguous()


class ImageModel:
    """The identity: the render is compared with the photo as it is."""

    name: ClassVar[str] = "none"

    def shade(self, image: Tensor, view: int, step: int | None = None,  # image [H, W, 3]
              iterations: int = 1) -> tuple[Tensor, Tensor | float]:  # -> ([H, W, 3], penalty)
        """Training image `view`'s render as the photo shows it, and the model's penalty
        for it; `step` (training) also sets the model's schedule for that step of
        `iterations`, None (measuring) gives no penalty."""
        return image, 0.0

    def parameters(self) -> dict[str, nn.Parameter]:
        return {}

    def optimizers(self) -> list[torch.optim.Optimizer]:
        return []

    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, d: dict[str, Any], where: str) -> None:
        """Restore a checkpoint's state (`where` names the file in errors)."""


def make_image_model(cfg: Any, n: int, device: torch.device,
                     centres: Tensor | None) -> ImageModel:  # centres [n, 3]: the training cameras'
    """The image model a TrainConfig's --appearance names, for `n` training images."""
    return Exposure(n, cfg.exposure, device, centres) if cfg.appearance == "exposure" else ImageModel()


class Exposure(ImageModel):
    """The per-training-image transforms [n_train, 3, 4] and their optimiser."""

    name = "exposure"

    def __init__(self, n: int, cfg: ExposureConfig, device: torch.device,
                 centres: Tensor | None = None) -> None:  # centres [n, 3]: the training cameras'
        self.cfg = cfg
        self.transforms = nn.Parameter(identity(n, device))  # [n, 3, 4]
        modes = max(1, round(cfg.smooth * n))
        basis = smooth_basis(centres, modes) if centres is not None else torch.ones(n, 1) / math.sqrt(n)
        # Adam's own betas and 3DGS's epsilon, not the rank-scaled ones of TrainConfig.for_world:
        # a row steps once per time its view is trained, however many ranks share a step.
        self.optimizer = _CentredAdam([self.transforms], lr=cfg.lr, eps=1e-15, betas=(0.9, 0.999),
                                      basis=basis.to(device))

    def shade(self, image: Tensor, view: int, step: int | None = None,  # image [H, W, 3]
              iterations: int = 1) -> tuple[Tensor, Tensor | float]:
        if step is None:
            return self.apply(image, view), 0.0
        self.schedule(step, iterations)
        return self.apply(image, view), self.penalty(view)

    def parameters(self) -> dict[str, nn.Parameter]:
        return {"transforms": self.transforms}

    def optimizers(self) -> list[torch.optim.Optimizer]:
        return [self.optimizer]

    def apply(self, image: Tensor, i: int) -> Tensor:  # image [H, W, 3] -> [H, W, 3]
        """Training image `i`'s colour transform applied to a render of its view."""
        t = self.transforms[i]
        return image @ t[:, :3].T + t[:, 3]

    def penalty(self, i: int) -> Tensor:  # -> [] scalar
        """The pull of view `i`'s transform towards [I | 0]."""
        t = self.transforms[i]
        return self.cfg.reg * (t - torch.eye(3, 4, dtype=t.dtype, device=t.device)).square().mean()

    def schedule(self, step: int, iterations: int) -> None:
        """Set the learning rate of step `step`: log-linear from lr to lr_final over
        `iterations`, held at lr_final after (a compaction fine-tune)."""
        t = min(max(step / max(iterations, 1), 0.0), 1.0)
        lr = math.exp(math.log(self.cfg.lr) * (1 - t) + math.log(self.cfg.lr_final) * t)
        self.optimizer.param_groups[0]["lr"] = lr

    def state_dict(self) -> dict[str, Any]:
        return {"kind": "exposure", "transforms": self.transforms.detach(), "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, d: dict[str, Any], where: str) -> None:
        t = d.get("transforms")
        if not isinstance(t, Tensor) or tuple(t.shape) != tuple(self.transforms.shape):
            shown = tuple(t.shape) if isinstance(t, Tensor) else type(t).__name__
            raise SplatError(f"{where}: the per-image colour transforms have shape {shown}, expected "
                             f"{tuple(self.transforms.shape)} (one per training image)")
        with torch.no_grad():
            self.transforms.copy_(t)
        if isinstance(d.get("optimizer"), dict):
            self.optimizer.load_state_dict(d["optimizer"])


def smooth_basis(centres: Tensor,  # [n, 3]
                 modes: int) -> Tensor:  # -> [n, modes], orthonormal columns
    """The `modes` smoothest functions over the cameras: the eigenvectors of the lowest
    eigenvalues of the graph Laplacian with Gaussian weights exp(-d^2 / 2 sigma^2), sigma
    twice the median distance from a camera to its nearest neighbour, and fewer where not
    that many vary slowly. The first is the constant (the transforms' mean)."""
    c = centres.detach().double().cpu()
    n = c.shape[0]
    modes = max(1, min(int(modes), n))
    if modes == 1 or n < 3:
        return torch.ones(n, 1) / math.sqrt(n)
    d = torch.cdist(c, c)
    nearest = (d + torch.diag(torch.full((n,), math.inf, dtype=d.dtype))).amin(1)
    sigma = 2.0 * float(nearest.median().clamp_min(1e-12))
    w = torch.exp(-d.square() / (2 * sigma**2))
    w.fill_diagonal_(0.0)
    vals, vecs = torch.linalg.eigh(torch.diag(w.sum(1)) - w)
    # Only modes that do vary slowly: below half the mean degree (cameras all on one spot, a
    # panorama, make a complete graph whose other eigenvalues are n / (n - 1) x the degree).
    modes = max(1, min(modes, int((vals < 0.5 * w.sum(1).mean()).sum())))
    basis = vecs[:, :modes]
    basis[:, 0] = 1.0 / math.sqrt(n)  # exactly the mean (eigh's null vector, without its rounding)
    q, r = torch.linalg.qr(basis)
    return (q * torch.sign(r.diagonal())).float()  # columns as eigh gave them (QR may flip signs)


class _CentredAdam(torch.optim.Optimizer):
    """Adam on the rows (views) that have a gradient this step, then the deviations from
    [I | 0] projected off `basis` (the smooth modes: with the constant alone, every
    transform moved by one common amount so that their mean is [I | 0]).

    A row's moments and bias correction advance only when its view is trained (as a sparse
    Adam's do). torch's Adam would keep moving every row on its decaying momentum for the
    ~20 steps after its view was seen: with views coming back only every n_train steps, a
    transform then lands about 9 learning rates past where its one gradient pointed, jumps
    that far again at every visit, and the scene is fitted through the jitter (on lego the
    training loss ran well above plain training's: docs/guide.md, "Photos whose exposure
    varies: `--appearance exposure`")."""

    def __init__(self, params: Any, lr: float, eps: float, betas: tuple[float, float],
                 basis: Tensor) -> None:  # basis [n, m]: orthonormal modes removed after each step
        super().__init__(params, {"lr": lr, "eps": eps, "betas": betas})
        self.basis = basis

    @torch.no_grad()
    def step(self, closure: Any = None) -> Any:
        for group in self.param_groups:
            b1, b2 = group["betas"]
            for t in group["params"]:  # [n, 3, 4]
                if t.grad is not None:
                    rows = t.grad.flatten(1).ne(0).any(1).nonzero().squeeze(1)  # the views trained this step
                    st = self.state[t]
                    if not st or st["step"].dim() == 0:  # (first step)
                        st["step"] = torch.zeros(t.shape[0], dtype=t.dtype, device=t.device)
                        st["exp_avg"], st["exp_avg_sq"] = torch.zeros_like(t), torch.zeros_like(t)
                    g = t.grad[rows]
                    n = st["step"][rows] + 1
                    m = st["exp_avg"][rows] * b1 + g * (1 - b1)
                    v = st["exp_avg_sq"][rows] * b2 + g * g * (1 - b2)
                    st["step"][rows], st["exp_avg"][rows], st["exp_avg_sq"][rows] = n, m, v
                    m_hat = m / (1 - b1 ** n)[:, None, None]
                    v_hat = v / (1 - b2 ** n)[:, None, None]
                    t[rows] -= group["lr"] * m_hat / (v_hat.sqrt() + group["eps"])
                dev = (t - torch.eye(3, 4, dtype=t.dtype, device=t.device)).flatten(1)  # [n, 12]
                t -= (self.basis @ (self.basis.T @ dev)).view_as(t)
        return None
