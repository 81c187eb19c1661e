"""Soak: a 20k-step `train --preset fast --max-gaussians 500` on the tests' tiny scene, resident memory and
open file descriptors from its log (one line every 100 steps).

    .venv/bin/python bench/soak.py [--steps 20000] [--no-write]

tests/test_soak.py asserts the same run stays flat once densification stops; this
script records the figures in the "## soak" section of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

from common import SPLATCLI, publish, run
from splatcli.eval.curve import read_log
from tiny_project import make_tiny_project  # the scene tests/test_soak.py runs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=20_000)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        proj = make_tiny_project(Path(d) / "p", trained=False)
        proj.update_manifest(scene={**proj.manifest()["scene"], "bounds_min": [-1.0] * 3, "bounds_max": [1.0] * 3})
        r = run(SPLATCLI + ["train", str(proj.root), "--preset", "fast", "--max-gaussians", "500",
                            "--iterations", str(args.steps), "--device", "cpu", "--quiet"],
                env={**os.environ, "OMP_NUM_THREADS": "1"})
        if r.returncode != 0:
            raise SystemExit(f"train failed (exit {r.returncode})")
        wall, (load0, load1) = r.wall_s, r.load
        log = read_log(proj.train_log_path)
    every = max(1, args.steps // 10 // 100) * 100
    rows = [x for x in log if x["step"] % every == 0 or x["step"] == 100]
    late = [x for x in log if x["step"] >= 5000]
    out = ["## soak", "",
           f"Measured by `python bench/soak.py --steps {args.steps}`: `train --preset fast --max-gaussians 500` on the tests' tiny scene "
           f"(10 views of 48x40, one torch thread; densification stops at step 4,000; a checkpoint every 1,000 "
           f"steps, two kept; held-out evaluation every 1,000), {wall:.0f} s wall, load average {load0:.2f} at the "
           f"start and {load1:.2f} at the end. tests/test_soak.py asserts the same run stays flat.", "",
           "| step | Gaussians | RSS MiB | open descriptors |", "| ---: | ---: | ---: | ---: |"]
    out += [f"| {x['step']:,} | {x['num_gaussians']} | {x.get('rss_mb')} | {x.get('open_fds')} |" for x in rows]
    if late:
        rss = [x["rss_mb"] for x in late]
        out += ["", f"From step 5,000 to {args.steps:,}: RSS {min(rss)}-{max(rss)} MiB "
                f"({max(rss) - min(rss)} MiB spread), open descriptors {sorted({x['open_fds'] for x in late})}."]
    publish("## soak", "\n".join(out) + "\n", write=not args.no_write)


if __name__ == "__main__":
    main()
