"""`splatcli render` (stub: being implemented)."""

from __future__ import annotations

from ..errors import SplatError


def render() -> None:
    """Not implemented yet."""
    raise SplatError("render: not implemented yet")
