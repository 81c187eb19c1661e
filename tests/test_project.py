"""Project layout, manifest and atomic writes."""

from __future__ import annotations

import json
import os

import pytest

from splatcli.errors import NotReadyError, SplatError
from splatcli.files import atomic
from splatcli.files.atomic import atomic_path, atomic_write_json, atomic_write_text, read_json_file
from splatcli.project import SCHEMA_VERSION, Project


def test_create_and_open(tmp_path):
    p = Project.create(tmp_path / "proj", source={"kind": "images", "path": "x"})
    m = Project.open(p.root).manifest()
    assert m["schema_version"] == SCHEMA_VERSION
    assert m["frame"] == "opencv"
    assert p.checkpoint_path(7000).name == "step-000007000.pt"
    assert p.export_path().name == "scene.ply"


def test_refuses_to_clobber_unrelated_folder(tmp_path):
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "precious.txt").write_text("keep")
    with pytest.raises(SplatError, match="not a splatcli project"):
        Project.create(tmp_path / "d", source={})
    assert (tmp_path / "d" / "precious.txt").read_text() == "keep"


def test_newer_schema_is_refused(tmp_path):
    p = Project.create(tmp_path / "p", source={})
    m = p.manifest()
    m["schema_version"] = SCHEMA_VERSION + 1
    p.manifest_path.write_text(json.dumps(m))
    with pytest.raises(SplatError, match="newer"):
        Project.open(p.root)


def test_readiness_names_the_command_to_run(tmp_path):
    p = Project.create(tmp_path / "p", source={})
    with pytest.raises(NotReadyError, match="splatcli process"):
        p.require_processed()
    p.record_step("process", config={}, summary={})
    p.images_dir.mkdir()
    p.sparse_dir.mkdir(parents=True)
    with pytest.raises(NotReadyError, match="splatcli train"):
        p.require_trained()
    p.checkpoints_dir.mkdir()
    p.checkpoint_path(5).write_bytes(b"x")
    p.checkpoint_path(10).write_bytes(b"x")
    assert p.require_trained() == p.checkpoint_path(10)


def test_atomic_write_leaves_old_file_on_failure(tmp_path):
    target = tmp_path / "f.json"
    atomic_write_json(target, {"v": 1})
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("interrupted mid-write")
    assert json.loads(target.read_text()) == {"v": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["f.json"]  # no temp debris


def test_write_error_is_one_line_and_keeps_old(tmp_path, monkeypatch):
    target = tmp_path / "f.txt"
    atomic_write_text(target, "old")

    def full(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", full)
    with pytest.raises(SplatError, match="No space left on device"):
        atomic_write_text(target, "new")
    assert target.read_text() == "old"


def test_json_reader_bounds_and_errors(tmp_path):
    f = tmp_path / "a.json"
    f.write_text("{not json")
    with pytest.raises(SplatError, match="not valid JSON"):
        read_json_file(f)
    f.write_text("[" + "1," * 100 + "1]")
    with pytest.raises(SplatError, match="more than"):
        read_json_file(f, max_bytes=50)


def test_atomic_files_get_the_usual_mode_not_mkstemps_0600(tmp_path):
    new = tmp_path / "new.json"
    atomic_write_text(new, "{}")
    assert new.stat().st_mode & 0o777 == 0o666 & ~atomic.UMASK  # e.g. 0644 under umask 022
    kept = tmp_path / "kept.json"
    kept.write_text("old")
    os.chmod(kept, 0o640)
    atomic_write_text(kept, "new")  # rewriting keeps the file's own mode
    assert kept.stat().st_mode & 0o777 == 0o640 and kept.read_text() == "new"
