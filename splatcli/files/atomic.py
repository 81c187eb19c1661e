"""Atomic file writes (a temp file beside the target, fsync, rename) and bounded
reads of the small JSON files we and other tools write.

An interrupted or failed write never leaves a half-written file at the target,
and the previous version stays as it was. Write errors (disk full, permissions)
become a one-line `SplatError` naming the file.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from ..errors import SplatError

MAX_JSON_BYTES = 64 * 1024 * 1024  # a manifest is kilobytes; refuse absurd files before parsing


# mkstemp creates 0600 files; what we publish gets the mode any other tool's file
# would (0666 less the umask), so viewers and servers running as other users can
# read an export. Read once, at import, while nothing else runs: os.umask can only
# be read by setting it.
UMASK = os.umask(0o022)  # the process umask (read once): the mode published files and folders get
os.umask(UMASK)


def _publish_mode(target: Path) -> int:
    """The target's current mode if it exists (rewriting keeps it), else 0666 & ~umask."""
    try:
        return target.stat().st_mode & 0o7777
    except OSError:
        return 0o666 & ~UMASK


@contextlib.contextmanager
def atomic_path(target: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path in the target's folder; on success rename it over
    the target. The caller writes the whole file to the yielded path."""
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        os.chmod(tmp_path, _publish_mode(target))
        yield tmp_path
        with open(tmp_path, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp_path, target)
        _fsync_dir(target.parent)
    except OSError as exc:
        _unlink_quiet(tmp_path)
        raise SplatError(f"cannot write {target}: {exc.strerror or exc}") from exc
    except BaseException:
        _unlink_quiet(tmp_path)
        raise


def atomic_write_bytes(target: str | os.PathLike, data: bytes) -> None:
    with atomic_path(target) as tmp:
        tmp.write_bytes(data)


def atomic_write_text(target: str | os.PathLike, text: str) -> None:
    atomic_write_bytes(target, text.encode("utf-8"))


def atomic_write_json(target: str | os.PathLike, obj: Any) -> None:
    atomic_write_text(target, json.dumps(obj, indent=2, sort_keys=False, default=json_default) + "\n")


def append_line(target: str | os.PathLike, line: str) -> None:
    """Append one line to a log (JSONL). A line is a single small write followed by
    fsync; a crash can at worst lose the last line, which readers skip if partial."""
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    try:
        with open(target, "a", encoding="utf-8") as f:
            f.write(line.rstrip("\n") + "\n")
            f.flush()
            os.fsync(f.fileno())
    except OSError as exc:
        raise SplatError(f"cannot write {target}: {exc.strerror or exc}") from exc


def json_default(o: Any) -> Any:
    import numpy as np

    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _unlink_quiet(path: Path) -> None:
    try:
        path.unlink()
    except OSError:
        pass


def read_json_file(path: Path, what: str = "JSON file", max_bytes: int = MAX_JSON_BYTES) -> Any:
    """Read JSON with a size bound, turning every failure into one-line SplatError."""
    path = Path(path)
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise SplatError(f"{path}: {what} not found") from None
    except OSError as exc:
        raise SplatError(f"{path}: cannot read {what}: {exc.strerror or exc}") from None
    if size > max_bytes:
        raise SplatError(f"{path}: {what} is {size} bytes, more than the {max_bytes} allowed")
    try:
        text = path.read_text(encoding="utf-8")
        return json.loads(text)
    except UnicodeDecodeError:
        raise SplatError(f"{path}: {what} is not UTF-8 text") from None
    except json.JSONDecodeError as exc:
        raise SplatError(f"{path}: {what} is not valid JSON ({exc.msg} at line {exc.lineno})") from None
    except OSError as exc:
        raise SplatError(f"{path}: cannot read {what}: {exc.strerror or exc}") from None
