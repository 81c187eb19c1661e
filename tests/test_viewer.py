"""`splatcli view` and `train --viewer`: what the server serves and refuses, the command's
life cycle, the live store, and a real browser's picture against `splatcli render`."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from splatcli.events import Progress, Snapshot
from splatcli.formats.ply import write_ply
from splatcli.model import load_model
from splatcli.viewer import LiveSink, SceneStore, ViewerServer, open_scene, server as server_mod
from support.browser import browser_problem, capture, open_page, psnr_u8, screenshot
from support.tiny_project import assert_user_error, make_tiny_project, run_cli, run_ok, snapshot, tiny_gaussians

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def proj(tmp_path_factory):
    """The tiny project at 6x its size (288x240 cameras, 300 Gaussians, SH degree 1), away
    from the origin: the cameras look elsewhere (a viewer that looks at the origin fails)."""
    return make_tiny_project(tmp_path_factory.mktemp("view") / "p", scale=6, center=(1.5, -0.5, 2.0))


@pytest.fixture
def served(proj):
    with ViewerServer(open_scene(proj.root), "127.0.0.1", 0) as s:
        yield s


def _get(url: str, headers: dict | None = None, method: str = "GET") -> tuple[int, bytes, dict]:
    req = urllib.request.Request(url, headers=headers or {}, method=method)
    try:
        with urllib.request.urlopen(req, timeout=10) as r:
            return r.status, r.read(), dict(r.headers)
    except urllib.error.HTTPError as e:
        return e.code, e.read(), dict(e.headers)


def _raw(port: int, data: bytes) -> bytes:
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        s.sendall(data)
        s.shutdown(socket.SHUT_WR)
        out = b""
        while chunk := s.recv(65536):
            out += chunk
        return out


def test_scene_facts_cameras_and_the_ply_is_the_exported_bytes(served, proj, tmp_path):
    code, body, hdr = _get(served.url + "api/scene")
    s = json.loads(body)
    assert code == 200 and hdr["Content-Type"] == "application/json"
    assert s["num_gaussians"] == 300 and s["sh_degree"] == 1 and s["version"] == 1
    assert len(s["cameras"]) == 10 and {c["split"] for c in s["cameras"]} == {"train", "test"}
    c = s["cameras"][0]
    assert (c["width"], c["height"]) == (288, 240) and len(c["K"]) == 9 and len(c["viewmat"]) == 16
    assert np.allclose(s["up"], [0, -1, 0], atol=0.05)  # the ring's cameras stand upright in -y
    code, ply, _ = _get(served.url + "api/scene.ply")
    write_ply(tmp_path / "e.ply", load_model(proj.root, torch.device("cpu")).gaussians)
    assert code == 200 and ply == (tmp_path / "e.ply").read_bytes() and s["ply_bytes"] == len(ply)
    code, pts, _ = _get(served.url + "api/points.bin")
    n = int.from_bytes(pts[:4], "little")
    assert n == 300 and len(pts) == 4 + 16 * n


def test_serves_only_its_files(served):
    page = _get(served.url)
    assert page[0] == 200 and b"importmap" in page[1]
    code, body, hdr = _get(served.url + "static/vendor/spark.module.min.js", {"Accept-Encoding": "gzip"})
    assert code == 200 and hdr.get("Content-Encoding") == "gzip" and body[:2] == b"\x1f\x8b"
    code, body, hdr = _get(served.url + "static/vendor/three.core.js")  # a client without gzip gets plain text
    assert code == 200 and "Content-Encoding" not in hdr and b"three" in body[:2000].lower()
    base = f"http://127.0.0.1:{served.port}"
    for path in ["/static/../server.py", "/static/%2e%2e/server.py", "/static/vendor/../../__init__.py",
                 "//etc/passwd", "/etc/passwd", "/static/", "/static/vendor/", "/api/", "/api/scene.ply/..",
                 "/static/index.html", "/favicon.ico", "/static/vendor/spark.module.min.js.gz"]:
        assert _get(base + path)[0] == 404, path
    raw = _raw(served.port, b"GET /../../../../etc/passwd HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n")
    assert raw.startswith(b"HTTP/1.0 404") and b"root:" not in raw


def test_refuses_other_methods_and_hosts(served):
    for method in ("POST", "PUT"):
        assert _get(served.url, method=method)[0] == 405, method
    assert _get(served.url, {"Host": "attacker.example:80"})[0] == 403  # DNS rebinding
    assert _get(served.url, {"Host": f"localhost:{served.port}"})[0] == 200


@pytest.mark.parametrize("junk", [b"GARBAGE\r\n\r\n", b"\x00\xff" * 500, b"GET " + b"a" * 70000 + b" HTTP/1.1\r\n\r\n",
                                  b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: x\r\n\r\n", b"", b"GET /"])
def test_malformed_requests_never_stop_the_server(served, junk):
    try:
        _raw(served.port, junk)
    except OSError:
        pass
    assert _get(served.url + "api/scene")[0] == 200


def test_a_failing_request_is_a_500_and_the_server_goes_on(served, monkeypatch):
    monkeypatch.setattr(SceneStore, "ply", lambda self: 1 / 0)
    assert _get(served.url + "api/scene.ply")[0] == 500
    assert _get(served.url + "api/scene")[0] == 200


def test_default_port_is_the_next_free_one(monkeypatch, proj):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        taken = s.getsockname()[1]
        s.listen()
        monkeypatch.setattr(server_mod, "DEFAULT_PORT", taken)
        with ViewerServer(SceneStore(source="x"), "127.0.0.1", None) as v:
            assert v.port > taken
        with pytest.raises(Exception, match=f"--port {taken}"):
            ViewerServer(SceneStore(source="x"), "127.0.0.1", taken)


def test_live_sink_publishes_at_most_every_period_and_passes_events_on():
    store = SceneStore(source="live")
    seen = []
    sink = LiveSink(store, seen.append, every_s=3600)
    store.asked = time.monotonic()  # a page is open
    g = tiny_gaussians(50)
    sink(Progress("train", 10, 100, {"loss": 0.5, "psnr": 20.1, "refined": {"x": 1}}))
    calls = []
    for step in (10, 11, 12):
        sink(Snapshot(step, lambda: calls.append(1) or g))
    assert store.version == 1 and len(calls) == 1  # the first snapshot only: copies cost training time
    s = store.state()
    assert s["live"] == {"step": 10, "loss": 0.5, "psnr": 20.1} and s["num_gaussians"] == 50
    assert [type(e).__name__ for e in seen] == ["Progress"]  # snapshots are the viewer's alone
    g.means += 1  # the store keeps its own copy
    assert not torch.equal(store._g.means, g.means)
    idle = SceneStore(source="idle")
    LiveSink(idle, None, every_s=0)(Snapshot(1, lambda: g))
    calls.clear()
    idle.asked = -float("inf")
    LiveSink(idle, None, every_s=0)(Snapshot(2, lambda: calls.append(1) or g))
    assert idle.version == 1 and not calls  # no page looking: no copy after the first


def _start_view(*args: str, env: dict | None = None) -> tuple[subprocess.Popen, dict]:
    p = subprocess.Popen([sys.executable, "-m", "splatcli", "view", *args, "--json"], cwd=REPO, text=True,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, env={**os.environ, **(env or {})},
                         start_new_session=True,
                         # Ctrl-C as at a terminal, even when the tests run as a shell's background job
                         # (which starts them with SIGINT ignored, and children inherit that)
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    line = p.stdout.readline()
    assert line, p.stderr.read()
    return p, json.loads(line)


def test_view_command_serves_until_ctrl_c_then_exits_0_leaving_nothing(proj):
    before = snapshot(proj.root)
    p, s = _start_view(str(proj.root), "--port", "0")
    try:
        assert s["url"].startswith("http://127.0.0.1:") and s["num_gaussians"] == 300 and s["cameras"] == 10
        assert _get(s["url"] + "api/scene")[0] == 200
    finally:
        p.send_signal(signal.SIGINT)
        time.sleep(0.05)
        p.send_signal(signal.SIGINT)  # impatient: again, while it closes
        _, err = p.communicate(timeout=20)
    assert p.returncode == 0, err
    assert "Traceback" not in err and "error" not in err
    assert snapshot(proj.root) == before


def test_view_of_a_file_and_a_warning_for_other_hosts(proj, tmp_path):
    write_ply(tmp_path / "s.ply", tiny_gaussians(40))
    p, s = _start_view(str(tmp_path / "s.ply"), "--port", "0", "--host", "0.0.0.0")
    try:
        st = json.loads(_get(f"http://127.0.0.1:{s['url'].rsplit(':', 1)[1]}api/scene")[1])
        assert st["num_gaussians"] == 40 and st["cameras"] == [] and "center" in st and st["radius"] > 0
        assert st["file_bytes"] == (tmp_path / "s.ply").stat().st_size
    finally:
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=20)
    assert p.returncode == 0 and "warning:" in err and "other machines" in err


def test_view_ctrl_c_as_soon_as_the_url_is_printed_exits_0(tmp_path):
    write_ply(tmp_path / "s.ply", tiny_gaussians(10))
    for _ in range(3):  # the window between printing the URL and waiting for Ctrl-C is small: knock thrice
        p, _ = _start_view(str(tmp_path / "s.ply"), "--port", "0")
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=20)
        assert p.returncode == 0, err


def test_view_bad_sources_are_one_line_errors(tmp_path):
    assert_user_error(run_cli("view", tmp_path / "nothing.ply"), "nothing.ply")
    (tmp_path / "junk.spz").write_bytes(b"junk")
    assert_user_error(run_cli("view", tmp_path / "junk.spz"), "junk.spz")
    assert_user_error(run_cli("view", tmp_path), str(tmp_path))


@pytest.mark.slow
def test_train_with_viewer(tmp_path):
    proj = make_tiny_project(tmp_path / "t", trained=False, photos=True)
    r = run_ok("train", proj.root, "--iterations", "30", "--eval-every", "15", "--viewer", "--viewer-port", "0")
    assert "live viewer at http://127.0.0.1:" in r.stderr


# a real browser: headless Chromium on SwiftShader (tests/support/browser.py), against `splatcli render`


@pytest.mark.skipif(browser_problem() is not None, reason=str(browser_problem()))
def test_browser_picture_matches_splatcli_render(proj, served, tmp_path):
    run_ok("render", proj.root, "--split", "test", "-o", tmp_path / "r")
    cams = [c for c in json.loads(_get(served.url + "api/scene")[1])["cameras"] if c["split"] == "test"]
    assert cams
    for c in cams:
        ref = cv2.imread(str(tmp_path / "r" / c["name"]))[..., ::-1]
        shot, st = screenshot(f"{served.url}?camera={c['name']}&hud=0", c["width"], c["height"])
        assert shot.shape == ref.shape
        assert shot.std() > 5  # not a blank canvas
        p = psnr_u8(shot, ref)
        # the bar: renderers sort and cut off differently, but a wrong frame,
        # wrong colours or a blank canvas fall far below 20 dB
        assert p >= 20.0, (c["name"], p)
        print(f"{c['name']}: {p:.2f} dB against splatcli render; first frame at {st['firstFrameMs']:.0f} ms")


@pytest.mark.skipif(browser_problem() is not None, reason=str(browser_problem()))
def test_browser_orbits_and_switches_to_points(proj, served):
    from selenium.webdriver.common.action_chains import ActionChains

    c = [c for c in json.loads(_get(served.url + "api/scene")[1])["cameras"]][3]
    with open_page(f"{served.url}?camera={c['name']}&hud=0", c["width"], c["height"]) as (d, _):
        time.sleep(1.0)
        before = capture(d, c["width"], c["height"])
        canvas = d.find_element("css selector", "canvas")
        ActionChains(d).move_to_element(canvas).click_and_hold().move_by_offset(60, 0).release().perform()
        time.sleep(1.5)
        after = capture(d, c["width"], c["height"])
        assert after.std() > 5 and psnr_u8(before, after) < 25  # the view moved, and still shows the scene
        d.execute_script("const m = document.getElementById('mode'); m.value = 'points';"
                         "m.dispatchEvent(new Event('change'));")
        time.sleep(1.5)
        pts = capture(d, c["width"], c["height"])
        assert psnr_u8(pts, after) < 25 and pts.std() > 2  # centres as points: another picture
