"""What the benchmark scripts share: paths and the shared data, the processed scenes, running
`splatcli` and measuring it, and writing a result (`report`: bench/out/<name>.json, its
table printed as markdown; the scripts never edit the docs).

Every script runs as `python bench/NAME.py`: Python puts bench/ first on the module path,
so the scripts import this module (and workloads.py beside it) without editing it. No test
imports them: tests/test_bench.py runs each one with --help.
"""

from __future__ import annotations

import contextlib
import json
import os
import shlex
import shutil
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from splatcli.camera import Camera, scene_extent
from splatcli.device import cpu_flags, cpu_name
from splatcli.eval.curve import read_curve
from splatcli.project import Project

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "bench" / "out"  # every script's results (git ignores it)
SPLATCLI = [sys.executable, "-m", "splatcli.cli.main"]


def data_dir() -> Path:
    """The third-party scenes: $SPLATCLI_DATA, else ../shared/data beside the checkout. May not exist."""
    env = os.environ.get("SPLATCLI_DATA")
    return Path(env) if env else REPO.parent / "shared" / "data"


# scene -> (input, process args, train args, preset): the scenes bench/train.py measures; the
# other scripts train copies of the same processed projects
SCENES = {
    "lego": (lambda: data_dir() / "lego", [], ["--max-size", "200"], None),
    "fox": (lambda: data_dir() / "fox", [], ["--max-size", "480"], None),
    # the same 50 photos without their poses: structure from motion at 400 px (issue 12's "real capture")
    "fox-photos": (lambda: data_dir() / "fox" / "images", ["--input-type", "images", "--max-size", "400"],
                   ["--max-size", "480"], None),
    "sample": (lambda: REPO / "sample_data" / "scene", [], [], "demo"),
}
PROCESSED = OUT / "train"  # <scene>/base: each scene processed once, never written to afterwards


def ensure_processed(scene: str) -> Path:
    """The scene's processed project (bench/out/train/<scene>/base), made on first use."""
    src, pargs, _, _ = SCENES[scene]
    base = PROCESSED / scene / "base"
    if (base / "splatcli.json").is_file() and (base / "sfm").is_dir():
        return base
    inp = src()
    if not inp.exists():
        raise SystemExit(f"{inp}: missing (scene {scene}); set SPLATCLI_DATA or skip it with --scenes")
    base.parent.mkdir(parents=True, exist_ok=True)
    splatcli(["process", str(inp), "-o", str(base), "--overwrite", *pargs], PROCESSED / scene / "process.log")
    return base


def fresh_copy(base: Path, dest: Path) -> Path:
    """`dest` = a copy of the processed project `base` without any training outputs (checkpoints,
    reports, renders, exports); whatever was at `dest` is replaced."""
    p = Project(Path(base))
    outputs = {d.name for d in (p.checkpoints_dir, p.reports_dir, p.renders_dir, p.exports_dir)}
    if dest.exists():
        shutil.rmtree(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    shutil.copytree(base, dest, ignore=lambda d, names: [n for n in names if Path(d) == Path(base) and n in outputs])
    return dest


# ---- running and measuring ------------------------------------------------------------


def loadavg() -> float:
    """The 1-minute load average, as every result records it beside its timings."""
    return round(os.getloadavg()[0], 2)


class RssSampler(threading.Thread):
    """Peak resident set size of a child, sampled from /proc (Linux)."""

    def __init__(self, pid: int, period: float = 0.5) -> None:
        super().__init__(daemon=True)
        self.pid, self.period, self.peak_kb, self.samples = pid, period, 0, []
        self._halt = threading.Event()
        self.t0 = time.monotonic()

    def run(self) -> None:
        while not self._halt.is_set():
            try:
                with open(f"/proc/{self.pid}/status") as f:
                    kb = next((int(ln.split()[1]) for ln in f if ln.startswith("VmRSS:")), 0)
                self.peak_kb = max(self.peak_kb, kb)
                self.samples.append((round(time.monotonic() - self.t0, 1), kb // 1024))
            except OSError:
                pass
            self._halt.wait(self.period)

    def stop(self) -> None:
        self._halt.set()
        self.join()


@dataclass
class Run:
    """A finished child process: its exit code and output, and what it cost."""

    returncode: int
    stdout: str
    wall_s: float
    peak_mb: int  # peak resident memory (sampled every 0.5 s from /proc; 0 where there is none)
    rss: list[tuple[float, int]] = field(default_factory=list)  # (seconds, MiB) samples
    load: tuple[float, float] = (0.0, 0.0)  # 1-minute load average before and after

    @property
    def summary(self) -> dict:
        """The JSON object a `--json` command printed last."""
        return json.loads(self.stdout.strip().splitlines()[-1])


def run(cmd: list[str], log: Path | None = None, *, cwd: Path = REPO, env: dict | None = None) -> Run:
    """Run `cmd` to its end, stdout captured, stderr into `log` (or inherited), timing it,
    sampling its memory and reading the load average before and after."""
    load0, t0 = loadavg(), time.monotonic()
    with open(log, "w") if log else contextlib.nullcontext() as err:
        p = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=err, text=True)
        sampler = RssSampler(p.pid)
        sampler.start()
        out, _ = p.communicate()
        sampler.stop()
    return Run(p.returncode, out, time.monotonic() - t0, sampler.peak_kb // 1024, sampler.samples,
               (load0, loadavg()))


def splatcli(args: list[str], log: Path, *, cwd: Path = REPO, env: dict | None = None) -> Run:
    """`splatcli ARGS --json -q` as a measured child (`run`); a failure ends the benchmark, naming the log."""
    r = run(SPLATCLI + [*args, "--json", "-q"], log, cwd=cwd, env=env)
    if r.returncode != 0:
        raise SystemExit(f"splatcli {args[0]} failed (exit {r.returncode}); see {log}")
    return r


def psnr_curve(project: Path) -> list[tuple[float, float]]:
    """Held-out PSNR against training seconds, from the project's train log (splatcli.eval.curve)."""
    return [(p.elapsed_s, p.psnr) for p in read_curve(Project(Path(project)).train_log_path)]


# ---- poses ----------------------------------------------------------------------------


def similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Umeyama: s, R, t minimising |dst - (s R src + t)|^2 over [N, 3] points."""
    ms, md = src.mean(0), dst.mean(0)
    xs, xd = src - ms, dst - md
    U, D, Vt = np.linalg.svd(xd.T @ xs / len(src))
    S = np.diag([1.0, 1.0, -1.0 if np.linalg.det(U) * np.linalg.det(Vt) < 0 else 1.0])
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / max((xs**2).sum() / len(src), 1e-300))
    return s, R, md - s * R @ ms


def angle_deg(Q: np.ndarray) -> float:
    s = 0.5 * np.linalg.norm([Q[2, 1] - Q[1, 2], Q[0, 2] - Q[2, 0], Q[1, 0] - Q[0, 1]])
    return float(np.degrees(np.arctan2(s, 0.5 * (np.trace(Q) - 1.0))))


def pose_errors(est: list[Camera], ref: list[Camera], tol: float = 0.02, seed: int = 0) -> dict:
    """`est` against `ref` (matched by name) after a similarity fitted by RANSAC on camera centres
    (inliers within `tol` of the reference's extent, `camera.scene_extent`), then refitted on the
    inliers, so that cameras placed apart do not pull it: rotation errors in degrees, centre errors
    as a percentage of the extent, their medians, means and largest, and the shares of cameras
    within 2 degrees and 2%, and within 1 degree and 1%."""
    by = {c.name: c for c in ref}
    pairs = [(c, by[c.name]) for c in est if c.name in by]
    ec = np.stack([c.center for c, _ in pairs])
    rc = np.stack([c.center for _, c in pairs])
    _, extent = scene_extent([c for _, c in pairs])
    rng, best = np.random.default_rng(seed), None
    for _ in range(500):
        pick = rng.choice(len(pairs), 3, replace=False)
        s, R, t = similarity(ec[pick], rc[pick])
        inl = np.linalg.norm(s * ec @ R.T + t - rc, axis=1) <= tol * extent
        if best is None or inl.sum() > best.sum():
            best = inl
    for _ in range(3):
        s, R, t = similarity(ec[best], rc[best])
        err = np.linalg.norm(s * ec @ R.T + t - rc, axis=1) / extent
        best = err <= tol
    rot = np.array([angle_deg((e.viewmat[:3, :3] @ R.T).T @ r.viewmat[:3, :3]) for e, r in pairs])
    return {"compared": len(pairs), "median_rot_deg": float(np.median(rot)), "median_centre_pct": 100 * float(np.median(err)),
            "mean_rot_deg": float(rot.mean()), "mean_centre_pct": 100 * float(err.mean()),
            "within_2deg_2pct": 100 * float(np.mean((rot <= 2) & (err <= 0.02))),
            "within_1deg_1pct": 100 * float(np.mean((rot <= 1) & (err <= 0.01))),
            "max_rot_deg": float(rot.max()), "max_centre_pct": 100 * float(err.max())}


# ---- results --------------------------------------------------------------------------


def commit() -> str:
    """This checkout's commit, `+dirty` where tracked files differ from it."""
    git = lambda *a: subprocess.run(["git", *a], cwd=REPO, capture_output=True, text=True).stdout.strip()  # noqa: E731
    return (git("rev-parse", "--short", "HEAD") or "unknown") + ("+dirty" if git("status", "--porcelain",
                                                                                 "--untracked-files=no") else "")


def cpu() -> dict:
    """The CPU model with its widest vector extensions (`device.cpu_name`), and the cores."""
    flags = cpu_flags()
    return {"model": cpu_name(), "avx512f": "avx512f" in flags, "avx2": "avx2" in flags, "cores": os.cpu_count()}


def cell(v: Any) -> str:
    """A markdown table cell: numbers rounded for reading (the JSON keeps them whole), a dash for none."""
    if v is None:
        return "–"
    if isinstance(v, float):
        spec = ".4g" if abs(v) < 1 else ".2f" if abs(v) < 100 else ",.1f" if abs(v) < 1e3 else ",.0f"
        return format(v, spec)
    return f"{v:,}" if isinstance(v, int) and not isinstance(v, bool) else str(v)


def report(name: str, rows: list[dict], columns: list[str] | None = None, **meta) -> Path:
    """A benchmark's result: bench/out/<name>.json holds the command line, the commit, the UTC date,
    the CPU, the load average now, `meta` and the `rows`; their markdown table (`columns`, by default
    every key some row gives a value and none a list or a dict) goes to stdout. Returns the path."""
    import torch

    path = OUT / f"{name}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    doc = {"command": shlex.join(["python", *sys.argv]), "commit": commit(),
           "date": datetime.now(timezone.utc).isoformat(timespec="seconds"), "cpu": cpu(), "load_average": loadavg(),
           "torch": torch.__version__, **meta, "rows": rows}
    path.write_text(json.dumps(doc, indent=1, default=str) + "\n")
    keys = list(dict.fromkeys(k for r in rows for k in r))
    columns = columns or [k for k in keys if any(r.get(k) is not None for r in rows)
                          and not any(isinstance(r.get(k), (list, dict)) for r in rows)]
    print("\n| " + " | ".join(columns) + " |\n|" + " --- |" * len(columns))
    for r in rows:
        print("| " + " | ".join(cell(r.get(c)) for c in columns) + " |")
    print(f"\n{path.relative_to(REPO)}: {doc['command']} at {doc['commit']}, {doc['date']}, {doc['cpu']['model']}, "
          f"load {doc['load_average']}", flush=True)
    return path
