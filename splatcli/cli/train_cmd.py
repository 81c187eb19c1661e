"""`splatcli train` (stub: being implemented)."""

from __future__ import annotations

from ..errors import SplatError


def train() -> None:
    """Not implemented yet."""
    raise SplatError("train: not implemented yet")
