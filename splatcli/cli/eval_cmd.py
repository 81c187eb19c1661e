"""`splatcli eval` (stub: being implemented)."""

from __future__ import annotations

from ..errors import SplatError


def evaluate() -> None:
    """Not implemented yet."""
    raise SplatError("eval: not implemented yet")
