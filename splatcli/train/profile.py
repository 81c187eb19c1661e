"""`train --profile`: where each step's time went, written to reports/profile.json and profile.md.

Stages as the loop runs them: data (the view and its photo at the step's resolution), the
render's projection, planning and compositing (render/timing.py), the loss (with the image
model), the backward pass's compositing and projection parts and the rest of it (the loss's
own), the optimiser (with the gradient checks and, with --nproc, the exchange), and
densification (the strategies). Held-out evaluation is not a step's time and is left out.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from typing import Any

from ..device import cpu_name
from ..files.atomic import atomic_write_json, atomic_write_text
from ..project import Project
from ..render import timing

# (stage, how it is measured): the loop's own stages, and the render's inside "render" and "backward"
RENDER = ("projection", "planning", "compositing")
BACKWARD = ("compositing backward", "projection backward")
ORDER = ("data", *RENDER, "render, other", "loss", *BACKWARD, "backward, other", "optimiser", "densification")


class StepProfile:
    """Seconds per stage, summed over the steps; off (free) unless `enabled`."""

    def __init__(self, enabled: bool):
        self.enabled = enabled
        self.totals: dict[str, float] = {}
        self.steps = 0

    @contextlib.contextmanager
    def stage(self, name: str) -> Iterator[None]:
        if not self.enabled:
            yield
            return
        if name in ("render", "backward"):  # the render's own stages, of this step's render alone (not evaluation's)
            timing.collect(self.totals)
        t = time.perf_counter()
        try:
            yield
        finally:
            self.totals[name] = self.totals.get(name, 0.0) + time.perf_counter() - t
            timing.collect(None)

    def step_done(self) -> None:
        self.steps += self.enabled

    def report(self, extra: dict[str, Any]) -> dict[str, Any]:
        """Milliseconds per step of each stage, its share, and pairs per step."""
        t, n = dict(self.totals), max(self.steps, 1)
        t["render, other"] = t.get("render", 0.0) - sum(t.get(k, 0.0) for k in RENDER)
        t["backward, other"] = t.get("backward", 0.0) - sum(t.get(k, 0.0) for k in BACKWARD)
        total = sum(t.get(k, 0.0) for k in ORDER)
        stages = {k: {"ms_per_step": round(1e3 * t.get(k, 0.0) / n, 3),
                      "share": round(t.get(k, 0.0) / total, 4) if total else 0.0} for k in ORDER}
        return {"steps": self.steps, "ms_per_step": round(1e3 * total / n, 3), "stages": stages,
                "pairs_per_step": round(t.get("pairs", 0.0) / n), "slots": slot_shares(t, n), "cpu": cpu_name(),
                **extra}

    def write(self, project: Project, extra: dict[str, Any]) -> None:
        if not self.enabled:
            return
        r = self.report(extra)
        atomic_write_json(project.profile_json_path, r)
        lines = ["# Where each training step's time went", "",
                 f"{r['steps']} steps, {r['ms_per_step']:.1f} ms a step, {r['pairs_per_step']:,} (Gaussian, block) "
                 f"pairs a step; {r['cpu']}; {', '.join(f'{k} {v}' for k, v in extra.items())}.", "",
                 "| stage | ms a step | share |", "| --- | ---: | ---: |"]
        lines += [f"| {k} | {v['ms_per_step']:.2f} | {100 * v['share']:.1f}% |" for k, v in r["stages"].items()]
        sl = r["slots"]
        if sl["per_step"]:
            lines += ["", f"The compositor's forward evaluated {sl['per_step']:,} (pixel, Gaussian) slots a step: "
                      f"{100 * sl['below']:.1f}% below alpha 1/255, {100 * sl['ended']:.1f}% behind a pixel whose "
                      f"transmittance had ended, {100 * sl['padding']:.1f}% padding past the end of a block's list; "
                      f"{100 * sl['blended']:.1f}% blended."]
        atomic_write_text(project.profile_md_path, "\n".join(lines) + "\n")


def slot_shares(totals: dict[str, float], steps: int) -> dict[str, float]:
    """The compositor's dense slots a step and their shares (render/timing.py): below alpha 1/255,
    behind an ended transmittance, padding, and blended (the rest)."""
    n = totals.get("slots", 0.0)
    shares = {k: round(totals.get(f"slots {k}", 0.0) / n, 4) if n else 0.0 for k in ("below", "ended", "padding")}
    blended = round(1.0 - sum(shares.values()), 4) if n else 0.0
    return {"per_step": round(n / max(steps, 1)), **shares, "blended": blended}
