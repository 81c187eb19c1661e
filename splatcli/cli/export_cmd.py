"""`splatcli export` (stub: being implemented)."""

from __future__ import annotations

from ..errors import SplatError


def export() -> None:
    """Not implemented yet."""
    raise SplatError("export: not implemented yet")
