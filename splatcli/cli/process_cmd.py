"""`splatcli process` (stub: being implemented)."""

from __future__ import annotations

from ..errors import SplatError


def process() -> None:
    """Not implemented yet."""
    raise SplatError("process: not implemented yet")
