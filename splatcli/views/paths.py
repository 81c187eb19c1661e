"""Generated camera paths for `render --path`, built around a set of cameras: an
`orbit` circling the point the cameras look at, an LLFF-style `spiral` around
their average pose, or `interpolate`, a smooth path through them in name order;
and a ring of cameras for a splat rendered without any."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ..camera import Camera, focus_point, scene_extent
from ..errors import SplatError
from .sources import View

PATHS = ("orbit", "spiral", "interpolate")



def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:  # [3],[3],[3] -> [4, 4]
    """World-to-camera in OpenCV axes: z towards `target`, y down (against `up`)."""
    z = target - eye
    z = z / max(np.linalg.norm(z), 1e-12)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking along `up`: any perpendicular will do
        x = np.cross(z, np.array([1.0, 0, 0]) if abs(z[0]) < 0.9 else np.array([0, 1.0, 0]))
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    view = np.eye(4)
    view[:3, :3] = np.stack([x, y, z])
    view[:3, 3] = -view[:3, :3] @ eye
    return view


def _up(cams: Sequence[Camera]) -> np.ndarray:  # [3] mean world "up" (= -camera y)
    up = -np.mean([c.viewmat[1, :3] for c in cams], axis=0)
    n = np.linalg.norm(up)
    return up / n if n > 1e-9 else np.array([0.0, -1.0, 0.0])


def target_point(cams: Sequence[Camera]) -> np.ndarray:  # [3]
    """What a path looks at: the cameras' common focus (camera.focus_point) when it
    lies at a sane distance, else a point in front of them at the scene's extent."""
    mid, radius = scene_extent(list(cams))
    p = focus_point(list(cams))
    if p is not None and np.linalg.norm(p - mid) <= 10 * radius:
        return p
    fwd = np.mean([c.viewmat[2, :3] for c in cams], axis=0)
    return np.stack([c.center for c in cams]).mean(axis=0) + fwd / max(np.linalg.norm(fwd), 1e-12) * radius


def rot_to_quat(R: np.ndarray) -> np.ndarray:  # [3, 3] -> [4] w, x, y, z
    t = np.trace(R)
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def _quat_to_rot(q: np.ndarray) -> np.ndarray:  # [4] -> [3, 3]
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _slerp(q0: np.ndarray, q1: np.ndarray, t: float) -> np.ndarray:
    if np.dot(q0, q1) < 0:
        q1 = -q1
    d = float(np.clip(np.dot(q0, q1), -1.0, 1.0))
    if d > 0.9995:
        q = q0 + t * (q1 - q0)
    else:
        a = math.acos(d)
        q = (math.sin((1 - t) * a) * q0 + math.sin(t * a) * q1) / math.sin(a)
    return q / np.linalg.norm(q)


def _generated(template: Camera, kind: str, viewmats: list[np.ndarray], Ks: list[np.ndarray] | None = None) -> list[View]:
    views = []
    for i, vm in enumerate(viewmats):
        K = template.K if Ks is None else Ks[i]
        cam = Camera(name=f"{kind}_{i:04d}", width=template.width, height=template.height, K=K.copy(), viewmat=vm)
        views.append(View(camera=cam, out_name=f"{kind}_{i:04d}.png"))
    return views


# A gap in the cameras' directions around the focus wider than this is left out of
# the orbit: those sides of the scene were never photographed.
ORBIT_MAX_GAP_DEG = 60.0


def orbit_path(cams: Sequence[Camera], frames: int) -> list[View]:
    """A circle around the focus point at the cameras' mean height and distance. When
    the cameras leave a gap wider than ORBIT_MAX_GAP_DEG (a 270-degree capture), the
    path sweeps the covered arc and back instead (smooth at the turns, so the video
    loops), rather than showing the side no photo saw."""
    target = target_point(cams)
    up = _up(cams)
    rel = np.stack([c.center for c in cams]) - target
    height = float(np.mean(rel @ up))
    horiz = rel - np.outer(rel @ up, up)
    radius = float(np.mean(np.linalg.norm(horiz, axis=1)))
    if radius < 1e-9:
        radius = scene_extent(list(cams))[1]
    e1 = horiz[0] / np.linalg.norm(horiz[0]) if np.linalg.norm(horiz[0]) > 1e-9 else np.cross(up, [1.0, 0, 0])
    e1 = e1 / np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    start, span, sweep = 0.0, 2 * math.pi, False
    ok = np.linalg.norm(horiz, axis=1) > 1e-9 * max(radius, 1e-12)
    if ok.sum() >= 2:
        az = np.sort(np.arctan2(horiz[ok] @ e2, horiz[ok] @ e1))
        gaps = np.diff(np.concatenate([az, az[:1] + 2 * math.pi]))
        g = int(np.argmax(gaps))
        if math.degrees(gaps[g]) > ORBIT_MAX_GAP_DEG:
            start, span, sweep = float(az[(g + 1) % len(az)]), 2 * math.pi - float(gaps[g]), True
    vms = []
    for i in range(frames):
        s = i / frames
        a = start + (span * (1 - math.cos(2 * math.pi * s)) / 2 if sweep else span * s)
        eye = target + height * up + radius * (math.cos(a) * e1 + math.sin(a) * e2)
        vms.append(look_at(eye, target, up))
    return _generated(cams[0], "orbit", vms)


def spiral_path(cams: Sequence[Camera], frames: int, rotations: float = 2.0) -> list[View]:
    """The LLFF render path: a spiral around the average camera, in its image
    plane, with a forward-backward swing, always looking at the focus point.
    Cameras that look inwards from all sides (a 360-degree capture, where the
    average viewing direction nearly cancels) get a rising and falling orbit
    instead: `rotations` turns around the focus point, the height swinging by
    half the orbit radius."""
    centers = np.stack([c.center for c in cams])
    mid = centers.mean(axis=0)
    z = np.mean([c.viewmat[2, :3] for c in cams], axis=0)
    up = _up(cams)
    if np.linalg.norm(z) < 0.5 or abs(np.dot(z, up)) > 0.9 * np.linalg.norm(z):
        return _spiral_360(cams, frames, rotations, up)
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    x = x / max(np.linalg.norm(x), 1e-12)
    y = np.cross(z, x)
    basis = np.stack([x, y, z])  # rows: average camera axes in world coordinates
    target = target_point(cams)
    focal = max(float(np.dot(target - mid, z)), 1e-3)
    local = np.abs((centers - mid) @ basis.T)
    rads = np.percentile(local, 90, axis=0)
    rads = np.maximum(rads, 0.05 * scene_extent(list(cams))[1])  # a single camera still spirals
    vms = []
    for i in range(frames):
        t = 2 * math.pi * rotations * i / frames
        off = rads * np.array([math.cos(t), -math.sin(t), -math.sin(0.5 * t)])
        eye = mid + off @ basis
        vms.append(look_at(eye, mid + focal * z, up))
    return _generated(cams[0], "spiral", vms)


def _spiral_360(cams: Sequence[Camera], frames: int, rotations: float, up: np.ndarray) -> list[View]:
    base = orbit_path(cams, 1)[0].camera  # the orbit's start: radius and height
    target = target_point(cams)
    rel = base.center - target
    height = float(rel @ up)
    horiz = rel - height * up
    radius = float(np.linalg.norm(horiz))
    e1 = horiz / max(radius, 1e-12)
    e2 = np.cross(up, e1)
    vms = []
    for i in range(frames):
        a = 2 * math.pi * rotations * i / frames
        h = height + 0.5 * radius * math.sin(a / rotations)  # one full rise and fall over the path
        eye = target + h * up + radius * (math.cos(a) * e1 + math.sin(a) * e2)
        vms.append(look_at(eye, target, up))
    return _generated(cams[0], "spiral", vms)


def interpolate_path(cams: Sequence[Camera], frames: int) -> list[View]:
    """A smooth path through the cameras in order: Catmull-Rom through the centres,
    slerp between the orientations, intrinsics blended linearly (at the first
    camera's image size)."""
    if len(cams) < 2:
        raise SplatError("--path interpolate needs at least 2 cameras")
    tmpl = cams[0]
    cams = [c.resized(tmpl.width, tmpl.height) for c in cams]
    P = np.stack([c.center for c in cams])
    Q = [rot_to_quat(c.viewmat[:3, :3]) for c in cams]
    n = len(cams)
    vms, Ks = [], []
    for i in range(frames):
        s = (n - 1) * i / max(frames - 1, 1)
        k = min(int(s), n - 2)
        t = s - k
        p0, p1, p2, p3 = P[max(k - 1, 0)], P[k], P[k + 1], P[min(k + 2, n - 1)]
        eye = 0.5 * (2 * p1 + (-p0 + p2) * t + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t * t
                     + (-p0 + 3 * p1 - 3 * p2 + p3) * t ** 3)
        R = _quat_to_rot(_slerp(Q[k], Q[k + 1], t))
        vm = np.eye(4)
        vm[:3, :3] = R
        vm[:3, 3] = -R @ eye
        vms.append(vm)
        Ks.append((1 - t) * cams[k].K + t * cams[k + 1].K)
    return _generated(tmpl, "interpolate", vms, Ks)


def cameras_around_points(points: np.ndarray, *, width: int = 800, height: int = 600, fov_deg: float = 50.0,
                          count: int = 8) -> list[Camera]:  # points [P, 3]
    """A ring of cameras looking at a point set, for a .ply rendered without any
    cameras. 'Up' is world -y, the usual COLMAP orientation. The ring sits at
    twice the radius holding 80% of the points, slightly above them."""
    pts = points[np.isfinite(points).all(axis=1)]
    center = np.median(pts, axis=0) if len(pts) else np.zeros(3)
    r = max(float(np.percentile(np.linalg.norm(pts - center, axis=1), 80)) if len(pts) else 1.0, 1e-3)
    up = np.array([0.0, -1.0, 0.0])
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    cams = []
    for i in range(count):
        a = 2 * math.pi * i / count
        eye = center + 2.5 * r * np.array([math.cos(a), 0.0, math.sin(a)]) + 0.8 * r * up
        cams.append(Camera(name=f"ring_{i}", width=width, height=height, K=K, viewmat=look_at(eye, center, up)))
    return cams


def generate_path(kind: str, cams: Sequence[Camera], frames: int) -> list[View]:
    if kind not in PATHS:
        raise SplatError(f"--path {kind!r} is not known; allowed values: {', '.join(PATHS)}")
    if frames < 1:
        raise SplatError(f"--frames {frames}: must be at least 1")
    if not cams:
        raise SplatError(f"--path {kind}: no cameras to build the path around")
    return {"orbit": orbit_path, "spiral": spiral_path, "interpolate": interpolate_path}[kind](cams, frames)
