"""The web viewer (`splatcli view`, `train --viewer`): first frame, picture, training overhead.

    .venv/bin/python bench/viewer.py [--project demo-project] [--scene lego] [--iterations 1000] [--no-write]

1. First frame: headless Chromium (SwiftShader: WebGL on the CPU) opens the viewer of a
   200,000-Gaussian scene (the fox model of bench/formats.py, resampled to 200k with its
   SH degree 3) and of the real models; the time is from navigation start to the first
   frame whose middle differs from the background (window.splatcli.firstFrameMs).
2. Picture: every test camera of PROJECT (make demo's project), the browser's screenshot
   against `splatcli render` of the same camera, PSNR; the first one is saved as
   docs/figures/viewer.png with the panel shown (README's screenshot).
3. Overhead: `train --preset fast --max-size 200 --iterations N` on SCENE, one after the
   other in one run: without a viewer; with --viewer and a client that polls as the page
   does (/api/scene every 2 s, the .ply on every new version); with --viewer and
   headless Chromium showing the page; and without a viewer again.
Results go to bench/out/viewer/results.json and the "## viewer" section of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import threading
import time
import urllib.request
from pathlib import Path

import cv2
import torch

from browser import capture, open_page, psnr_u8
from common import REPO, SPLATCLI, ensure_processed, fresh_copy, load_span, loadavg, write_section
from splatcli.gaussians import Gaussians
from splatcli.io.ply import write_ply
from splatcli.model import load_model
from splatcli.viewer import ViewerServer, open_scene

OUT = REPO / "bench" / "out" / "viewer"
FIGURE = REPO / "docs" / "figures" / "viewer.png"
MODELS = REPO / "bench" / "out" / "formats" / "models"


def resampled(g: Gaussians, n: int, seed: int = 0) -> Gaussians:
    """`n` Gaussians drawn from `g` with replacement, each moved by a fraction of its own size."""
    gen = torch.Generator().manual_seed(seed)
    idx = torch.randint(len(g), (n,), generator=gen)
    out = g.select(idx)
    out.means = out.means + torch.randn(out.means.shape, generator=gen) * out.log_scales.exp() * 0.5
    return out


def first_frame(source: Path, size=(1280, 720), reps: int = 3) -> dict:
    store = open_scene(source)
    s = store.state()
    times, decoded = [], []
    l0 = loadavg()
    with ViewerServer(store, "127.0.0.1", 0) as server:
        for _ in range(reps):
            with open_page(server.url, *size) as (_, st):
                times.append(st["firstFrameMs"] / 1000)
                decoded.append(st["marks"]["splats"] / 1000)
    return {"source": str(source.relative_to(REPO)) if source.is_relative_to(REPO) else str(source),
            "num_gaussians": s["num_gaussians"], "sh_degree": s["sh_degree"], "mb": round(s["ply_bytes"] / 1e6, 1),
            "first_frame_s": sorted(times), "decoded_s": sorted(decoded), "load_before": [l0], "load_after": [loadavg()]}


def pictures(project: Path) -> list[dict]:
    rend = OUT / "renders"
    r = subprocess.run(SPLATCLI + ["render", str(project), "--split", "test", "-o", str(rend), "-q"], cwd=REPO)
    assert r.returncode == 0
    store = open_scene(project)
    rows = []
    with ViewerServer(store, "127.0.0.1", 0) as server:
        for i, c in enumerate(x for x in store.state()["cameras"] if x["split"] == "test"):
            ref = cv2.imread(str(rend / Path(c["name"]).with_suffix(".png").name))[..., ::-1]
            h, w = ref.shape[:2]  # render draws at the trained resolution; the page fits the camera to its height
            with open_page(f"{server.url}?camera={c['name']}&hud=0", w, h) as (d, st):
                time.sleep(1.5)
                shot = capture(d, w, h)
            rows.append({"camera": c["name"], "size": f"{w}x{h}", "psnr": round(psnr_u8(shot, ref), 2)})
            if i == 0:  # README's screenshot: the same view, with the panel
                W, H = 960, 640
                with open_page(f"{server.url}?camera={c['name']}", W, H) as (d, st):
                    time.sleep(1.5)
                    FIGURE.parent.mkdir(parents=True, exist_ok=True)
                    cv2.imwrite(str(FIGURE), capture(d, W, H)[..., ::-1])
    return rows


class Poller(threading.Thread):
    """What the page does, without drawing: /api/scene every 2 s, the .ply on each new version."""

    def __init__(self, url: str) -> None:
        super().__init__(daemon=True)
        self.url, self.stop, self.versions, self.bytes = url, threading.Event(), 0, 0

    def run(self) -> None:
        seen = None
        while not self.stop.wait(2.0):
            try:
                with urllib.request.urlopen(self.url + "api/scene", timeout=10) as r:
                    v = json.loads(r.read())["version"]
                if v != seen:
                    with urllib.request.urlopen(self.url + "api/scene.ply", timeout=60) as r:
                        self.bytes += len(r.read())
                    seen, self.versions = v, self.versions + 1
            except OSError:
                pass


def train_run(scene: str, label: str, iterations: int, client: str | None) -> dict:
    proj = fresh_copy(ensure_processed(scene), OUT / scene / label)
    cmd = SPLATCLI + ["train", str(proj), "--device", "cpu", "--json", "--preset", "fast",
           "--max-size", "200", "--iterations", str(iterations), "--eval-every", str(iterations // 4)]
    if client:
        cmd += ["--viewer", "--viewer-port", "0"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    l0 = loadavg()
    p = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    extra: dict = {}
    if client:
        url = None
        for line in p.stderr:  # the note with the URL comes before the progress display
            m = re.search(r"live viewer at (http://\S+)", line)
            if m:
                url = m.group(1)
                break
        assert url, "no viewer URL"
        drain = threading.Thread(target=p.stderr.read, daemon=True)
        drain.start()
        if client == "poller":
            poller = Poller(url)
            poller.start()
            out = p.stdout.read()
            poller.stop.set()
            extra = {"versions_fetched": poller.versions, "mb_fetched": round(poller.bytes / 1e6, 1)}
        else:
            with open_page(url, 960, 600, timeout_s=300) as (d, _):
                out = p.stdout.read()
                extra = {"versions_shown": d.execute_script("return window.splatcli.version")}
    else:
        out, _ = p.communicate()
    p.wait()
    assert p.returncode == 0, f"{label}: exit {p.returncode}"
    s = json.loads(out.strip().splitlines()[-1])
    return {"label": label, "client": client, "train_seconds": s["train_seconds"], "psnr": s["psnr"],
            "steps": s["steps"], "load_before": [l0], "load_after": [loadavg()], **extra}


def markdown(res: dict) -> str:
    lines = ["## viewer", "",
             "Measured by `python bench/viewer.py` on this machine (2 cores, no GPU): headless "
             f"{res['chromium']} with WebGL on SwiftShader (the CPU), Spark 2.2.0. Load average (1 min) before → after.", "",
             "**First frame** (1280×720, navigation start to the first frame showing the scene; three page loads):", "",
             "| scene | Gaussians | SH | .ply MB | scene decoded s (median) | first frame s (min / median / max) | load |",
             "| --- | ---: | ---: | ---: | ---: | --- | --- |"]
    for r in res["first_frame"]:
        t = r["first_frame_s"]
        lines.append(f"| {r['source']} | {r['num_gaussians']:,} | {r['sh_degree']} | {r['mb']} | "
                     f"{r['decoded_s'][len(t) // 2]:.2f} | {t[0]:.2f} / {t[len(t) // 2]:.2f} / {t[-1]:.2f} | {load_span(r)} |")
    lines += ["", f"**Picture**: the browser's screenshot at each test camera of `{res['project']}` against "
              "`splatcli render` of that camera:", "", "| camera | size | PSNR dB |", "| --- | --- | ---: |"]
    lines += [f"| {r['camera']} | {r['size']} | {r['psnr']:.2f} |" for r in res["pictures"]]
    import statistics

    base = statistics.median(r["train_seconds"] for r in res["train"] if r["client"] is None)
    lines += ["", f"**Training overhead** (`train --preset fast --max-size 200 --iterations {res['iterations']}` on "
              f"{res['scene']}, one torch thread, one after the other):", "",
              "| run | train s | vs median without viewer | held-out PSNR | client | load |", "| --- | ---: | ---: | ---: | --- | --- |"]
    for r in res["train"]:
        c = {None: "–", "poller": f"polls like the page: {r.get('versions_fetched')} versions, {r.get('mb_fetched')} MB",
             "chromium": f"Chromium showing the page ({r.get('versions_shown')} versions)"}[r["client"]]
        lines.append(f"| {r['label']} | {r['train_seconds']:.1f} | {r['train_seconds'] / base:.3f} | {r['psnr']:.2f} | "
                     f"{c} | {load_span(r)} |")
    lines += ["", "![viewer](figures/viewer.png)", ""]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--project", default="demo-project")
    ap.add_argument("--scene", default="lego")
    ap.add_argument("--iterations", type=int, default=1000)
    ap.add_argument("--skip", default="", help="comma list of parts to skip: frame,picture,train")
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    skip = set(args.skip.split(","))
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / "results.json"
    res = json.loads(path.read_text()) if path.exists() else {}
    res["chromium"] = subprocess.run(["chromium", "--version"], capture_output=True, text=True).stdout.strip()
    res["project"], res["scene"], res["iterations"] = args.project, args.scene, args.iterations
    if "frame" not in skip:
        big = OUT / "fox-200k.ply"
        write_ply(big, resampled(load_model(MODELS / "fox", torch.device("cpu")).gaussians, 200_000))
        res["first_frame"] = [first_frame(big), first_frame(MODELS / "fox"), first_frame(REPO / args.project)]
        res["first_frame_load"] = [loadavg()]
        print(json.dumps(res["first_frame"], indent=1), flush=True)
    if "picture" not in skip:
        os.chdir(REPO)  # the page shows the project as the user names it
        res["pictures"] = pictures(Path(args.project))
        print(json.dumps(res["pictures"], indent=1), flush=True)
    if "train" not in skip:
        res["train"] = []
        for label, client in [("no viewer", None), ("--viewer, polling client", "poller"), ("no viewer (2)", None),
                              ("--viewer, polling client (2)", "poller"), ("--viewer, Chromium", "chromium"),
                              ("no viewer (3)", None)]:
            res["train"].append(train_run(args.scene, label, args.iterations, client))
            print(json.dumps(res["train"][-1]), flush=True)
    path.write_text(json.dumps(res, indent=1))
    if not args.no_write:
        write_section("## viewer", markdown(res))


if __name__ == "__main__":
    main()
