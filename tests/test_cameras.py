"""Cameras grouped as the photos were taken (issue 38): the EXIF reader and the
grouping rule of process/cameras.py. Fast: no structure from motion here (see
test_process.py for photos of two cameras through SfM)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from splatcli.errors import SplatError
from splatcli.inputs.exif import read_exif_camera
from splatcli.inputs.images import StagedImage
from splatcli.process.cameras import group_cameras

_MAKE, _MODEL, _EXIF_IFD, _FOCAL, _FOCAL_35 = 0x010F, 0x0110, 0x8769, 0x920A, 0xA405


def photo(path: Path, size: tuple[int, int] = (64, 48), *, make: str | None = None, model: str | None = None,
          focal: float | None = None, focal_35: int | None = None, seed: int = 0) -> Path:
    """A JPEG (or PNG, by suffix) of random texture with the EXIF camera tags given (Pillow writes them)."""
    rgb = np.random.default_rng(seed).integers(0, 256, (size[1], size[0], 3), dtype=np.uint8)
    ex = Image.Exif()
    if make is not None:
        ex[_MAKE] = make
    if model is not None:
        ex[_MODEL] = model
    if focal is not None or focal_35 is not None:
        sub = ex.get_ifd(_EXIF_IFD)
        if focal is not None:
            sub[_FOCAL] = focal
        if focal_35 is not None:
            sub[_FOCAL_35] = focal_35
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(rgb).save(path, exif=ex) if len(ex) else Image.fromarray(rgb).save(path)
    return path


def staged(path: Path, size: tuple[int, int] = (64, 48)) -> StagedImage:
    return StagedImage(path.name, size[0], size[1], False)


def test_exif_camera_facts_are_read(tmp_path):
    e = read_exif_camera(photo(tmp_path / "a.jpg", make="Canon", model="Canon EOS 60D", focal=50.0, focal_35=80))
    assert (e.make, e.model, e.focal_mm, e.focal_35mm, e.problems) == ("Canon", "Canon EOS 60D", 50.0, 80.0, ())
    assert e.describe() == "Canon Canon EOS 60D at 50 mm"
    assert read_exif_camera(photo(tmp_path / "b.jpg")).empty
    assert read_exif_camera(photo(tmp_path / "c.png")).empty


@pytest.mark.parametrize("focal, why", [(0.0, "focal length 0 mm"), (-35.0, "focal length -35 mm"),
                                        (1e7, "focal length 1e+07 mm")])
def test_exif_that_lies_about_the_focal_length_is_dropped_and_said(tmp_path, focal, why):
    e = read_exif_camera(photo(tmp_path / "a.jpg", make="FUJIFILM", model="FinePix S4500", focal=focal))
    assert e.focal_mm is None and e.make == "FUJIFILM" and len(e.problems) == 1 and why in e.problems[0]


def test_exif_names_with_control_characters_are_cleaned(tmp_path):
    e = read_exif_camera(photo(tmp_path / "a.jpg", make="\x00\x01Pana\x07sonic  ", model="x" * 500))
    assert e.make == "Pana sonic" and e.model == "x" * 64


def test_damaged_or_absent_files_have_no_exif(tmp_path):
    p = photo(tmp_path / "a.jpg", make="Canon", model="EOS", focal=50.0)
    data = p.read_bytes()
    (tmp_path / "cut.jpg").write_bytes(data[:40])
    assert read_exif_camera(tmp_path / "cut.jpg").empty
    (tmp_path / "junk.jpg").write_bytes(b"\xff\xd8\xff\xe1\xff\xffExif\x00\x00" + b"\xff" * 64)
    assert read_exif_camera(tmp_path / "junk.jpg").empty
    assert read_exif_camera(tmp_path / "missing.jpg").empty


def test_photos_group_by_make_model_focal_length_and_size(tmp_path):
    files = [photo(tmp_path / "a1.jpg", make="Canon", model="EOS 60D", focal=50.0),
             photo(tmp_path / "a2.jpg", make="Canon", model="EOS 60D", focal=50.0),
             photo(tmp_path / "b1.jpg", make="Canon", model="EOS 60D", focal=24.0),  # zoomed out
             photo(tmp_path / "c1.jpg", make="Panasonic", model="DMC-FZ150", focal=108.0),
             photo(tmp_path / "c2.jpg", make="Panasonic", model="DMC-FZ150", focal=108.0, size=(48, 64)),  # portrait
             photo(tmp_path / "n1.jpg"), photo(tmp_path / "n2.jpg")]
    imgs = [staged(f, (48, 64) if f.name == "c2.jpg" else (64, 48)) for f in files]
    g = group_cameras(imgs, {f.name: f for f in files}, "auto", video=False)
    assert sorted(sorted(x.names) for x in g.groups) == [["a1.jpg", "a2.jpg"], ["b1.jpg"], ["c1.jpg"], ["c2.jpg"],
                                                         ["n1.jpg", "n2.jpg"]]
    assert g.rule == "exif" and "5 camera(s)" in g.reason and "4 by their EXIF" in g.reason
    canon = next(x for x in g.groups if x.names == ["a1.jpg", "a2.jpg"]).summary()
    assert canon["make"] == "Canon" and canon["focal_mm"] == 50.0 and canon["source"] == "exif"
    assert next(x for x in g.groups if x.names == ["n1.jpg", "n2.jpg"]).source == "size"


def test_photos_without_exif_share_a_camera_only_when_they_share_a_size(tmp_path):
    files = [photo(tmp_path / f"{i}.png", seed=i) for i in range(3)]
    same = [staged(f) for f in files]
    g = group_cameras(same, {f.name: f for f in files}, "auto", video=False)
    assert [x.names for x in g.groups] == [["0.png", "1.png", "2.png"]]
    mixed = same[:2] + [staged(files[2], (48, 64))]
    g = group_cameras(mixed, {f.name: f for f in files}, "auto", video=False)
    assert len(g.groups) == 3 and "in 2 sizes; using one camera per image" in g.reason


def test_the_user_overrides_and_video(tmp_path):
    files = [photo(tmp_path / "a.jpg", make="Canon", model="A", focal=50.0),
             photo(tmp_path / "b.jpg", make="Nikon", model="B", focal=35.0)]
    imgs = [staged(f) for f in files]
    src = {f.name: f for f in files}
    assert [x.names for x in group_cameras(imgs, src, "single", video=False).groups] == [["a.jpg", "b.jpg"]]
    assert len(group_cameras(imgs, src, "per-image", video=False).groups) == 2
    assert group_cameras(imgs, None, "auto", video=True).rule == "video"
    imgs[1] = staged(files[1], (48, 64))
    with pytest.raises(SplatError, match="--single-camera: the images come in 2 sizes"):
        group_cameras(imgs, src, "single", video=False)
