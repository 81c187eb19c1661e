"""The check of every model `process` writes (sfm/check.py), and what follows a model that fails it:
the global mapper, else the largest consistent part kept and the rest named.

A broken model is made the way a walk-around capture breaks the incremental mapper: an arc of
cameras placed apart from the rest (here: moved by half the scene's extent, their rotations kept),
so the strong pairs at the arc's two ends disagree with the poses while every other pair agrees.
The sample scene's views orbit it in name order, so views 004-008 are one arc.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from splatcli.camera import scene_extent
from splatcli.events import Note
from splatcli.process.run import ProcessConfig, process
from splatcli.project import Project
from splatcli.sfm import colmap, reconstruct
from splatcli.sfm.check import check_model
from splatcli.sfm.colmap import Model, read_model, read_scene
from splatcli.train.loop import pose_warning
from support.align import compare_poses
from support.tiny_project import run_ok
from test_process import N_VIEWS, H, W, ground_truth, render

ARC = [f"{i:03d}.jpg" for i in range(4, 9)]


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    return render(tmp_path_factory.mktemp("scene") / "scene", num_views=N_VIEWS, width=W, height=H)


@pytest.fixture(scope="module")
def processed(scene, tmp_path_factory) -> Project:
    out = tmp_path_factory.mktemp("proj") / "p"
    process(scene, out, ProcessConfig(num_threads=1))
    return Project(out)


def moved(model: Model, names: list[str], offset: np.ndarray) -> Model:
    """`model` with the cameras of `names` moved by `offset` (world units), their rotations kept."""
    import pycolmap

    rec = model._rec
    for im in rec.images.values():
        if im.name in names and im.has_pose:
            frame = rec.frames[im.frame_id]
            m = frame.rig_from_world.matrix()
            frame.rig_from_world = pycolmap.Rigid3d(np.c_[m[:, :3], m[:, 3] - m[:, :3] @ offset])
    return model


def arc_offset(model: Model) -> np.ndarray:
    """Half the model's extent, across the orbit's plane."""
    centre, extent = scene_extent(model.cameras())
    return np.array([0.0, 0.0, 0.5 * extent])


def test_a_mapped_model_agrees_with_its_pairs_and_the_manifest_says_so(processed):
    summary = processed.step("process")["summary"]
    check = summary["consistency"]
    assert check["consistent"] and check["parts"] == [N_VIEWS] and check["placed_apart"] == []
    assert check["strong_pairs"] >= N_VIEWS and check["share"] >= 0.99, check
    assert check["median_error_px"] < 1.0
    assert any(t["attempt"] == "the consistency check" and t["kept"] for t in summary["sfm_tried"])
    assert pose_warning(processed) is None


def test_an_arc_placed_apart_is_found_and_its_cameras_named(processed):
    """The check on the raw model with views 004-008 moved: the pairs joining the arc to the rest
    disagree (many pixels of epipolar error), and the arc is the group placed apart; the same model
    unmoved passes."""
    db, raw = processed.database_path, processed.sfm_dir / "distorted"
    model_dir = raw if raw.is_dir() else processed.sparse_dir
    assert check_model(db, read_model(model_dir)).consistent
    model = read_model(model_dir)
    c = check_model(db, moved(model, ARC, arc_offset(model)))
    assert not c.consistent
    assert c.named() == ARC and [len(p) for p in c.parts] == [N_VIEWS - len(ARC), len(ARC)]
    assert c.breaks and all(not p.agrees and p.error_px > 4 for p in c.breaks)
    assert all({p.a, p.b} & set(ARC) and {p.a, p.b} - set(ARC) for p in c.breaks)  # each joins the arc to the rest
    s = c.summary()
    assert s["placed_apart"] == ARC and not s["consistent"] and s["share"] < 1.0
    assert "004.jpg" in c.line() and "placed apart" in c.line()


def _broken_first_mapping(monkeypatch) -> None:
    """The incremental mapper's models, with views 004-008 placed apart."""
    real = colmap.incremental_mapping

    def broken(*a, **k):
        models = real(*a, **k)
        if models and set(ARC) <= set(models[0].registered_names()):
            moved(models[0], ARC, arc_offset(models[0]))
        return models

    monkeypatch.setattr(colmap, "incremental_mapping", broken)


def test_a_model_that_fails_the_check_is_mapped_again_with_the_global_mapper(scene, tmp_path, monkeypatch):
    """The check fails, the global mapper places every camera at once, its model passes and is kept:
    every view where the ground truth has it, and the manifest says which model it was."""
    _broken_first_mapping(monkeypatch)
    notes = []
    r = process(scene, tmp_path / "p", ProcessConfig(num_threads=1), on_event=notes.append)
    assert r.registered == N_VIEWS and r.placed_apart == []
    assert r.consistency["consistent"]
    said = [n.message for n in notes if isinstance(n, Note)]
    assert any(n.level == "warning" and "fails the consistency check" in n.message and "004.jpg" in n.message
               for n in notes if isinstance(n, Note)), said
    glob = [t for t in r.sfm_tried if t["attempt"] == reconstruct.GLOBAL_MAPPER]
    assert len(glob) == 1 and glob[0]["kept"] and glob[0]["registered"] == N_VIEWS
    e = compare_poses(read_scene(Project(tmp_path / "p").sparse_dir).cameras, ground_truth(scene))
    assert e.max_rotation_deg < 1.0 and e.max_center_error_rel < 0.01


def test_where_no_model_passes_the_largest_consistent_part_is_kept_and_training_is_warned(scene, tmp_path,
                                                                                          monkeypatch):
    """The global mapper stopped at its cap: the model is split at its broken joins, the 11 views that
    agree are the dataset, the 5 placed apart are named (warning, manifest), and `train` says so
    before its first step."""
    _broken_first_mapping(monkeypatch)

    def over_time(*a, **k):
        raise colmap.OverTime

    monkeypatch.setattr(colmap, "global_mapping", over_time)
    notes = []
    r = process(scene, tmp_path / "p", ProcessConfig(num_threads=1), on_event=notes.append)
    assert r.registered == N_VIEWS - len(ARC) and r.placed_apart == ARC
    assert set(ARC) <= set(r.unregistered)
    warned = [n.message for n in notes if isinstance(n, Note) and n.level == "warning"]
    assert any("leaving out 5 placed apart" in m and "004.jpg" in m for m in warned), warned
    assert any(t["attempt"] == reconstruct.GLOBAL_MAPPER and "cap" in t["result"] for t in r.sfm_tried)
    proj = Project(tmp_path / "p")
    names = [c.name for c in read_scene(proj.sparse_dir).cameras]
    assert not set(names) & set(ARC) and len(names) == N_VIEWS - len(ARC)
    e = compare_poses(read_scene(proj.sparse_dir).cameras, ground_truth(scene))
    assert e.max_rotation_deg < 1.0 and e.max_center_error_rel < 0.01  # the part kept is right
    warning = pose_warning(proj)
    assert warning and "left out 5 image(s)" in warning and "004.jpg" in warning and "training on the 11" in warning
    r = run_ok("train", proj.root, "--iterations", "2", "--eval-every", "0", "--max-size", "64")
    err = r.stderr.splitlines()
    said = next(i for i, line in enumerate(err) if "process left out 5 image(s)" in line)
    assert err[said].startswith("warning: ") and any(line.strip().startswith("train ") for line in err[said + 1 :])
