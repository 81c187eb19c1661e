"""Where a render's time goes, for `train --profile`: nothing is recorded (and nothing costs
more than a clock read) unless a collector is set.

    timing.collect(totals)   # a dict: seconds per stage, and "pairs", added up from now on
    timing.collect(None)     # off
"""

from __future__ import annotations

_sink: dict[str, float] | None = None


def collect(sink: dict[str, float] | None) -> None:
    global _sink
    _sink = sink


def add(name: str, amount: float) -> None:
    if _sink is not None:
        _sink[name] = _sink.get(name, 0.0) + amount
