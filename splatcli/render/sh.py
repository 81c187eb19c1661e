"""Real spherical harmonics, degrees 0-3, in the convention of 3D Gaussian Splatting.

Coefficients are stored per Gaussian as sh [N, (d+1)^2, 3] (DC first). The basis is
the standard real SH basis Y_l^m evaluated at a unit direction (x, y, z), with the
sign convention of the 3DGS reference implementation (so that .ply files exchange
colour with other tools). colour = sum_k sh[k] * Y_k(dir) + 0.5, clamped at 0 by the
caller.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

# Normalisation constants of the real SH basis: Y_0^0 = 1 / (2 sqrt(pi)), ...
SH_C0 = 0.28209479177387814  # 1 / (2 sqrt(pi))
SH_C1 = 0.4886025119029199  # sqrt(3 / (4 pi))
SH_C2 = (
    1.0925484305920792,  # sqrt(15 / pi) / 2    : xy
    -1.0925484305920792,  # -sqrt(15 / pi) / 2  : yz
    0.31539156525252005,  # sqrt(5 / pi) / 4    : 2z^2 - x^2 - y^2
    -1.0925484305920792,  # -sqrt(15 / pi) / 2  : xz
    0.5462742152960396,  # sqrt(15 / pi) / 4    : x^2 - y^2
)
SH_C3 = (
    -0.5900435899266435,  # -sqrt(35 / (2 pi)) / 4 : y (3x^2 - y^2)
    2.890611442640554,  # sqrt(105 / pi) / 2       : xyz
    -0.4570457994644658,  # -sqrt(21 / (2 pi)) / 4 : y (4z^2 - x^2 - y^2)
    0.3731763325901154,  # sqrt(7 / pi) / 4        : z (2z^2 - 3x^2 - 3y^2)
    -0.4570457994644658,  # -sqrt(21 / (2 pi)) / 4 : x (4z^2 - x^2 - y^2)
    1.445305721320277,  # sqrt(105 / pi) / 4       : z (x^2 - y^2)
    -0.5900435899266435,  # -sqrt(35 / (2 pi)) / 4 : x (x^2 - 3y^2)
)

assert math.isclose(SH_C0, 0.5 / math.sqrt(math.pi))


# The basis as polynomials, term by term: Y_k = sum coef x^i y^j z^l over (coef, (i, j, l)). `sh_basis`
# evaluates them and `sh_basis_rows_backward` differentiates them; the tests hold them to the closed forms.
_POLY = (
    ((SH_C0, (0, 0, 0)),),
    ((-SH_C1, (0, 1, 0)),),
    ((SH_C1, (0, 0, 1)),),
    ((-SH_C1, (1, 0, 0)),),
    ((SH_C2[0], (1, 1, 0)),),
    ((SH_C2[1], (0, 1, 1)),),
    ((2 * SH_C2[2], (0, 0, 2)), (-SH_C2[2], (2, 0, 0)), (-SH_C2[2], (0, 2, 0))),
    ((SH_C2[3], (1, 0, 1)),),
    ((SH_C2[4], (2, 0, 0)), (-SH_C2[4], (0, 2, 0))),
    ((3 * SH_C3[0], (2, 1, 0)), (-SH_C3[0], (0, 3, 0))),
    ((SH_C3[1], (1, 1, 1)),),
    ((4 * SH_C3[2], (0, 1, 2)), (-SH_C3[2], (2, 1, 0)), (-SH_C3[2], (0, 3, 0))),
    ((2 * SH_C3[3], (0, 0, 3)), (-3 * SH_C3[3], (2, 0, 1)), (-3 * SH_C3[3], (0, 2, 1))),
    ((4 * SH_C3[4], (1, 0, 2)), (-SH_C3[4], (3, 0, 0)), (-SH_C3[4], (1, 2, 0))),
    ((SH_C3[5], (2, 0, 1)), (-SH_C3[5], (0, 2, 1))),
    ((SH_C3[6], (3, 0, 0)), (-3 * SH_C3[6], (1, 2, 0))),
)
# The monomials of degree <= 3 the basis is made of, lowest degree first (so a degree's basis uses a prefix).
_MONO3 = tuple(sorted({e for poly in _POLY for _, e in poly}, key=lambda e: (sum(e), tuple(-i for i in e))))


def _basis_matrix(degree: int) -> list[list[float]]:  # [monomials of degree <= `degree`, (degree+1)^2]
    mono = [e for e in _MONO3 if sum(e) <= degree]
    C = [[0.0] * (degree + 1) ** 2 for _ in mono]
    for k, poly in enumerate(_POLY[: (degree + 1) ** 2]):
        for coef, e in poly:
            C[mono.index(e)][k] += coef
    return C


_BASIS = [_basis_matrix(d) for d in range(4)]


def _monomials(x: Tensor, y: Tensor, z: Tensor, degree: int) -> Tensor:  # 3 x [N] -> [m, N]
    """The monomials of `_MONO3` up to `degree`, in its order: each one lower times one variable."""
    pw = {(0, 0, 0): torch.ones_like(x)}
    for e in _MONO3[1:]:
        if sum(e) > degree:
            break
        i = next(j for j in range(3) if e[j])
        pw[e] = pw[tuple(p - (j == i) for j, p in enumerate(e))] * (x, y, z)[i]
    return torch.stack(list(pw.values()))


def sh_basis(dirs: Tensor, degree: int) -> Tensor:  # dirs [N, 3] unit -> [N, (degree+1)^2]
    """The (degree+1)^2 real SH basis functions at unit directions `dirs`: the monomials of the
    direction as rows [m, N], then one matrix product with the polynomials' coefficients, which
    writes the [N, k] result row by row (stacking k columns into it wrote each with a stride: 3x
    the time at degree 3). Fastest when dirs is the transpose of a contiguous [3, N]."""
    if not 0 <= degree <= 3:
        raise ValueError(f"sh degree {degree} is not supported (0..3)")
    mono = _monomials(*dirs.unbind(-1), degree)  # [m, N]
    return torch.mm(mono.T, torch.tensor(_BASIS[degree], dtype=dirs.dtype, device=dirs.device))


# The monomials of degree <= 2 that the derivatives are made of (`_monomials(..., 2)`'s rows).
_MONO2 = tuple(e for e in _MONO3 if sum(e) <= 2)


def _gradient_matrix() -> list[list[list[float]]]:  # [3 * 10, 16]: d Y_k / d x_i in monomials
    D = [[0.0] * 16 for _ in range(3 * len(_MONO2))]
    for k, poly in enumerate(_POLY):
        for coef, e in poly:
            for i in range(3):
                if e[i]:
                    d = tuple(p - (j == i) for j, p in enumerate(e))
                    D[i * len(_MONO2) + _MONO2.index(d)][k] += coef * e[i]
    return D


_DY = _gradient_matrix()


def sh_basis_rows_backward(
    dirs: Tensor,  # [3, N] the directions the basis was evaluated at
    g: Tensor,  # [(degree+1)^2, N] d loss / d basis
    degree: int,
) -> Tensor:  # [3, N] d loss / d (x, y, z), each component taken as free
    """The chain rule through `sh_basis`: sum_k g_k grad Y_k, with each grad Y_k a
    combination of the monomials of degree <= 2 (one matrix product, then one weighted sum)."""
    k = (degree + 1) ** 2
    x, y, z = dirs
    mono = _monomials(x, y, z, 2)  # [10, N]
    D = torch.tensor(_DY, dtype=g.dtype, device=g.device)[:, :k]
    coef = torch.mm(D, g).view(3, len(_MONO2), -1)  # [3, 10, N]
    out = coef[:, 0] * mono[0]  # [3, N]; a monomial at a time: (coef * mono).sum(1) wrote a [3, 10, N] product first
    for i in range(1, len(_MONO2)):
        out.addcmul_(coef[:, i], mono[i])
    return out


def eval_sh(
    sh: Tensor,  # [N, K, 3] coefficients, K >= (degree+1)^2, DC first
    dirs: Tensor,  # [N, 3] unit view directions (camera centre -> mean)
    degree: int,
) -> Tensor:  # [N, 3] raw SH radiance (no +0.5, no clamp)
    k = (degree + 1) ** 2
    basis = sh_basis(dirs, degree)  # [N, k]
    return torch.einsum("nk,nkc->nc", basis, sh[:, :k])


def sh_to_rgb(
    sh: Tensor,  # [N, K, 3]
    dirs: Tensor,  # [N, 3] unit
    degree: int,
) -> Tensor:  # [N, 3] colour = SH + 0.5, clamped at 0 (not above: HDR-safe as in 3DGS)
    return torch.clamp_min(eval_sh(sh, dirs, degree) + 0.5, 0.0)
