"""A tiny trained project built by hand, for render/export/eval tests.

Ten 48x40 cameras on a ring look at a cloud of 300 Gaussians. The "photos" are
renders of the true Gaussians; the "trained" checkpoint is a perturbed copy, so
PSNR is finite and not perfect. The sparse model is a COLMAP text model that
pycolmap reads; the manifest holds what `process` and `train` would record.
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np
import torch

from splatcli.camera import Camera
from splatcli.files.checkpoint import save_checkpoint
from splatcli.formats.ply import ply_bytes
from splatcli.gaussians import Gaussians
from splatcli.project import LOCK_NAME, Project
from splatcli.render import rasterize
from splatcli.views.paths import look_at

W, H = 48, 40
N_CAMS = 10


def tiny_gaussians(n: int = 300, seed: int = 0, sh_degree: int = 1) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.randn(*s, generator=g)  # noqa: E731
    sh = r(n, (sh_degree + 1) ** 2, 3) * 0.3
    sh[:, 0] = r(n, 3) * 1.2
    return Gaussians(means=r(n, 3) * 0.5, quats=r(n, 4), log_scales=r(n, 3) * 0.3 - 2.6,
                     opacity_logits=r(n) + 1.0, sh=sh)


def ring_cameras(n: int = N_CAMS, scale: int = 1, center=(0.0, 0.0, 0.0)) -> list[Camera]:
    w, h = W * scale, H * scale
    K = np.array([[40.0 * scale, 0, w / 2], [0, 40.0 * scale, h / 2], [0, 0, 1]])
    cams = []
    for i in range(n):
        a = 2 * math.pi * i / n
        eye = np.array([3.0 * math.cos(a), -0.8, 3.0 * math.sin(a)]) + np.asarray(center)
        cams.append(Camera(name=f"img_{i:03d}.png", width=w, height=h, K=K,
                           viewmat=look_at(eye, np.asarray(center, dtype=float), np.array([0.0, -1.0, 0.0]))))
    return cams


def _write_colmap_text(sparse: Path, cams: list[Camera]) -> None:
    from splatcli.views.paths import rot_to_quat as _rot_to_quat

    sparse.mkdir(parents=True, exist_ok=True)
    c = cams[0]
    (sparse / "cameras.txt").write_text(
        f"1 PINHOLE {c.width} {c.height} {c.K[0, 0]} {c.K[1, 1]} {c.K[0, 2]} {c.K[1, 2]}\n")
    lines = []
    for i, cam in enumerate(cams, start=1):
        q = _rot_to_quat(cam.viewmat[:3, :3])
        t = cam.viewmat[:3, 3]
        lines.append(f"{i} {q[0]} {q[1]} {q[2]} {q[3]} {t[0]} {t[1]} {t[2]} 1 {cam.name}\n\n")
    (sparse / "images.txt").write_text("".join(lines))
    (sparse / "points3D.txt").write_text("")


def render_gt(g: Gaussians, cam: Camera, bg: float = 0.0) -> np.ndarray:  # -> [H, W, 3] uint8
    vm, K = cam.torch(torch.device("cpu"))
    with torch.no_grad():
        out = rasterize(g.means, g.quats, g.log_scales, g.opacity_logits, g.sh, vm, K, cam.width, cam.height,
                        torch.full((3,), bg))
    return (out.image.clamp(0, 1) * 255).round().to(torch.uint8).numpy()


def make_tiny_project(root: Path, *, trained: bool = True, background: float = 0.0, n: int = 300,
                      photos: bool = True, scale: int = 1, center=(0.0, 0.0, 0.0)) -> Project:
    """photos=False writes grey images instead of renders (faster; for error tests);
    scale multiplies the cameras' size and focal length; center moves the scene (the
    cameras look at it)."""
    import cv2

    proj = Project.create(root, source={"kind": "test", "path": "tiny"})
    cams = ring_cameras(scale=scale, center=center)
    truth = tiny_gaussians(n, seed=0)
    truth.means += torch.tensor(center, dtype=truth.means.dtype)
    proj.images_dir.mkdir(parents=True)
    for cam in cams:
        img = render_gt(truth, cam, background)[..., ::-1] if photos else np.full((cam.height, cam.width, 3), 128, np.uint8)
        cv2.imwrite(str(proj.images_dir / cam.name), img)
    _write_colmap_text(proj.sparse_dir, cams)
    names = [c.name for c in cams]
    proj.update_manifest(
        splits={"train": [n_ for i, n_ in enumerate(names) if i % 8], "test": [n_ for i, n_ in enumerate(names) if i % 8 == 0]},
        scene={"background": [background] * 3},
    )
    proj.record_step("process", config={}, summary={"num_images": len(cams)})
    if trained:
        model = tiny_gaussians(n, seed=0)
        model.means += torch.tensor(center, dtype=model.means.dtype)
        gen = torch.Generator().manual_seed(1)
        model.means += torch.randn(model.means.shape, generator=gen) * 0.02
        model.sh[:, 0] += torch.randn(model.sh[:, 0].shape, generator=gen) * 0.1
        save_checkpoint(proj.checkpoint_path(200), step=200, gaussians=model, sh_degree=1)
        proj.record_step("train", config={"downscale": 1.0, "max_size": 1600}, summary={
            "steps": 200, "train_seconds": 12.5, "num_gaussians": n, "sh_degree": 1,
            "ply_bytes": ply_bytes(n, 1), "device": "cpu", "final_loss": 0.05, "psnr": 25.0})
        log = [{"step": s, "elapsed_s": s * 0.0625, "loss": 0.2 / (1 + s / 50), "num_gaussians": n,
                **({"psnr": 15.0 + s / 20, "ssim": 0.5 + s / 1000} if s % 100 == 0 else {})}
               for s in range(0, 201, 50)]
        proj.reports_dir.mkdir(parents=True, exist_ok=True)
        proj.train_log_path.write_text("".join(json.dumps(x) + "\n" for x in log))
    return proj


# ---- CLI helpers ----------------------------------------------------------------


def run_cli(*args: object):
    """Run `splatcli ARGS` in-process; returns typer's Result (stdout and stderr apart)."""
    from typer.testing import CliRunner

    from splatcli.cli.main import app

    return CliRunner().invoke(app, [str(a) for a in args])


def run_ok(*args: object):
    """`run_cli`, asserting that the command succeeded (its output shown where it did not)."""
    r = run_cli(*args)
    assert r.exit_code == 0, r.output
    return r


def assert_user_error(result, *fragments: str, alone: bool = True) -> str:
    """Exit 2, one line `error: ...` on stderr naming what it should, no traceback; returns it.
    Errors found before any work are the only output; one found mid-way (a bad image in a
    folder) comes after the progress shown so far."""
    lines = result.stderr.strip().splitlines()
    assert result.exit_code == 2, (result.exit_code, result.output)
    assert lines and lines[-1].startswith("error: "), result.stderr
    assert sum(line.startswith("error:") for line in lines) == 1, result.stderr
    assert "Traceback" not in result.output
    if alone:
        assert len(lines) == 1 and result.stdout == "", result.output
    err = lines[-1]
    for f in fragments:
        assert f in err, (f, err)
    return err


def snapshot(*roots: Path) -> dict[str, tuple[str, int]]:
    """Every file under `roots` (or a root that is a file) with the sha256 of its bytes and its mtime
    (ns), and every folder by its name (a failed run may make and remove a temp folder inside): to
    prove nothing changed. The writer lock (held while a command runs) is not project content."""
    out: dict[str, tuple[str, int]] = {}
    for root in map(Path, roots):
        for p in [root] if root.is_file() else sorted(root.rglob("*")):
            if p.is_dir():
                out[str(p)] = ("folder", 0)
            elif p.name != LOCK_NAME:
                out[str(p)] = (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
    return out
