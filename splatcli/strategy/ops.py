"""Edits of the Gaussian set that keep parameters, Adam state and strategy state in step.

Growing, pruning or resetting rows must edit the Adam moments (`exp_avg`,
`exp_avg_sq`) the same way, or the optimiser would apply stale momentum to the
wrong Gaussian, and every strategy's per-Gaussian rows (`RowState.ROWS`) too.
`_edit` is the one function that replaces parameters and moments; `keep`, `append`
and `replace_rows` also edit the strategy rows; `nudge` and `assign` move parameters in place;
nothing else in splatcli touches any of them.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import torch
from torch import Tensor, nn

from ..render.projection import quat_rotate, unit_quat
from .base import Splats

_MOMENTS = ("exp_avg", "exp_avg_sq")


@torch.no_grad()
def _edit(
    splats: Splats,
    param_fn: Callable[[str, Tensor], Tensor],  # (name, value [N, ...]) -> new value [M, ...]
    moment_fn: Callable[[str, Tensor], Tensor],  # (name, moment [N, ...]) -> new moment [M, ...]
    row_fn: Callable[[Tensor], Tensor] | None,  # strategy row [N, ...] -> [M, ...]; None: rows unchanged
    names: Iterable[str] | None = None,
) -> None:
    """Replace each named parameter by `param_fn(name, p)` and each of its Adam moments
    by `moment_fn(name, m)`, rebinding the optimiser to the new tensor, and every
    strategy row by `row_fn(row)`. The Adam `step` counter is per tensor and kept."""
    params, optimizers = splats.params, splats.optimizers
    for name in list(params if names is None else names):
        old = params[name]
        new = nn.Parameter(param_fn(name, old.detach()), requires_grad=old.requires_grad)
        opt = optimizers.get(name)
        if opt is not None:
            for group in opt.param_groups:
                for i, p in enumerate(group["params"]):
                    if p is not old:
                        continue
                    state = opt.state.pop(old, None)
                    if state:
                        for k in _MOMENTS:
                            if k in state:
                                state[k] = moment_fn(name, state[k])
                        opt.state[new] = state
                    group["params"][i] = new
        params[name] = new
    if row_fn is not None:
        for st in splats.states:
            for field_name in st.ROWS:
                setattr(st, field_name, row_fn(getattr(st, field_name)))


def append(splats: Splats, rows: dict[str, Tensor]) -> None:
    """Add Gaussians (`rows[name]` [M, ...] for every parameter) with zero moments
    and empty strategy rows."""
    m = next(iter(rows.values())).shape[0]
    _edit(
        splats,
        lambda n, p: torch.cat([p, rows[n].to(p)], dim=0),
        lambda n, v: torch.cat([v, v.new_zeros((rows[n].shape[0], *v.shape[1:]))], dim=0),
        lambda r: torch.cat([r, r.new_zeros((m, *r.shape[1:]))], dim=0),
    )


def keep(splats: Splats, mask: Tensor) -> None:  # mask [N] bool (or index [M])
    """Keep only the selected Gaussians (prune the rest): moments and strategy rows too."""
    _edit(splats, lambda n, p: p[mask], lambda n, v: v[mask], lambda r: r[mask])


def clone_rows(params: dict[str, Tensor], sel: Tensor) -> dict[str, Tensor]:  # sel [N] bool
    """Clone: exact copies of the selected Gaussians (3DGS clones in place and lets
    the gradient pull the pair apart)."""
    return {n: p.detach()[sel] for n, p in params.items()}


def draws(quats: Tensor, log_scales: Tensor, noise: Tensor) -> Tensor:
    """Offsets of points drawn from the Gaussians themselves, R diag(s) z, for standard
    normal `noise` z. quats [M, 4], log_scales [M, 3], noise [..., M, 3] -> [..., M, 3]."""
    v = (noise * log_scales.exp()).unbind(-1)  # 3 x [..., M]
    return torch.stack(quat_rotate(unit_quat(quats), v), -1)  # (the components broadcast over the leading dims)


@torch.no_grad()
def split_rows(
    params: dict[str, Tensor],
    sel: Tensor,  # [N] bool
    generator: torch.Generator | None,
    samples: int = 2,
    scale_div: float = 1.6,  # 3DGS: new scale = old / (0.8 * samples)
) -> dict[str, Tensor]:
    """The `samples` Gaussians that replace each selected one: positions drawn from
    the Gaussian itself, scales divided by `scale_div`, the rest copied."""
    means = params["means"][sel]  # [M, 3]
    log_scales = params["log_scales"][sel]  # [M, 3]
    noise = torch.randn((samples, means.shape[0], 3), generator=generator, device=means.device, dtype=means.dtype)
    offsets = draws(params["quats"][sel], log_scales, noise)  # [S, M, 3]
    rows: dict[str, Tensor] = {}
    for n, p in params.items():
        v = p.detach()[sel]
        if n == "means":
            rows[n] = (means[None] + offsets).reshape(-1, 3)
        elif n == "log_scales":
            rows[n] = (log_scales - torch.log(torch.tensor(scale_div, dtype=v.dtype, device=v.device))).repeat(samples, 1)
        else:
            rows[n] = v.repeat(samples, *([1] * (v.dim() - 1)))
    return rows


def cat_rows(parts: list[dict[str, Tensor]]) -> dict[str, Tensor]:
    return {n: torch.cat([p[n] for p in parts], dim=0) for n in parts[0]}


def split(splats: Splats, sel: Tensor, generator: torch.Generator | None, samples: int = 2) -> None:  # sel [N] bool
    """Replace each selected Gaussian by `samples` smaller ones inside it."""
    rows = split_rows(splats.params, sel, generator, samples)
    keep(splats, ~sel)
    append(splats, rows)


def replace_rows(splats: Splats, idx: Tensor, rows: dict[str, Tensor]) -> None:  # idx [M] long
    """Overwrite the Gaussians at `idx` with `rows[name]` [M, ...] for every parameter, as
    new Gaussians: their Adam moments and strategy rows are zeroed (MCMC relocation)."""

    def put(x: Tensor, v: Tensor) -> Tensor:
        x = x.clone()
        x[idx] = v.to(x)
        return x

    _edit(splats, lambda n, p: put(p, rows[n]), lambda n, v: put(v, v.new_zeros((len(idx), *v.shape[1:]))),
          lambda r: put(r, r.new_zeros((len(idx), *r.shape[1:]))))


@torch.no_grad()
def nudge(splats: Splats, name: str, delta: Tensor) -> None:
    """Add `delta` to one parameter in place (moments kept: a small move, not a new Gaussian)."""
    splats.params[name].add_(delta.to(splats.params[name]))


@torch.no_grad()
def assign(splats: Splats, values: dict[str, Tensor]) -> None:
    """Overwrite parameters in place with `values[name]` (same shapes), moments kept: the same
    Gaussians, moved to values near their own (strategy/average.py)."""
    for name, v in values.items():
        splats.params[name].copy_(v)


def set_rows(splats: Splats, name: str, fn: Callable[[Tensor], Tensor]) -> None:
    """Overwrite one parameter with `fn(value)` (same shape) and zero its moments
    (the opacity reset: stale momentum would undo it at once)."""
    _edit(splats, lambda n, p: fn(p), lambda n, v: torch.zeros_like(v), None, names=[name])


def truncate_bands(splats: Splats, name: str, bands: int) -> None:
    """Keep the first `bands` columns (dim 1) of one parameter and of its moments
    (dropping unused SH bands); `bands == 0` removes the parameter entirely."""
    if bands > 0:
        _edit(splats, lambda n, p: p[:, :bands].contiguous(), lambda n, v: v[:, :bands].contiguous(), None,
              names=[name])
    else:
        del splats.params[name]
        splats.optimizers.pop(name, None)
