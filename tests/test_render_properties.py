"""Property tests: Gaussian parameters drawn from extreme ranges always give finite
pictures and gradients; non-finite inputs give a ValueError naming the parameter."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings, strategies as st

from splatcli import rasterize

PARAMS = ["means", "quats", "log_scales", "opacity_logits", "sh", "viewmat", "K", "background"]
SETTINGS = settings(
    max_examples=60, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow]
)


def _rotation(q):
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


@st.composite
def scenes(draw):
    """A random camera and N random Gaussians whose parameters span extreme magnitudes:
    means up to 1e6, log scales +-30, quaternions from 1e-30 to 1e30 (and exactly 0),
    opacity logits +-100, SH up to 100; plus one Gaussian drawn element by element."""
    n = draw(st.integers(0, 12))
    w, h = draw(st.integers(1, 32)), draw(st.integers(1, 32))
    seed = draw(st.integers(0, 2**31 - 1))
    dtype = draw(st.sampled_from([torch.float32, torch.float64]))
    rng = np.random.default_rng(seed)
    mscale = 10.0 ** draw(st.integers(-3, 6))
    means = rng.normal(size=(n, 3)) * mscale
    means[:, 2] = np.abs(means[:, 2]) * draw(st.sampled_from([1.0, -1.0, 0.0, 1.0]))  # mostly in front
    quats = rng.normal(size=(n, 4)) * 10.0 ** rng.uniform(-30, 30, size=(n, 1))
    quats[rng.random(n) < 0.2] = 0.0
    log_scales = rng.uniform(-30, 30, size=(n, 3)) if draw(st.booleans()) else rng.uniform(-6, 1, size=(n, 3))
    logits = rng.uniform(-100, 100, size=n) if draw(st.booleans()) else rng.normal(size=n) * 3
    degree = draw(st.integers(0, 3))
    sh = rng.normal(size=(n, (degree + 1) ** 2, 3)) * 10.0 ** draw(st.integers(-2, 2))
    if n:
        f32 = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False, width=32)
        means[0] = [draw(f32), draw(f32), draw(st.floats(-10, 1e6, width=32))]
        log_scales[0] = [draw(st.floats(-30, 30, width=32)) for _ in range(3)]
        quats[0] = [draw(st.floats(-1e30, 1e30)) for _ in range(4)]
        logits[0] = draw(st.floats(-100, 100, width=32))
    viewmat = np.eye(4)
    viewmat[:3, :3] = _rotation(rng.normal(size=4))
    viewmat[:3, 3] = rng.uniform(-10, 10, size=3)
    f = 10.0 ** draw(st.floats(0, 4))
    K = np.array([[f, 0, rng.uniform(-w, 2 * w)], [0, f * rng.uniform(0.5, 2), rng.uniform(-h, 2 * h)], [0, 0, 1]])
    bg = rng.random(3)
    t = lambda a: torch.tensor(a, dtype=dtype)  # noqa: E731
    args = [t(means), t(quats), t(log_scales), t(logits), t(sh), t(viewmat), t(K)]
    return args, w, h, t(bg), draw(st.booleans())


@SETTINGS
@given(scenes())
def test_extreme_parameters_give_finite_pictures_and_gradients(scene):
    args, w, h, bg, antialiased = scene
    xs = [a.clone().requires_grad_(True) for a in args]
    bgx = bg.clone().requires_grad_(True)
    out = rasterize(*xs, w, h, bgx, antialiased=antialiased)
    out.means2d.retain_grad()
    for name in ("image", "alpha", "depth", "means2d"):
        assert torch.isfinite(getattr(out, name)).all(), name
    assert (out.alpha >= 0).all() and (out.alpha <= 1).all()
    assert (out.image >= 0).all()  # colours are clamped at 0 and the background is >= 0
    g = torch.Generator().manual_seed(0)
    loss = (out.image * torch.randn(out.image.shape, generator=g, dtype=bg.dtype)).sum() + out.alpha.sum() + 1e-3 * out.depth.sum()
    loss.backward()
    for name, x in zip(PARAMS, xs + [bgx]):
        assert x.grad is not None and torch.isfinite(x.grad).all(), name
    assert torch.isfinite(out.means2d.grad).all()


@SETTINGS
@given(
    which=st.integers(0, len(PARAMS) - 1),
    bad=st.sampled_from([math.nan, math.inf, -math.inf]),
    n=st.integers(1, 5),
    pos=st.integers(0, 10**6),
)
def test_non_finite_input_is_a_value_error_naming_it(which, bad, n, pos):
    rng = np.random.default_rng(pos)
    args = [
        torch.tensor(rng.normal(size=(n, 3)) + [0, 0, 5], dtype=torch.float32),
        torch.tensor(rng.normal(size=(n, 4)), dtype=torch.float32),
        torch.tensor(rng.uniform(-3, -1, size=(n, 3)), dtype=torch.float32),
        torch.tensor(rng.normal(size=n), dtype=torch.float32),
        torch.tensor(rng.normal(size=(n, 4, 3)), dtype=torch.float32),
        torch.eye(4),
        torch.tensor([[10.0, 0, 4], [0, 10, 4], [0, 0, 1]]),
        torch.zeros(3),
    ]
    flat = args[which].view(-1)
    flat[pos % flat.numel()] = bad
    with pytest.raises(ValueError, match=rf"\b{PARAMS[which]}\b.*non-finite"):
        rasterize(*args[:7], 8, 8, args[7])
