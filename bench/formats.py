"""File formats: size against held-out error on trained scenes, and codec speed and memory at 1M Gaussians.

    .venv/bin/python bench/formats.py [PROJECT ...] [--million] [--formats ply,spz,sog,compressed-ply,splat]
                                      [--no-write]

For each trained PROJECT it runs `splatcli eval PROJECT --formats ...` (each format
written, read back through splatcli's reader and scored on the held-out views) and
tabulates bytes, bytes per Gaussian, the ratio to .ply, held-out PSNR and the dB lost.
With --million it times encode + decode of 1,000,000 synthetic Gaussians (SH degree 3)
per format, each in a fresh process, and reports its peak memory above the process's
baseline against the raw parameter size (1M x 59 float32 = 236 MB). Results go to the
"## formats" section of docs/benchmarks.md, with the load average beside every timing.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from common import REPO, run, splatcli, write_section

OUT = REPO / "bench" / "out" / "formats"
FORMATS = "ply,spz,sog,compressed-ply,splat"

CODEC = r"""
import json, resource, sys, time, torch
from splatcli.gaussians import Gaussians
from splatcli.io.formats import read_format, write_format
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


def scene_table(projects: list[str], formats: str) -> list[str]:
    rows = []
    for proj in projects:
        out = OUT / Path(proj).name
        cmd = ["eval", proj, "--formats", formats, "--budgets", "1", "--no-plots", "-o", str(out)]
        print("splatcli " + " ".join(cmd), flush=True)
        r = splatcli(cmd, OUT / f"{Path(proj).name}.log", cwd=Path.cwd(), env={**os.environ, "OMP_NUM_THREADS": "1"})
        rep = json.loads((out / "eval.json").read_text())
        load0, load1 = r.load
        steps = rep.get("train_steps")
        for f in rep["formats"]:
            rows.append(f"| `{Path(proj).parent.name}/{Path(proj).name}` ({steps} steps, {rep['width']}x{rep['height']}) "
                        f"| {rep['num_gaussians']:,} | {f['format']} | {f['bytes'] / 1e6:.2f} MB | "
                        f"{f['bytes_per_gaussian']:.1f} | {f['ratio']:.1f}x | {f['psnr']:.2f} | {f['db_lost']:.2f} | "
                        f"{f['encode_s']:.2f} + {f['decode_s']:.2f} | {load0:.2f} → {load1:.2f} |")
    return rows


def million(formats: str, n: int = 1_000_000) -> list[str]:
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
        rows.append(f"| {fmt} | {d['bytes'] / 1e6:.1f} MB | {d['encode_s']:.1f} | {d['decode_s']:.1f} | "
                    f"{d['encode_s'] + d['decode_s']:.1f} | {d['extra_mb']:.0f} MB ({d['extra_mb'] / raw_mb:.2f}x) | "
                    f"{r.load[0]:.2f} → {r.load[1]:.2f} |")
        print(rows[-1], flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("projects", nargs="*")
    ap.add_argument("--formats", default=FORMATS)
    ap.add_argument("--million", action="store_true")
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    text = ["## formats", "",
            "Measured by `python bench/formats.py`: `splatcli eval PROJECT --formats ...` writes the model in each "
            "format, reads it back through splatcli's reader and scores the held-out views (2 cores, one torch "
            "thread). *lost* is dB below the full-precision model; *ratio* is .ply bytes over these bytes.", ""]
    if args.projects:
        text += ["| model | Gaussians | format | size | bytes/Gaussian | ratio | held-out PSNR | lost (dB) | "
                 "encode + decode s | load before → after |",
                 "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |", *scene_table(args.projects, args.formats),
                 ""]
    if args.million:
        text += [f"Encode + decode of 1,000,000 synthetic Gaussians (SH degree 3), each format in a fresh process "
                 f"with OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', '2')}; *extra memory* is the peak RSS above "
                 "the process's own after the model exists, against the raw parameters (236 MB).", "",
                 "| format | size | encode s | decode s | total s | extra memory (x raw) | load before → after |",
                 "| --- | --- | --- | --- | --- | --- | --- |", *million(args.formats), ""]
    if not args.no_write:
        write_section("## formats", "\n".join(text) + "\n")
    print("\n".join(text))


if __name__ == "__main__":
    main()
