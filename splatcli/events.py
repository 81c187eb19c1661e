"""Progress events: the core reports through these, the CLI displays them.

The core never prints. Long-running functions take `on_event: EventSink | None`
and call it with typed events; the CLI turns them into rich progress bars, the
tests collect them in a list, and `--json` ignores all but the summary.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Union


@dataclass(frozen=True)
class Stage:
    """A stage starts. `total` is None for spinners (unknown length)."""

    name: str
    total: int | None = None


@dataclass(frozen=True)
class Progress:
    """`done` units of the current stage are finished; `info` holds live figures
    (e.g. loss, PSNR, Gaussian count) for the progress bar."""

    name: str
    done: int
    total: int | None = None
    info: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class StageDone:
    name: str
    seconds: float


@dataclass(frozen=True)
class Note:
    """Something the user should know (skipped files, dropped frames).
    `level` is "note" or "warning"."""

    message: str
    level: str = "note"


Event = Union[Stage, Progress, StageDone, Note]
EventSink = Callable[[Event], None]


def null_sink(event: Event) -> None:
    """Default sink: drop everything."""


def emit(sink: EventSink | None, event: Event) -> None:
    if sink is not None:
        sink(event)
