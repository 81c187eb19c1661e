"""`splatcli export --format web`: `view`'s page as a folder that any static web server serves.

The folder holds what server.py serves, at the same relative paths, so the page is the same
one: index.html, static/ (viewer.js and the vendored renderer, uncompressed: a plain server
sends no Content-Encoding), api/scene (server.py's /api/scene answer as a file, with
"static": true and "splats": the model's file) and api/scene.sog (the model, in place of
/api/scene.ply). The page then neither polls for a training run nor offers the points
display (its file would be as large as the .sog). The folder is written under a hidden name
beside the target and renamed into place: an interrupted export leaves no complete-looking folder.
"""

from __future__ import annotations

import dataclasses
import gzip
import json
import os
import shutil
import tempfile
from pathlib import Path

from ..errors import SplatError
from ..events import EventSink
from ..files.atomic import UMASK, atomic_write_bytes
from ..formats.export import ExportConfig, ExportResult, check_web_folder, export_gaussians
from ..model import LoadedModel
from . import project_scene
from .server import SceneStore, assets

SPLATS = "api/scene.sog"


def export_site(m: LoadedModel, out: Path, config: ExportConfig, on_event: EventSink | None = None) -> ExportResult:
    """Write the folder `out` showing `m` (a project's cameras and background when it has one)."""
    check_web_folder(out)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    except OSError as exc:
        raise SplatError(f"cannot write {out}: {exc.strerror or exc}") from exc
    try:
        os.chmod(tmp, 0o777 & ~UMASK)  # mkdtemp's 0700 would hide the site from a server run as another user
        r = export_gaussians(m.gaussians, tmp / SPLATS, dataclasses.replace(config, format="sog"),
                             source=m.path, step=m.step, notes=m.notes, on_event=on_event)
        for url, a in assets().items():
            atomic_write_bytes(tmp / ("index.html" if url == "/" else url[1:]), gzip.decompress(a.body) if a.gzipped else a.body)
        store = project_scene(m.project, m.project.root.name) if m.project else SceneStore(source=m.path.name)
        store.publish(m.gaussians)
        state = {**store.state(), "static": True, "splats": SPLATS, "file_bytes": r.bytes}
        atomic_write_bytes(tmp / "api" / "scene", json.dumps(state).encode())
        old = out.with_name(f".{out.name}.old.tmp")
        if out.exists():  # a previous web export (check_web_folder): out of the way, then removed
            shutil.rmtree(old, ignore_errors=True)
            os.replace(out, old)
        os.replace(tmp, out)
        shutil.rmtree(old, ignore_errors=True)
    except BaseException as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(exc, OSError):
            raise SplatError(f"cannot write {out}: {exc.strerror or exc}") from exc
        raise
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    return dataclasses.replace(r, path=out, format="web", bytes=size)
