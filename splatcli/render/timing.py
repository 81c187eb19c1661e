"""Where a render's time goes, for `train --profile`: nothing is recorded (and nothing costs
more than a clock read) unless a collector is set.

    timing.collect(totals)   # a dict: seconds per stage, and "pairs", added up from now on
    timing.collect(None)     # off

With a collector set, the compositor's forward also counts its dense slots (one per pixel of each
block and each Gaussian in the block's list, padding included): "slots", "slots padding" (past
the end of a block's list), "slots below" (alpha < 1/255, never blended) and "slots ended"
(alpha >= 1/255 but behind a pixel whose transmittance has ended).
"""

from __future__ import annotations

_sink: dict[str, float] | None = None


def collect(sink: dict[str, float] | None) -> None:
    global _sink
    _sink = sink


def add(name: str, amount: float) -> None:
    if _sink is not None:
        _sink[name] = _sink.get(name, 0.0) + amount


def active() -> bool:
    """Whether a collector is set (the compositor then counts its slots)."""
    return _sink is not None
