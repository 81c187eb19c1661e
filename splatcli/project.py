"""The project directory: the only module that knows paths and file names.

    PROJECT/
      splatcli.json    manifest: schema version, source, frame, splits, scene facts,
                       and each command's resolved config and summary
      images/          the images training uses (undistorted, RGB)
      masks/           <image name>.png, 255 = keep, when the input had masks (alpha or files)
      sfm/             database.db, sparse/0 (PINHOLE COLMAP model of images/),
                       distorted/ (the raw model, when undistortion happened)
      checkpoints/     step-000007000.pt ...
      renders/<name>/  rendered PNGs and videos
      exports/         scene.ply, scene.splat
      reports/         eval.json, eval.md, train_log.jsonl, plots
      .splatcli.lock   the writer lock (flock): process/train alone, export/eval shared

Everyone else asks a `Project` for paths; no file name appears in two places.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import math
import os
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

try:
    import fcntl
except ImportError:  # Windows: no advisory locks; writer_lock is a no-op there
    fcntl = None  # type: ignore[assignment]

from . import __version__
from .errors import NotReadyError, ProjectBusy, SplatError
from .files.atomic import atomic_write_json, read_json_file

SCHEMA_VERSION = 1
MANIFEST_NAME = "splatcli.json"
LOCK_NAME = ".splatcli.lock"
FRAME_CONVENTION = "opencv"  # x right, y down, z forward; viewmat maps world to camera
HOLDOUT_EVERY = 8  # without the data's own test split, every 8th image is held out (holdout_split)
_CKPT_RE = re.compile(r"^step-(\d{9})\.pt$")


def now_iso() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _at(*parts: str) -> property:
    """A path below the project root."""
    return property(lambda self: self.root.joinpath(*parts))


@dataclass(frozen=True)
class Project:
    """A project directory. Construct with `Project.create` (process) or
    `Project.open` (every later command)."""

    root: Path

    # ---- paths (the layout in the module docstring) ---------------------------
    manifest_path = _at(MANIFEST_NAME)
    images_dir = _at("images")
    masks_dir = _at("masks")
    sfm_dir = _at("sfm")
    database_path = _at("sfm", "database.db")
    sparse_dir = _at("sfm", "sparse", "0")  # the PINHOLE COLMAP model that matches images/
    distorted_dir = _at("sfm", "distorted")  # the raw model, kept when undistortion happened
    checkpoints_dir = _at("checkpoints")
    renders_dir = _at("renders")
    exports_dir = _at("exports")
    reports_dir = _at("reports")
    train_log_path = _at("reports", "train_log.jsonl")
    train_report_path = _at("reports", "train.json")
    process_report_path = _at("reports", "process.json")
    profile_json_path = _at("reports", "profile.json")  # train --profile
    profile_md_path = _at("reports", "profile.md")
    eval_json_path = _at("reports", "eval.json")
    eval_md_path = _at("reports", "eval.md")
    lock_path = _at(LOCK_NAME)

    def mask_path(self, image_name: str) -> Path:
        """The mask of images/<image_name>: masks/<image_name>.png (COLMAP's naming)."""
        return self.masks_dir / f"{image_name}.png"

    def plot_path(self, name: str) -> Path:
        return self.reports_dir / f"{name}.png"

    def render_dir(self, name: str) -> Path:
        return self.renders_dir / name

    def export_path(self, fmt: str = "ply") -> Path:
        """exports/scene.<format's suffix> (compressed-ply: scene.compressed.ply; web: the folder exports/web)."""
        if fmt == "web":
            return self.exports_dir / "web"
        return self.exports_dir / f"scene.{fmt.replace('-', '.')}"

    def checkpoint_path(self, step: int) -> Path:
        return self.checkpoints_dir / f"step-{int(step):09d}.pt"

    def checkpoints(self) -> list[tuple[int, Path]]:
        """All checkpoints, oldest first, as (step, path)."""
        if not self.checkpoints_dir.is_dir():
            return []
        found = []
        for p in self.checkpoints_dir.iterdir():
            m = _CKPT_RE.match(p.name)
            if m and p.is_file():
                found.append((int(m.group(1)), p))
        return sorted(found)

    def latest_checkpoint(self) -> Path | None:
        ck = self.checkpoints()
        return ck[-1][1] if ck else None

    # ---- lifecycle ---------------------------------------------------------
    @classmethod
    def create(cls, root: str | Path, *, source: dict[str, Any], overwrite: bool = False) -> Project:
        """Start a new project (used by `process`). Refuses to clobber a folder that
        holds something other than a project unless `overwrite`."""
        root = Path(root)
        if root.exists() and not root.is_dir():
            raise SplatError(f"{root}: exists and is not a directory")
        if root.is_dir() and any(root.iterdir()) and not (root / MANIFEST_NAME).exists() and not overwrite:
            raise SplatError(
                f"{root}: folder exists, is not empty and is not a splatcli project; choose another -o or pass --overwrite"
            )
        root.mkdir(parents=True, exist_ok=True)
        proj = cls(root)
        manifest = {
            "schema_version": SCHEMA_VERSION,
            "splatcli_version": __version__,
            "created_at": now_iso(),
            "frame": FRAME_CONVENTION,
            "source": source,
            "splits": {},
            "scene": {},
            "steps": {},
        }
        proj.write_manifest(manifest)
        return proj

    @classmethod
    def open(cls, root: str | Path) -> Project:
        """Open an existing project, checking it is one and of a schema we read."""
        root = Path(root)
        if not root.exists():
            raise SplatError(f"{root}: no such project directory", hint=f"run `splatcli process INPUT -o {root}` first")
        if not root.is_dir() or not (root / MANIFEST_NAME).is_file():
            raise SplatError(f"{root}: not a splatcli project (no {MANIFEST_NAME})",
                             hint=f"run `splatcli process INPUT -o {root}` first")
        proj = cls(root)
        proj.manifest()  # validates
        return proj

    # ---- manifest ----------------------------------------------------------
    def manifest(self) -> dict[str, Any]:
        data = read_json_file(self.manifest_path, "project manifest")
        if not isinstance(data, dict) or "schema_version" not in data:
            raise SplatError(f"{self.manifest_path}: not a splatcli manifest (no schema_version)")
        version = data.get("schema_version")
        if not isinstance(version, int) or version > SCHEMA_VERSION:
            raise SplatError(
                f"{self.manifest_path}: schema version {version} is newer than this splatcli reads "
                f"({SCHEMA_VERSION}); upgrade splatcli"
            )
        _check_manifest_fields(self.manifest_path, data)
        return data

    def write_manifest(self, data: dict[str, Any]) -> None:
        atomic_write_json(self.manifest_path, data)

    def update_manifest(self, **top_level: Any) -> dict[str, Any]:
        data = self.manifest()
        data.update(top_level)
        self.write_manifest(data)
        return data

    def record_step(self, step: str, *, config: dict[str, Any], summary: dict[str, Any]) -> None:
        """Record a command's resolved config and summary in the manifest."""
        data = self.manifest()
        data.setdefault("steps", {})[step] = {
            "finished_at": now_iso(),
            "splatcli_version": __version__,
            "config": config,
            "summary": summary,
        }
        self.write_manifest(data)

    def step(self, step: str) -> dict[str, Any] | None:
        return self.manifest().get("steps", {}).get(step)

    # ---- splits ------------------------------------------------------------
    def splits(self, names: list[str] | None = None) -> dict[str, list[str]]:
        """Image names per split: {"train": [...], "test": [...]}, as `process` recorded them.
        With `names` (the registered images) and no split recorded (a project assembled by
        hand), the hold-out rule's split of them (`holdout_split`), so every command uses one."""
        s = self.manifest().get("splits") or {}
        out = {"train": list(s.get("train", [])), "test": list(s.get("test", []))}
        if names is not None and not out["train"] and not out["test"]:
            return holdout_split(names)
        return out

    # ---- scene facts -------------------------------------------------------
    def background(self) -> tuple[float, float, float] | None:
        """The scene's background (white for Blender scenes) recorded by `process`."""
        bg = (self.manifest().get("scene") or {}).get("background")
        return tuple(float(v) for v in bg) if bg is not None else None  # type: ignore[return-value]

    def mask_source(self) -> str | None:
        """Where the masks in masks/ came from: "alpha" (images already composited over
        the background), "files" (a masks folder or mask_path), or None (no masks)."""
        facts = self.manifest().get("scene") or {}
        if not facts.get("masks") or not self.masks_dir.is_dir():
            return None
        return "files" if facts.get("mask_source") == "files" else "alpha"  # older projects: alpha only

    def mask_mode(self, requested: str = "auto") -> str:
        """What a --mask-mode means for this project: "ignore" (masked pixels take no part
        in the loss or the scores), "background" (they are fitted to the background
        colour) or "off". auto: background for alpha masks (the images are already
        composited over it), ignore for mask files; always off without masks."""
        source = self.mask_source()
        if source is None or requested == "off":
            return "off"
        if requested == "auto":
            return "background" if source == "alpha" else "ignore"
        return requested

    def trained_resolution(self) -> tuple[float, int | None]:
        """(downscale, max_size) that `train` recorded: eval and render use the
        resolution the model was trained at (Camera.at_resolution). A hand-edited
        value is named, not guessed."""
        tcfg = (self.step("train") or {}).get("config") or {}
        where = f"{self.manifest_path}: steps.train.config"
        d = tcfg.get("downscale")
        if d is None:
            d = 1.0
        if isinstance(d, bool) or not isinstance(d, (int, float)) or not (math.isfinite(d) and 0 < d <= 64):
            raise SplatError(f"{where}.downscale is {d!r}, not a number in (0, 64]; pass --downscale")
        m = tcfg.get("max_size")
        if m is not None and (isinstance(m, bool) or not isinstance(m, int) or m < 16):
            raise SplatError(f"{where}.max_size is {m!r}, not a whole number of pixels >= 16; pass --downscale")
        return float(d), m

    # ---- readiness ---------------------------------------------------------
    def require_processed(self) -> None:
        if self.step("process") is None or not self.sparse_dir.is_dir() or not self.images_dir.is_dir():
            raise NotReadyError(f"{self.root}: has no processed dataset", "process")

    def require_trained(self) -> Path:
        self.require_processed()
        ck = self.latest_checkpoint()
        if ck is None:
            raise NotReadyError(f"{self.root}: has no trained model (no checkpoint)", "train")
        return ck


def _check_manifest_fields(path: Path, data: dict[str, Any]) -> None:
    """The shapes every reader of the manifest relies on (a hand-edited file may break them)."""
    def bad(what: str, value: Any, expected: str) -> SplatError:
        shown = " ".join(repr(value).split())
        shown = shown if len(shown) <= 40 else shown[:37] + "..."
        return SplatError(f"{path}: manifest field {what} is {shown}, expected {expected} "
                          "(edited by hand? run `splatcli process` again)")

    for key in ("source", "splits", "scene", "steps"):
        if key in data and not isinstance(data[key], dict):
            raise bad(key, data[key], "an object")
    scene = data.get("scene") or {}
    for key, n in (("background", 3), ("bounds_min", 3), ("bounds_max", 3)):
        v = scene.get(key)
        if v is not None and not (isinstance(v, list) and len(v) == n and all(
                isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)):
            raise bad(f"scene.{key}", v, f"a list of {n} finite numbers")
    for name, names in (data.get("splits") or {}).items():
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise bad(f"splits.{name}", names, "a list of image names")
    for name, step in (data.get("steps") or {}).items():
        if not isinstance(step, dict):
            raise bad(f"steps.{name}", step, "an object")
        for k in ("config", "summary"):
            if k in step and not isinstance(step[k], dict):
                raise bad(f"steps.{name}.{k}", step[k], "an object")


@contextlib.contextmanager
def writer_lock(root: str | Path, command: str, *, shared: bool = False) -> Iterator[None]:
    """One writer per project: a `flock` on ROOT/.splatcli.lock while `command` writes
    the project. process and train rewrite the dataset and the model: they hold it
    exclusively. export and eval only add files derived from the model (`shared`): they
    may run beside each other (a Makefile's `-j` runs them together), never beside
    process or train. The kernel drops the lock when its process dies, so it never goes
    stale; a conflicting writer is refused at once with the holder's PID and command.
    Readers (render elsewhere) take no lock: every file they read is replaced
    atomically. A no-op without `fcntl`."""
    if fcntl is None:
        yield
        return
    path = Project(Path(root)).lock_path
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:
        raise SplatError(f"{path}: cannot create the project lock ({exc.strerror or exc})") from exc
    try:
        try:
            fcntl.flock(fd, (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = " and ".join(_live_holders(os.pread(fd, 4096, 0).decode("utf-8", "replace"))) or "another process"
            raise ProjectBusy(f"{root}: in use by {holder}", hint="wait for it to end; process and train need the "
                              "project to themselves, export and eval may run together") from None
        line = f"PID {os.getpid()} (splatcli {command})\n".encode()
        if shared:  # beside other shared holders: each adds its line
            os.pwrite(fd, line, os.fstat(fd).st_size)
        else:
            os.ftruncate(fd, 0)
            os.pwrite(fd, line, 0)
        yield
    finally:
        os.close(fd)  # releases the lock


def _live_holders(text: str) -> list[str]:
    """The lock file's "PID n (splatcli cmd)" lines whose process still runs."""
    out = []
    for line in text.splitlines():
        m = re.match(r"PID (\d+) \(", line)
        if m:
            try:
                os.kill(int(m.group(1)), 0)
            except ProcessLookupError:
                continue
            except OSError:  # alive, another user's
                pass
            out.append(line.strip())
    return out[-2:]


def holdout_split(names: list[str], test: list[str] | None = None) -> dict[str, list[str]]:
    """The one hold-out rule: the data's own `test` images when it names some, else every
    HOLDOUT_EVERY-th image by sorted name (index % 8 == 0, the 3DGS convention); a single
    image is trained on, never held out. Returns {"train": [...], "test": [...]}, sorted."""
    names = sorted(names)
    if test:
        held = set(test)
    else:
        held = set(names[::HOLDOUT_EVERY]) if len(names) > 1 else set()
    return {"train": [n for n in names if n not in held], "test": [n for n in names if n in held]}


def is_project(path: str | Path) -> bool:
    return (Path(path) / MANIFEST_NAME).is_file()
