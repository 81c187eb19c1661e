"""`splatcli view` and `train --viewer`: a web viewer served from this machine.

The page runs Spark (static/vendor); server.py serves it and the scene. This module
builds the scene from a project or a splat file and keeps it current during training.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from ..events import Event, EventSink, Progress, Snapshot
from ..model import load_model
from ..project import Project
from ..sfm.colmap import read_project_scene
from .server import CameraInfo, SceneStore, ViewerServer, is_loopback

__all__ = ["SceneStore", "ViewerServer", "is_loopback", "open_scene", "project_scene", "LiveSink"]


def project_scene(project: Project, source: str) -> SceneStore:
    """A store with the project's cameras (train/test), background and up direction; no Gaussians yet."""
    cams = read_project_scene(project).cameras
    test = set(project.splits().get("test", []))
    infos = [CameraInfo(name=c.name, split="test" if c.name in test else "train", width=c.width, height=c.height,
                        K=[float(x) for x in c.K.reshape(-1)], viewmat=[float(x) for x in c.viewmat.reshape(-1)])
             for c in cams]
    store = SceneStore(source=source, background=tuple(project.background() or (0.0, 0.0, 0.0)), cameras=infos)
    if cams:  # the cameras' mean "up" (-y of each camera, in world coordinates): the scene stands upright
        up = -np.mean([c.viewmat[1, :3] for c in cams], axis=0)
        if np.linalg.norm(up) > 1e-6:
            store.up = [float(x) for x in up / np.linalg.norm(up)]
    return store


def open_scene(source: str | Path, appearance_of: str | None = None) -> SceneStore:
    """The store for `splatcli view SOURCE`: a project (latest checkpoint) or any splat file;
    `appearance_of`: a training photo's light instead of the scene's (model.load_model)."""
    m = load_model(source, torch.device("cpu"), appearance_of)
    if m.project is not None:
        store = project_scene(m.project, str(source))
        store.background = m.lit(store.background)  # what shows through goes through the photo's light too
    else:
        store = SceneStore(source=str(source), file_bytes=m.path.stat().st_size)
    store.publish(m.gaussians, {"step": m.step} if m.step is not None else {})
    store.ply()  # built now, before the URL is shown, not when the page first asks
    return store


class LiveSink:
    """An event sink for `train --viewer`: passes every event on to `inner` and, at most
    every `every_s` seconds and only while a page is looking, copies the model of a
    Snapshot event into `store`."""

    def __init__(self, store: SceneStore, inner: EventSink | None, every_s: float = 3.0) -> None:
        self.store, self.inner, self.every_s = store, inner, every_s
        self._last = -float("inf")
        self._info: dict = {}

    def __call__(self, event: Event) -> None:
        if isinstance(event, Snapshot):
            now = time.monotonic()
            if now - self._last >= self.every_s and (self.store.wanted() or self.store.version == 0):
                self._last = now
                self.store.publish(event.model(), {"step": event.step, **self._info})
            return
        if isinstance(event, Progress):
            self._info = {k: v for k, v in event.info.items() if isinstance(v, (int, float, str))}
        if self.inner is not None:
            self.inner(event)
