"""`splatcli export --format web`: the folder, its size, its one-line errors, and the page it
holds served by a plain static file server in a real browser, against `splatcli render` and `view`."""

from __future__ import annotations

import contextlib
import functools
import gzip
import json
import threading
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path

import cv2
import pytest

from splatcli.errors import SplatError
from splatcli.formats.export import ExportConfig
from splatcli.formats.sog import read_sog
from splatcli.model import export_project
from splatcli.viewer import ViewerServer, open_scene, site
from support.browser import browser_problem, open_page, psnr_u8, screenshot
from support.tiny_project import assert_user_error, make_tiny_project, run_cli, run_ok, snapshot

VENDOR = resources.files("splatcli.viewer") / "static" / "vendor"
RENDERER = ["spark.module.min.js", "three.module.js", "three.core.js", "addons/controls/OrbitControls.js",
            "addons/postprocessing/Pass.js"]


@pytest.fixture(scope="module")
def proj(tmp_path_factory):
    """As test_viewer's: the tiny project at 6x (288x240 cameras, 300 Gaussians, SH degree 1), off the origin."""
    return make_tiny_project(tmp_path_factory.mktemp("web") / "p", scale=6, center=(1.5, -0.5, 2.0))


@pytest.fixture(scope="module")
def site_dir(proj):
    r = run_ok("export", proj.root, "--format", "web", "--json")
    out = proj.export_path("web")
    assert json.loads(r.stdout)["path"] == str(out) == str(proj.root / "exports" / "web")
    return out


def _files(folder: Path) -> dict[str, int]:
    return {p.relative_to(folder).as_posix(): p.stat().st_size for p in folder.rglob("*") if p.is_file()}


def test_folder_holds_the_page_the_plain_renderer_and_the_scene_within_the_size_bound(proj, site_dir):
    files = _files(site_dir)
    assert set(files) == {"index.html", "api/scene", "api/scene.sog", "static/viewer.js", "static/vendor/LICENSES",
                          "static/vendor/VERSIONS", *(f"static/vendor/{n}" for n in RENDERER)}
    static = resources.files("splatcli.viewer") / "static"
    assert (site_dir / "index.html").read_bytes() == (static / "index.html").read_bytes()  # the same page as view's
    assert (site_dir / "static/viewer.js").read_bytes() == (static / "viewer.js").read_bytes()
    for n in RENDERER:  # plain JavaScript: a static server sends no Content-Encoding
        assert (site_dir / "static/vendor" / n).read_bytes() == gzip.decompress((VENDOR / (n + ".gz")).read_bytes())
    s = json.loads((site_dir / "api/scene").read_text())
    assert s["static"] is True and s["splats"] == "api/scene.sog" and s["file_bytes"] == files["api/scene.sog"]
    assert s["num_gaussians"] == 300 and s["sh_degree"] == 1 and s["source"] == "p"  # no path of this machine
    assert len(s["cameras"]) == 10 and {c["split"] for c in s["cameras"]} == {"train", "test"}
    assert s["background"] == [0.0, 0.0, 0.0] and s["radius"] > 0 and len(s["center"]) == 3
    g = read_sog(site_dir / "api/scene.sog")
    assert len(g) == 300 and g.sh_degree == 1
    renderer = sum(files[f"static/vendor/{n}"] for n in RENDERER)
    assert sum(files.values()) <= 1.2 * (files["api/scene.sog"] + renderer)
    assert [p.name for p in site_dir.parent.iterdir()] == ["web"]  # no temporary folder left beside it


def test_a_second_export_replaces_the_folder_and_an_interrupted_one_leaves_the_old(proj, site_dir, monkeypatch):
    before = _files(site_dir)
    (site_dir / "api/scene").write_text("{}")  # a stale file: replaced
    export_project(proj.root, ExportConfig(format="web"), write=site.export_site)
    assert _files(site_dir) == before and json.loads((site_dir / "api/scene").read_text())["static"]
    calls, write = [], site.atomic_write_bytes

    def full(path, data):  # the disk fills after a few files
        calls.append(path)
        if len(calls) > 3:
            raise OSError(28, "No space left on device")
        return write(path, data)

    monkeypatch.setattr(site, "atomic_write_bytes", full)
    with pytest.raises(SplatError, match="cannot write .*web: No space left"):
        export_project(proj.root, ExportConfig(format="web"), write=site.export_site)
    assert _files(site_dir) == before and [p.name for p in site_dir.parent.iterdir()] == ["web"]
    new = proj.root.parent / "new-site"
    monkeypatch.setattr(site, "atomic_write_bytes", lambda path, data: (_ for _ in ()).throw(KeyboardInterrupt))
    with pytest.raises(KeyboardInterrupt):
        export_project(proj.root, ExportConfig(format="web", out=new), write=site.export_site)
    assert not new.exists() and not list(proj.root.parent.glob(".new-site*"))


def test_web_errors_are_one_line(proj, tmp_path):
    before = snapshot(proj.root)
    (tmp_path / "file").write_text("x")
    assert_user_error(run_cli("export", proj.root, "--format", "web", "-o", tmp_path / "file"), "is a file", "folder")
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep me")
    assert_user_error(run_cli("export", proj.root, "-f", "web", "-o", tmp_path / "mine"), "other files in it")
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep me"
    assert_user_error(run_cli("export", proj.root, "--format", "html"), "'html'", "sog, splat, web")
    assert snapshot(proj.root) == before
    untrained = make_tiny_project(tmp_path / "u", trained=False, photos=False)
    assert_user_error(run_cli("export", untrained.root, "--format", "web"), "no trained model", "splatcli train")
    assert not (untrained.root / "exports" / "web").exists()
    (tmp_path / "empty").mkdir()  # an empty folder is fine
    r = run_cli("export", proj.root, "--format", "web", "-o", tmp_path / "empty", "-q")
    assert r.exit_code == 0 and (tmp_path / "empty" / "index.html").is_file(), r.output


@contextlib.contextmanager
def static_server(folder: Path):
    """Python's plain file server on `folder`: no API, no gzip, what any static host does."""
    handler = functools.partial(type("Quiet", (SimpleHTTPRequestHandler,), {"log_message": lambda *a: None}),
                                directory=str(folder))
    httpd = ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}/"
    finally:
        httpd.shutdown()
        httpd.server_close()


@pytest.mark.slow
@pytest.mark.skipif(browser_problem() is not None, reason=str(browser_problem()))
def test_static_page_draws_the_test_cameras_as_view_does(proj, site_dir, tmp_path):
    run_ok("render", proj.root, "--split", "test", "-o", tmp_path / "r")
    cams = [c for c in json.loads((site_dir / "api/scene").read_text())["cameras"] if c["split"] == "test"]
    assert cams
    with static_server(site_dir) as url, ViewerServer(open_scene(proj.root), "127.0.0.1", 0) as served:
        for c in cams:
            ref = cv2.imread(str(tmp_path / "r" / c["name"]))[..., ::-1]
            shot, _ = screenshot(f"{url}?camera={c['name']}&hud=0", c["width"], c["height"])
            view, _ = screenshot(f"{served.url}?camera={c['name']}&hud=0", c["width"], c["height"])
            p, pv = psnr_u8(shot, ref), psnr_u8(view, ref)
            print(f"{c['name']}: static {p:.2f} dB, view {pv:.2f} dB against splatcli render")
            assert shot.shape == ref.shape and shot.std() > 5
            assert p >= 20.0 and p >= pv - 2.0, (c["name"], p, pv)
        with open_page(f"{url}?hud=0", 288, 240) as (d, st):  # the free view; everything from the folder
            names = d.execute_script("return performance.getEntriesByType('resource').map((e) => e.name)")
            shown = d.execute_script("return [document.getElementById('show').hidden, document.getElementById('facts').textContent]")
    assert st["version"] == 1 and names and all(n.startswith(url) for n in names), names
    assert not any("points" in n or "scene.ply" in n for n in names)  # (Spark fetches the .sog in a worker)
    assert shown[0] is True and "300 Gaussians" in shown[1]
