"""Spherical harmonics: every band against its closed form in spherical coordinates,
and orthonormality over the sphere."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from splatcli.render.sh import SH_C0, eval_sh, sh_basis, sh_to_rgb


def _dirs(n=200, seed=0):
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g, dtype=torch.float64)
    return d / d.norm(dim=1, keepdim=True)


def _closed_forms(theta, phi):
    """Real SH (with the Condon-Shortley phase, as in 3DGS) in spherical coordinates,
    ordered m = -l..l per band: written from the textbook formulas, not from sh.py."""
    st, ct = np.sin(theta), np.cos(theta)
    pi = math.pi
    Y = [np.full_like(theta, 0.5 / math.sqrt(pi))]
    k1 = math.sqrt(3 / (4 * pi))
    Y += [-k1 * st * np.sin(phi), k1 * ct, -k1 * st * np.cos(phi)]
    Y += [
        0.25 * math.sqrt(15 / pi) * st**2 * np.sin(2 * phi),
        -0.5 * math.sqrt(15 / pi) * st * ct * np.sin(phi),
        0.25 * math.sqrt(5 / pi) * (3 * ct**2 - 1),
        -0.5 * math.sqrt(15 / pi) * st * ct * np.cos(phi),
        0.25 * math.sqrt(15 / pi) * st**2 * np.cos(2 * phi),
    ]
    Y += [
        -0.25 * math.sqrt(35 / (2 * pi)) * st**3 * np.sin(3 * phi),
        0.25 * math.sqrt(105 / pi) * st**2 * ct * np.sin(2 * phi),
        -0.25 * math.sqrt(21 / (2 * pi)) * st * (5 * ct**2 - 1) * np.sin(phi),
        0.25 * math.sqrt(7 / pi) * (5 * ct**3 - 3 * ct),
        -0.25 * math.sqrt(21 / (2 * pi)) * st * (5 * ct**2 - 1) * np.cos(phi),
        0.25 * math.sqrt(105 / pi) * st**2 * ct * np.cos(2 * phi),
        -0.25 * math.sqrt(35 / (2 * pi)) * st**3 * np.cos(3 * phi),
    ]
    return np.stack(Y, -1)


def test_bands_match_closed_forms():
    d = _dirs()
    theta = np.arccos(d[:, 2].numpy())
    phi = np.arctan2(d[:, 1].numpy(), d[:, 0].numpy())
    ours = sh_basis(d, 3).numpy()
    want = _closed_forms(theta, phi)
    np.testing.assert_allclose(ours, want, atol=1e-12)  # float64: rounding only


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_orthonormal_on_sphere(degree):
    # Gauss-Legendre in cos(theta) x uniform phi: exact for the degree-6 products here.
    nt, nphi = 8, 16
    x, wx = np.polynomial.legendre.leggauss(nt)
    phi = np.arange(nphi) * 2 * math.pi / nphi
    ct, ph = np.meshgrid(x, phi, indexing="ij")
    st = np.sqrt(1 - ct**2)
    dirs = torch.tensor(np.stack([st * np.cos(ph), st * np.sin(ph), ct], -1).reshape(-1, 3))
    w = torch.tensor((wx[:, None] * np.full(nphi, 2 * math.pi / nphi)[None]).reshape(-1))
    Y = sh_basis(dirs, degree)
    gram = (Y * w[:, None]).T @ Y
    # float64 and an exact quadrature: rounding only
    torch.testing.assert_close(gram, torch.eye((degree + 1) ** 2, dtype=torch.float64), atol=1e-12, rtol=0)


def test_dc_only_colour_and_clamp():
    sh = torch.tensor([[[1.0, -3.0, 0.0]]], dtype=torch.float64)
    rgb = sh_to_rgb(sh, _dirs(1), 0)
    torch.testing.assert_close(rgb, torch.tensor([[SH_C0 + 0.5, 0.0, 0.5]], dtype=torch.float64))


def test_degree_truncation_uses_leading_bands():
    d = _dirs(10)
    g = torch.Generator().manual_seed(1)
    sh = torch.randn(10, 16, 3, generator=g, dtype=torch.float64)
    torch.testing.assert_close(eval_sh(sh, d, 1), eval_sh(sh[:, :4], d, 1))
    assert not torch.allclose(eval_sh(sh, d, 1), eval_sh(sh, d, 3))
