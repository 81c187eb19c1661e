"""File formats: size against held-out error on trained scenes, and codec speed and memory at 1M Gaussians.

    .venv/bin/python bench/formats.py [PROJECT ...] [--million] [--formats ply,spz,sog,compressed-ply,splat]

For each trained PROJECT it runs `splatcli eval PROJECT --formats ...` (each format
written, read back through splatcli's reader and scored on the held-out views) and
tabulates bytes, bytes per Gaussian, the ratio to .ply, held-out PSNR and the dB lost.
With --million it times encode + decode of 1,000,000 synthetic Gaussians (SH degree 3)
per format, each in a fresh process, and reports its peak memory above the process's
baseline against the raw parameter size (1M x 59 float32 = 236 MB). Results, with the load
average beside every timing: bench/out/formats.json (common.report), the table printed.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from common import OUT as ALL_OUT, report, run, splatcli

OUT = ALL_OUT / "formats"
FORMATS = "ply,spz,sog,compressed-ply,splat"

CODEC = r"""
import json, resource, sys, time, torch
from splatcli.gaussians import Gaussians
from splatcli.formats.registry import read_format, write_format
fmt, path, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
g = torch.Generator().manual_seed(0)
r = lambda *s: torch.randn(*s, generator=g)
sh = r(n, 16, 3) * 0.05
sh[:, 0] = r(n, 3)
G = Gaussians(r(n, 3) * 3, r(n, 4), r(n, 3) * 0.5 - 4, r(n) * 2, sh)
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t0 = time.perf_counter(); w = write_format(fmt, path, G); t1 = time.perf_counter()
back = read_format(path, fmt=fmt).gaussians; t2 = time.perf_counter()
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({"bytes": w.bytes, "encode_s": t1 - t0, "decode_s": t2 - t1, "extra_mb": (peak - base) / 1024,
                  "rows": len(back)}))
"""


def scene_rows(projects: list[str], formats: str) -> list[dict]:
    """Each format of each trained project, written, read back and scored by `splatcli eval` (one torch thread)."""
    rows = []
    for proj in projects:
        out = OUT / Path(proj).name
        cmd = ["eval", proj, "--formats", formats, "--budgets", "1", "--no-plots", "-o", str(out)]
        print("splatcli " + " ".join(cmd), flush=True)
        r = splatcli(cmd, OUT / f"{Path(proj).name}.log", cwd=Path.cwd(), env={**os.environ, "OMP_NUM_THREADS": "1"})
        rep = json.loads((out / "eval.json").read_text())
        for f in rep["formats"]:  # ratio: .ply bytes over these; db_lost: below the full-precision model
            rows.append({"model": f"{Path(proj).parent.name}/{Path(proj).name}", "steps": rep.get("train_steps"),
                         "size": f"{rep['width']}x{rep['height']}", "gaussians": rep["num_gaussians"],
                         "format": f["format"], "mb": f["bytes"] / 1e6, "bytes_per_gaussian": f["bytes_per_gaussian"],
                         "ratio": f["ratio"], "psnr": f["psnr"], "db_lost": f["db_lost"], "encode_s": f["encode_s"],
                         "decode_s": f["decode_s"], "load_before": r.load[0], "load_after": r.load[1]})
    return rows


def million(formats: str, n: int = 1_000_000) -> list[dict]:
    """Encode + decode of `n` synthetic Gaussians (SH degree 3), each format in a fresh process; extra_mb
    is the peak RSS above the process's own once the model exists, against the raw parameters."""
    OUT.mkdir(parents=True, exist_ok=True)
    rows = []
    raw_mb = n * 59 * 4 / 1e6
    for fmt in formats.split(","):
        path = OUT / f"million.{fmt.replace('-', '.')}"
        log = OUT / f"million.{fmt}.log"
        r = run([sys.executable, "-c", CODEC, fmt, str(path), str(n)], log,
                env={**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "2")})
        if r.returncode != 0:
            raise SystemExit(f"{fmt}: the codec run failed (exit {r.returncode}); see {log}")
        d = r.summary
        path.unlink(missing_ok=True)
        rows.append({"model": f"{n:,} synthetic", "format": fmt, "mb": d["bytes"] / 1e6, "encode_s": d["encode_s"],
                     "decode_s": d["decode_s"], "extra_mb": d["extra_mb"], "extra_x_raw": d["extra_mb"] / raw_mb,
                     "load_before": r.load[0], "load_after": r.load[1]})
        print(rows[-1], flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("projects", nargs="*")
    ap.add_argument("--formats", default=FORMATS)
    ap.add_argument("--million", action="store_true")
    args = ap.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    rows = scene_rows(args.projects, args.formats) + (million(args.formats) if args.million else [])
    report("formats", rows, columns=["model", "format", "mb", "bytes_per_gaussian", "ratio", "psnr", "db_lost",
                                     "encode_s", "decode_s", "extra_mb", "load_before", "load_after"])


if __name__ == "__main__":
    main()
