"""Fast rasterizer (being implemented; see issue 7)."""

from __future__ import annotations


def rasterize(*args, **kwargs):  # pragma: no cover - placeholder
    raise NotImplementedError("rasterize: being implemented")
