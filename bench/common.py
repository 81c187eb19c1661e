"""What the bench scripts share: paths and the shared data, the processed scenes, running
`splatcli` and measuring it, reading training curves, plotting them, and writing one
section of docs/benchmarks.md.

Every script runs as `python bench/NAME.py`: Python puts bench/ first on the module path,
so the scripts import this module (and align, browser, scenes, tiny_project beside it)
without editing it. The tests import the same modules: pyproject.toml's pytest
`pythonpath` names bench/.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import json
import os
import shlex
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any

from splatcli.eval.curve import read_curve
from splatcli.project import Project

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "bench" / "out"  # every script's results, one folder each (git ignores it)
DOC = REPO / "docs" / "benchmarks.md"
FIGURES = REPO / "docs" / "figures"
SPLATCLI = [sys.executable, "-m", "splatcli.cli.main"]  # also what an earlier commit has (bench/versus.py)
TOL_DB = 0.1  # "reached" a PSNR: the first held-out evaluation within this of it


# ---- data ---------------------------------------------------------------------------


def data_dir() -> Path:
    """The third-party scenes: $SPLATCLI_DATA, else ../shared/data beside the checkout. May not exist."""
    env = os.environ.get("SPLATCLI_DATA")
    return Path(env) if env else REPO.parent / "shared" / "data"


def make_scene() -> ModuleType:
    """sample_data/make_scene.py (the sample scene's renderer) as a module; it is a script, not a package."""
    spec = importlib.util.spec_from_file_location("make_scene", REPO / "sample_data" / "make_scene.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def zoom_about_centre(img, zoom: float):  # [H, W, C] uint8 -> the same size
    """The picture a `zoom` times longer lens on the same camera takes: zoomed about the image
    centre (pixel centres at i + 0.5), which stays the principal point."""
    import cv2
    import numpy as np

    h, w = img.shape[:2]
    t = (0.5 - w / 2) * zoom + w / 2 - 0.5, (0.5 - h / 2) * zoom + h / 2 - 0.5
    return cv2.warpAffine(img, np.array([[zoom, 0, t[0]], [0, zoom, t[1]]]), (w, h), flags=cv2.INTER_AREA)


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


def cpu_model(checkpoint: Path, max_size: int) -> tuple[Any, dict]:
    """What the scripts that time the rasterizer on one torch thread start from: the training
    views at `max_size` of the project `checkpoint` (PROJECT/checkpoints/step-*.pt) belongs to,
    and its Gaussians' parameters by name (Gaussians.PARAM_NAMES order), detached, on the CPU."""
    import torch  # here: the scripts that only run `splatcli` start without it

    from splatcli.io.checkpoint import load_checkpoint
    from splatcli.train.data import load_train_data

    torch.set_num_threads(1)
    dev = torch.device("cpu")
    data = load_train_data(Project.open(checkpoint.parents[1]), 1.0, max_size, dev, 0)
    return data, load_checkpoint(checkpoint, dev).gaussians.detach().as_dict()


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
    """The 1-minute load average, as every table reports it beside its timings."""
    return round(os.getloadavg()[0], 2)


class RssSampler(threading.Thread):
    """Peak resident set size of a child, sampled from /proc (Linux)."""

    def __init__(self, pid: int, period: float = 0.5) -> None:
        super().__init__(daemon=True)
        self.pid, self.period, self.peak_kb, self.samples = pid, period, 0, []
        self._halt = threading.Event()
        self.t0 = time.monotonic()

    def run(self) -> None:
        path = f"/proc/{self.pid}/status"
        while not self._halt.is_set():
            try:
                with open(path) as f:
                    for line in f:
                        if line.startswith("VmRSS:"):
                            kb = int(line.split()[1])
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

    def train_record(self, proj: Path, **extra) -> dict:
        """What a benchmark keeps of a `train --json` run of `proj` (with `extra`): steps, training
        and wall seconds, final PSNR, Gaussians, peak memory, the held-out curve, the load."""
        s = self.summary
        return {**extra, "steps": s["steps"], "train_seconds": s["train_seconds"], "final_psnr": s["psnr"],
                "num_gaussians": s["num_gaussians"], "comm_seconds": s.get("comm_seconds"),
                "wall_seconds": round(self.wall_s, 1), "peak_rss_mb": self.peak_mb,
                "curve": psnr_curve(proj), "load_before": [self.load[0]], "load_after": [self.load[1]]}


def run(cmd: list[str], log: Path | None = None, *, cwd: Path = REPO, env: dict | None = None,
        append: bool = False) -> Run:
    """Run `cmd` to its end, stdout captured, stderr into `log` (or inherited), timing it,
    sampling its memory and reading the load average before and after."""
    load0, t0 = loadavg(), time.monotonic()
    with open(log, "a" if append else "w") if log else contextlib.nullcontext() as err:
        p = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=err, text=True)
        sampler = RssSampler(p.pid)
        sampler.start()
        out, _ = p.communicate()
        sampler.stop()
    return Run(p.returncode, out, time.monotonic() - t0, sampler.peak_kb // 1024, sampler.samples,
               (load0, loadavg()))


def splatcli(args: list[str], log: Path, *, cwd: Path = REPO, env: dict | None = None, append: bool = False) -> Run:
    """`splatcli ARGS --json -q` as a measured child (`run`); a failure ends the benchmark, naming the log."""
    r = run(SPLATCLI + [*args, "--json", "-q"], log, cwd=cwd, env=env, append=append)
    if r.returncode != 0:
        raise SystemExit(f"splatcli {args[0]} failed (exit {r.returncode}); see {log}")
    return r


# ---- curves, plots, the document ------------------------------------------------------


def train_fresh(scene: str, dest: Path, args: list[str], /, *, cwd: Path = REPO, env: dict | None = None,
                **extra) -> dict:
    """`splatcli train --device cpu ARGS` on a fresh copy (`dest`) of the processed `scene`, its
    log beside it (dest.log): what a benchmark keeps of it (`Run.train_record`, with `extra`)."""
    proj = fresh_copy(ensure_processed(scene), dest)
    cmd = ["train", str(proj), "--device", "cpu", *args]
    print(f"[{scene}/{dest.name}] {' '.join(cmd)}", flush=True)
    r = splatcli(cmd, dest.parent / f"{dest.name}.log", cwd=cwd, env=env)
    return r.train_record(proj, **extra)


def psnr_curve(project: Path) -> list[tuple[float, float]]:
    """Held-out PSNR against training seconds, from the project's train log (splatcli.eval.curve)."""
    return [(p.elapsed_s, p.psnr) for p in read_curve(Project(Path(project)).train_log_path)]


def seconds_to(curve: list[tuple[float, float]], target: float) -> float | None:
    """Training seconds of the first held-out evaluation within TOL_DB of `target`."""
    return next((t for t, p in curve if p >= target - TOL_DB), None)


def fmt(v, spec=".2f") -> str:
    """A table cell: `v` formatted, or a dash where there is none."""
    return "–" if v is None else format(v, spec)


def load_span(r: dict) -> str:
    """A table cell: the 1-minute load average before → after a run (its record's load_before, load_after)."""
    return f"{r['load_before'][0]} → {r['load_after'][0]}"


def psnr_figure(path: Path, scene: str, curves: dict[str, list[tuple[float, float]]],
                side: Callable[[Any], None] | None = None) -> bool:
    """Held-out PSNR against training seconds, one line per labelled curve, drawn off-screen
    into the PNG `path` (with `side` drawing on a second axis beside it); False where
    matplotlib (the `plots` extra) is absent."""
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        return False
    fig = Figure(figsize=(6 if side is None else 10, 4), dpi=100)
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 1 if side is None else 2)
    ax = axes if side is None else axes[0]
    for label, curve in curves.items():
        ax.plot([t for t, _ in curve], [p for _, p in curve], "o-", label=label)
    ax.set_xlabel("training time (s)")
    ax.set_ylabel("held-out PSNR (dB)")
    ax.set_title(f"{scene}: PSNR against training time")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    if side is not None:
        side(axes[1])
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, format="png")
    return True


def scene_parser(doc: str, scenes: str, train_args: str) -> argparse.ArgumentParser:
    """The options of a benchmark that trains scenes (`train_scenes`); the script adds its own."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default=scenes, help="comma-separated (bench/common.py SCENES)")
    ap.add_argument("--train-args", default=train_args, help="train's arguments (each scene adds its own)")
    ap.add_argument("--eval-every", type=int, default=250)
    ap.add_argument("--no-write", action="store_true", help="leave docs/benchmarks.md as it is")
    return ap


def train_scenes(out: Path, scenes: str, train_args: str, eval_every: int, name: str,
                 runs: Callable[[str, list[str]], list[dict]],
                 plot: Callable[[str, list[dict], Path], bool]) -> dict:
    """For each scene of `scenes` (comma-separated): `runs(scene, args)`, args being `train_args`,
    the scene's own and --eval-every; their figure by `plot` (docs/figures/<name>_<scene>.png).
    Kept in out/results.json beside the scenes of earlier runs, which it returns."""
    out.mkdir(parents=True, exist_ok=True)
    path = out / "results.json"
    results = json.loads(path.read_text()) if path.exists() else {}
    for scene in [s for s in scenes.split(",") if s]:
        done = runs(scene, shlex.split(train_args) + [*SCENES[scene][2], "--eval-every", str(eval_every)])
        fig = FIGURES / f"{name}_{scene}.png"
        results[scene] = {"runs": done, "figure": str(fig) if plot(scene, done, fig) else None}
        path.write_text(json.dumps(results, indent=1))
    return results


def scene_benchmark(args: argparse.Namespace, out: Path, name: str, runs: Callable[[str, list[str]], list[dict]],
                    plot: Callable[[str, list[dict], Path], bool], head: list[str],
                    row: Callable[[str, dict, dict, float | None, float | None], str]) -> None:
    """The benchmark `scene_parser`'s `args` ask for: `train_scenes`, then its section published:
    `head` (heading, text, table header), each scene's runs, a row each (`row(scene, run, first,
    t, speed-up)`: the seconds to the first run's final PSNR, `seconds_to`, and the speed-up over
    the first run there, None where either never got there), and its figure, where one was drawn."""
    results = train_scenes(out, args.scenes, args.train_args, args.eval_every, name, runs, plot)
    lines = list(head)
    for scene, r in results.items():
        first = r["runs"][0]
        ts = [seconds_to(run["curve"], first["final_psnr"]) for run in r["runs"]]
        lines += [row(scene, run, first, t, ts[0] / t if t and ts[0] else None) for run, t in zip(r["runs"], ts)]
        if r.get("figure"):
            lines += ["", f"![{scene}](figures/{Path(r['figure']).name})", ""]
    publish(head[0], "\n".join(lines) + "\n", write=not args.no_write)


def publish(heading: str, text: str, *, write: bool) -> None:
    """A benchmark's section: printed, and written into docs/benchmarks.md (`write_section`)
    unless the run said --no-write."""
    print(text)
    if write:
        write_section(heading, text)


def write_section(heading: str, text: str, doc: Path = DOC) -> None:
    """Replace the section that starts at the line `heading` (up to the next "## "
    line) with `text`, or append it; other sections stay as they are. Atomic."""
    old = doc.read_text(encoding="utf-8") if doc.exists() else "# Benchmarks\n"
    lines = old.splitlines(keepends=True)
    start = next((i for i, ln in enumerate(lines) if ln.strip() == heading), None)
    if start is None:
        new = old.rstrip("\n") + "\n\n" + text
    else:
        end = next((i for i in range(start + 1, len(lines)) if lines[i].startswith("## ")), len(lines))
        rest = "".join(lines[end:])
        new = "".join(lines[:start]) + text + ("\n" + rest if rest else "")
    tmp = doc.with_suffix(".md.tmp")
    tmp.write_text(new, encoding="utf-8")
    os.replace(tmp, doc)
