"""Progress events: the core reports through these, the CLI displays them.

The core never prints. Long-running functions take `on_event: EventSink | None`
and call it with typed events; the CLI turns them into rich progress bars, the
tests collect them in a list, and `--json` ignores all but the summary.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Union


@dataclass(frozen=True)
class Stage:
    """A stage starts. `total` is None for spinners (unknown length)."""

    name: str
    total: int | None = None


@dataclass(frozen=True)
class Progress:
    """`done` units of the current stage are finished; `info` holds live figures
    (e.g. loss, PSNR, Gaussian count) for the progress bar; `eta_s` the seconds left where
    the stage knows them better than the count does (training: its time plan, or its steps
    priced by their resolution), None: the displays extrapolate from the count, unless `eta_own`:
    the stage gives its own once it has measured, and until then the displays show none (training's
    first step loads kernels and memory, which the count's extrapolation would price into every step).
    `share`: the fraction of the stage done where the stage knows it better than done / total (a
    planned run: its clock); `total` is then an estimate, which may move as the stage plans again."""

    name: str
    done: int
    total: int | None = None
    info: dict[str, Any] = field(default_factory=dict)
    eta_s: float | None = None
    eta_own: bool = False
    share: float | None = None


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


@dataclass(frozen=True)
class Snapshot:
    """The model as it is after step `step`, for live displays. `model()` returns a
    copy on the CPU; call it during the event or not at all (training goes on after)."""

    step: int
    model: Callable[[], Any]


Event = Union[Stage, Progress, StageDone, Note, Snapshot]
EventSink = Callable[[Event], None]


def emit(sink: EventSink | None, event: Event) -> None:
    if sink is not None:
        sink(event)


class Stages:
    """The one timed-stage helper: `with stages.stage(name, total) as s: s.progress(k)`
    emits Stage, Progress and StageDone, and adds each stage's seconds to `seconds`;
    `note` emits a Note and keeps warnings in `warnings`."""

    def __init__(self, sink: EventSink | None) -> None:
        self.sink = sink
        self.seconds: dict[str, float] = {}
        self.warnings: list[str] = []

    def note(self, message: str, level: str = "note") -> None:
        if level == "warning":
            self.warnings.append(message)
        emit(self.sink, Note(message, level))

    def stage(self, name: str, total: int | None = None) -> _Timed:
        return _Timed(self, name, total)


class _Timed:
    def __init__(self, stages: Stages, name: str, total: int | None) -> None:
        self.stages, self.name, self.total = stages, name, total

    def __enter__(self) -> _Timed:
        emit(self.stages.sink, Stage(self.name, self.total))
        self.t0 = time.perf_counter()
        return self

    def progress(self, done: int, total: int | None = None, **info: Any) -> None:
        emit(self.stages.sink, Progress(self.name, done, total if total is not None else self.total, info))

    def __exit__(self, *exc: Any) -> None:
        dt = time.perf_counter() - self.t0
        self.stages.seconds[self.name] = self.stages.seconds.get(self.name, 0.0) + dt
        if exc[0] is None:
            emit(self.stages.sink, StageDone(self.name, dt))
