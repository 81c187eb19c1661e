"""The web viewer's server: a page, the vendored renderer, and the current scene.

The browser side is Spark (a three.js Gaussian-splat renderer, vendored under
static/vendor by tools/vendor_viewer.sh); this side only serves bytes:

    /                    the page (static/index.html)
    /static/NAME         a file of a fixed list, read once from the package
    /api/scene           JSON: the scene's facts, background, cameras and version
    /api/scene.ply       the current Gaussians as a 3DGS .ply (the same bytes `export` writes)
    /api/points.bin      the Gaussians' centres and base colours, for the points display

No URL reaches the file system: the static files are a dictionary built at start-up.
A request for anything else is a 404, a method other than GET or HEAD a 405, and a
Host header that names another site a 403 (a web page cannot reach this server
through DNS rebinding). Every request is handled on its own thread; an exception in
one is answered with a 500 and never stops the server.
"""

from __future__ import annotations

import gzip
import ipaddress
import json
import socket
import threading
import time
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import PurePosixPath
from typing import Any, ClassVar

import numpy as np
import torch

from ..errors import SplatError
from ..formats.ply import gaussians_to_rows, ply_bytes, ply_header
from ..gaussians import SH_C0, Gaussians
from ..render.projection import NEAR

DEFAULT_PORT = 7007  # nerfstudio's viewer port: what users of the field try first
PORT_TRIES = 50

_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8", ".css": "text/css",
          ".txt": "text/plain; charset=utf-8", "": "text/plain; charset=utf-8"}


@dataclass(frozen=True)
class Asset:
    body: bytes
    content_type: str
    gzipped: bool = False


def assets() -> dict[str, Asset]:
    """Every file the page may load, by URL path: the list is fixed here."""
    root = resources.files("splatcli.viewer") / "static"
    names = ["index.html", "viewer.js", "vendor/LICENSES", "vendor/VERSIONS",
             "vendor/spark.module.min.js", "vendor/three.module.js", "vendor/three.core.js",
             "vendor/addons/controls/OrbitControls.js", "vendor/addons/postprocessing/Pass.js"]
    out = {}
    for name in names:
        ext = PurePosixPath(name).suffix  # "" for LICENSES, VERSIONS
        gz = name.endswith(".js") and name.startswith("vendor/")
        body = (root / (name + ".gz" if gz else name)).read_bytes()
        out["/" if name == "index.html" else f"/static/{name}"] = Asset(body, _TYPES.get(ext, _TYPES[""]), gz)
    return out


@dataclass
class CameraInfo:
    name: str
    split: str  # "train" | "test" | ""
    width: int
    height: int
    K: list[float]  # [9] row-major intrinsics, pixels
    viewmat: list[float]  # [16] row-major world-to-camera (OpenCV: x right, y down, z forward)


@dataclass
class SceneStore:
    """The scene the viewer shows, replaced while training runs (`publish`), read by
    the server's threads. The .ply bytes are built on the first request for a version."""

    source: str
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    cameras: list[CameraInfo] = field(default_factory=list)
    up: list[float] = field(default_factory=lambda: [0.0, -1.0, 0.0])  # OpenCV scenes: y points down
    file_bytes: int | None = None  # the size of the file shown, when the source is a file
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    _g: Gaussians | None = None
    _info: dict[str, Any] = field(default_factory=dict)
    _ply: bytes | None = None
    _points: bytes | None = None
    _bounds: dict[str, Any] = field(default_factory=dict)
    version: int = 0
    asked: float = -float("inf")  # time.monotonic() of the page's last /api/scene request

    def wanted(self, within_s: float = 10.0) -> bool:
        """Whether a page has asked for the scene lately: live updates cost nothing without one."""
        return time.monotonic() - self.asked < within_s

    def publish(self, g: Gaussians, info: dict[str, Any] | None = None) -> None:
        """Show `g` from now on (a copy on the CPU is kept; the caller may go on editing
        its tensors). `info`: live figures such as step, loss and held-out PSNR."""
        g = Gaussians(**{k: v.detach().to("cpu", torch.float32, copy=True) for k, v in g.as_dict().items()})
        bounds = {}
        if len(g):  # where to look from when no camera is given: the bulk of the centres
            centre = g.means.median(0).values
            radius = float(torch.quantile((g.means[:100_000] - centre).norm(dim=1), 0.9))
            bounds = {"center": centre.tolist(), "radius": max(radius, 1e-3)}
        with self._lock:
            self._g, self._info, self._ply, self._points, self._bounds = g, dict(info or {}), None, None, bounds
            self.version += 1

    def ply(self) -> bytes:
        with self._lock:
            g = self._g
            if self._ply is None and g is not None:
                self._ply = ply_header(len(g), g.sh_degree) + np.ascontiguousarray(gaussians_to_rows(g)).tobytes()
            return self._ply or b""

    def points(self, limit: int = 1_000_000) -> bytes:
        """[n] float32 x, y, z then [n] uint8 r, g, b, a (a = opacity), for at most `limit` centres."""
        with self._lock:
            g = self._g
            if self._points is None and g is not None:
                idx = torch.arange(len(g)) if len(g) <= limit else torch.randperm(
                    len(g), generator=torch.Generator().manual_seed(0))[:limit]
                xyz = g.means[idx].numpy().astype("<f4")
                rgb = (g.sh[idx, 0] * SH_C0 + 0.5).clamp(0, 1)
                a = torch.sigmoid(g.opacity_logits[idx])[:, None]
                rgba = (torch.cat([rgb, a], 1) * 255).round().to(torch.uint8).numpy()
                self._points = len(idx).to_bytes(4, "little") + xyz.tobytes() + rgba.tobytes()
            return self._points or b""

    def state(self) -> dict[str, Any]:
        with self._lock:
            g = self._g
            n, d = (0, 0) if g is None else (len(g), g.sh_degree)
            return {"source": self.source, "version": self.version, "num_gaussians": n, "sh_degree": d,
                    "ply_bytes": ply_bytes(n, d), "file_bytes": self.file_bytes, "near": NEAR, "background": list(self.background), "up": self.up,
                    "cameras": [c.__dict__ for c in self.cameras], "live": dict(self._info), **self._bounds}


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class _Handler(BaseHTTPRequestHandler):
    """The viewer's requests: its assets, the scene's state, model and points; GET and HEAD only."""

    store: ClassVar[SceneStore]
    assets: ClassVar[dict[str, Asset]]
    allowed_hosts: ClassVar[set[str] | None]  # Host headers served (None: any)
    server_version = "splatcli"
    sys_version = ""

    def log_message(self, *args: Any) -> None:  # the core never prints
        pass

    def _send(self, code: int, body: bytes, ctype: str, gz: bool = False, head: bool = False) -> None:
        self.send_response(code)
        headers = {"Content-Type": ctype, "Content-Length": str(len(body)), "Cache-Control": "no-store",
                   "X-Content-Type-Options": "nosniff", **({"Content-Encoding": "gzip"} if gz else {})}
        for name, value in headers.items():
            self.send_header(name, value)
        self.end_headers()
        if not head:
            self.wfile.write(body)

    def _route(self, head: bool) -> None:
        host = (self.headers.get("Host") or "").rsplit(":", 1)[0].strip("[]").lower()
        if self.allowed_hosts is not None and host not in self.allowed_hosts:
            return self._send(403, b"forbidden host\n", _TYPES[""], head=head)
        path = self.path.split("?", 1)[0].split("#", 1)[0]
        if path in self.assets:
            a = self.assets[path]
            if a.gzipped and "gzip" not in (self.headers.get("Accept-Encoding") or ""):
                return self._send(200, gzip.decompress(a.body), a.content_type, False, head)
            return self._send(200, a.body, a.content_type, a.gzipped, head)
        if path == "/api/scene":
            self.store.asked = time.monotonic()
            return self._send(200, json.dumps(self.store.state()).encode(), "application/json", head=head)
        data = {"/api/scene.ply": self.store.ply, "/api/points.bin": self.store.points}.get(path)
        if data is not None:
            return self._send(200, data(), "application/octet-stream", head=head)
        return self._send(404, b"not found\n", _TYPES[""], head=head)

    def do_GET(self) -> None:
        self._guarded(False)

    def do_HEAD(self) -> None:
        self._guarded(True)

    def _guarded(self, head: bool) -> None:
        try:
            self._route(head)
        except (BrokenPipeError, ConnectionResetError):
            pass
        except Exception:  # a bug in one request must not stop the server
            try:
                self._send(500, b"internal error\n", _TYPES[""], head=head)
            except OSError:
                pass

    def _refuse(self) -> None:
        self._send(405, b"method not allowed\n", _TYPES[""])

    do_POST = do_PUT = do_DELETE = do_PATCH = do_OPTIONS = _refuse


def _handler(store: SceneStore, assets: dict[str, Asset], allowed_hosts: set[str] | None) -> type[_Handler]:
    return type("Handler", (_Handler,), {"store": store, "assets": assets, "allowed_hosts": allowed_hosts})


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = False

    def handle_error(self, request, client_address) -> None:  # malformed requests: drop them quietly
        pass


class ViewerServer:
    """Serves `store` on host:port in a background thread until `close()`; port None:
    the default port or the next free one, 0: any free port."""

    def __init__(self, store: SceneStore, host: str = "127.0.0.1", port: int | None = None) -> None:
        self.store, self.host = store, host
        allowed = {host.lower(), "localhost", "127.0.0.1", "::1"} if is_loopback(host) else None
        handler = _handler(store, assets(), allowed)
        self._httpd = _bind(host, port, handler)
        self.port = int(self._httpd.server_address[1])
        self._thread = threading.Thread(target=self._httpd.serve_forever, kwargs={"poll_interval": 0.2},
                                        name="splatcli-viewer", daemon=True)

    @property
    def url(self) -> str:
        h = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{h}:{self.port}/"

    def start(self) -> ViewerServer:
        self._thread.start()
        return self

    def close(self) -> None:
        self._httpd.shutdown()
        self._httpd.server_close()

    def __enter__(self) -> ViewerServer:
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.close()


def _bind(host: str, port: int, handler) -> _Server:
    """`port`, or with port None the default port or the next free one after it."""
    cls = type("_Server6", (_Server,), {"address_family": socket.AF_INET6}) if ":" in host else _Server
    tries = [port] if port is not None else [DEFAULT_PORT + i for i in range(PORT_TRIES)]
    last: OSError | None = None
    for p in tries:
        try:
            return cls((host, p), handler)
        except OSError as exc:
            last = exc
    if port is not None:
        raise SplatError(f"--port {port}: cannot listen on {host}:{port} ({last.strerror or last})",
                         hint="choose another --port, or leave it out to use a free one") from None
    raise SplatError(f"no free port on {host} from {DEFAULT_PORT} to {DEFAULT_PORT + PORT_TRIES - 1}",
                     hint="pass --port") from None
