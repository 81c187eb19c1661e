"""The training curve: reports/train_log.jsonl, written by train, read by train
(resume, summary) and eval (held-out PSNR against training seconds)."""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any


@dataclass
class TrainLogLine:
    """One line of reports/train_log.jsonl (the speed-against-error curve)."""

    step: int
    elapsed_s: float  # training seconds only: evaluation and checkpoint writes excluded
    loss: float  # mean loss over the steps since the previous line
    num_gaussians: int
    psnr: float | None = None  # held-out, every --eval-every steps
    ssim: float | None = None
    train_psnr: float | None = None  # the same, on as many evenly spaced training views (the gap is overfitting)
    train_ssim: float | None = None
    bad_steps: int = 0  # non-finite steps skipped so far
    rss_mb: int | None = None  # the process's resident memory now (flat once densification stops)
    open_fds: int | None = None  # the process's open file descriptors now (flat: nothing leaks)
    cloned: int = 0  # Gaussians cloned, split and pruned since the previous line
    split: int = 0
    pruned: int = 0

    def to_json(self) -> dict[str, Any]:
        return {k: v for k, v in asdict(self).items() if v is not None}


@dataclass
class CurvePoint:
    step: int
    elapsed_s: float  # training seconds
    psnr: float
    ssim: float | None = None
    num_gaussians: int | None = None


def read_log(path: Path) -> list[dict[str, Any]]:
    """The log's complete lines (a torn or malformed line, as a crash can leave, is skipped)."""
    try:
        text = Path(path).read_text(encoding="utf-8", errors="replace")
    except OSError:
        return []
    out = []
    for line in text.splitlines():
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(rec, dict) and isinstance(rec.get("step"), int):
            out.append(rec)
    return out


def read_curve(path: Path) -> list[CurvePoint]:
    """Held-out PSNR against training seconds: the log lines that carry a PSNR."""
    points = []
    for d in read_log(path):
        p, t, s = d.get("psnr"), d.get("elapsed_s"), d["step"]
        if isinstance(p, (int, float)) and isinstance(t, (int, float)) and math.isfinite(p):
            ss, n = d.get("ssim"), d.get("num_gaussians")
            points.append(CurvePoint(step=s, elapsed_s=float(t), psnr=float(p),
                                     ssim=float(ss) if isinstance(ss, (int, float)) else None,
                                     num_gaussians=int(n) if isinstance(n, int) else None))
    return points
