"""Features and matches kept for the next `process` of the same photos.

SIFT and matching are most of what structure from motion costs on a few hundred photos, and
they depend only on the photos and the feature options. So the database that holds them is
kept: in the project (`sfm/database.db`, with `sfm/features.key`) when `process` succeeds, and
in `PROJ/.sfm-cache/` when it is interrupted. The next `process` of the same photos with the
same feature options (also `--overwrite` with other mapping options) starts from it: COLMAP
skips the pairs a database has matched already, so only new pairs are matched.

The key is a hash of the staged photos' bytes (and their masks'), their names, and what the
features depend on (SIFT's options, the octave, the camera model and grouping).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

CACHE_DIR = ".sfm-cache"  # in the output folder, after an interrupted run
KEY_FILE = "features.key"  # beside a database.db


def features_key(image_dir: Path, names: list[str], mask_dir: Path | None, options: dict) -> str:
    """The hash a reusable database must carry (module docstring)."""
    h = hashlib.sha256(json.dumps({"names": names, "options": options}, sort_keys=True).encode())
    for n in names:
        h.update(hashlib.sha256((image_dir / n).read_bytes()).digest())
        if mask_dir is not None:
            m = mask_dir / f"{n}.png"
            h.update(hashlib.sha256(m.read_bytes()).digest() if m.is_file() else b"-")
    return h.hexdigest()


def _matches(folder: Path, key: str) -> bool:
    k = folder / KEY_FILE
    return (folder / "database.db").is_file() and k.is_file() and k.read_text(encoding="utf-8").strip() == key


def reuse(root: Path, work: Path, key: str) -> str | None:
    """Put a database with `key` at work/database.db (from an interrupted run's cache, or a copy of
    the project's own), with its key; where it came from, or None (then `mark` follows extraction)."""
    cache, published = root / CACHE_DIR, root / "sfm"
    work.mkdir(parents=True, exist_ok=True)
    found = None
    if _matches(cache, key):
        os.replace(cache / "database.db", work / "database.db")
        found = "an interrupted run"
    elif _matches(published, key):
        shutil.copyfile(published / "database.db", work / "database.db")  # the project stays whole if this run fails
        found = "the project's last run"
    shutil.rmtree(cache, ignore_errors=True)
    if found:
        mark(work, key)
    return found


def mark(work: Path, key: str) -> None:
    """work/database.db holds every photo's features: from now on it may be kept."""
    (work / KEY_FILE).write_text(key + "\n", encoding="utf-8")


def keep(root: Path, work: Path) -> bool:
    """After an interruption: move work's database and key to the output folder's cache, unless the
    project holds the same; whether it did."""
    if not ((work / "database.db").is_file() and (work / KEY_FILE).is_file()):
        return False
    if _matches(root / "sfm", (work / KEY_FILE).read_text(encoding="utf-8").strip()):
        return False  # the project holds the same already
    cache = root / CACHE_DIR
    shutil.rmtree(cache, ignore_errors=True)
    cache.mkdir(parents=True)
    os.replace(work / "database.db", cache / "database.db")
    os.replace(work / KEY_FILE, cache / KEY_FILE)
    return True
