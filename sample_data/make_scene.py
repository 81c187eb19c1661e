"""Render splatcli's sample scene: a small textured still life seen from an orbit.

A deterministic ray caster written with numpy only (OpenCV just encodes the
JPEGs), independent of splatcli's rasterizer so that it can serve as ground
truth for it. The scene is a handful of analytic primitives -- a ground disc, a
cylindrical back wall, three boxes and two spheres -- with procedural solid
textures (multi-octave value noise, checkers, stripes and random coloured dots)
chosen so that SIFT finds many distinctive features, lit by Lambert shading
with one directional light, hard shadows and an ambient term. Every pixel is
the mean of a 2x2 grid of sub-pixel rays.

Conventions (the project's): world is z-up; cameras are OpenCV/COLMAP (x
right, y down, z forward); `viewmat` [4, 4] maps world to camera; pixel
(u, v) is sampled at its centre (u + 0.5, v + 0.5) in the coordinates of K.

    python sample_data/make_scene.py [--out sample_data/scene] [--views 28] [--kind object]
                                     [--width 320] [--height 240] [--seed 0] [--distractor]

writes out/images/NNN.jpg and out/ground_truth.json (see README.md). --distractor
adds a ball rolling through the scene, seen in three views of four at most (never
in a view numbered a multiple of 4, so never in the held-out views, every 8th from
000), and writes masks as out/masks/NNN.jpg.png (0 where the ball is).
"""

# No `from __future__ import annotations`: tests load this file by path, without a
# sys.modules entry, and dataclasses must then not need to resolve string annotations.

import argparse
import functools
import json
import math
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

# ---------------------------------------------------------------------------
# Scene layout (world units ~ metres, z up). Fixed: the seed only changes
# textures, so every seed gives the same geometry and the same cameras.
# ---------------------------------------------------------------------------

WALL_RADIUS = 6.0  # cylinder enclosing the scene: textured background in every view
WALL_HEIGHT = 4.0
LOOK_AT = np.array([0.0, 0.0, 0.45])  # every camera looks at this point
ORBIT_RADIUS = 3.6
ORBIT_HEIGHT = 1.55  # mean camera height above the ground
ORBIT_HEIGHT_SWING = 0.6  # +- height variation along the arc: varied views pin down the focal length in SfM
ARC_DEGREES = 270.0  # the longest arc; fewer views get a shorter one (see arc_for_views)
MAX_STEP_DEGREES = 10.0  # between neighbouring views: SIFT still matches at 160 x 120 pixels
FOCAL_FACTOR = 1.0  # fx = fy = FOCAL_FACTOR * width
LIGHT_DIR = np.array([0.45, -0.35, 0.82]) / np.linalg.norm([0.45, -0.35, 0.82])  # towards the light
AMBIENT = 0.38  # fraction of light that reaches surfaces facing away / in shadow
EPS = 1e-6
DOT_FILL = 0.75  # fraction of texture cells that carry a coloured dot


@dataclass(frozen=True)
class Box:
    center: tuple[float, float, float]
    half: tuple[float, float, float]  # half extents along the box's own axes
    yaw_deg: float  # rotation about world z
    material: int


@dataclass(frozen=True)
class Sphere:
    center: tuple[float, float, float]
    radius: float
    material: int


# Material ids: 0 ground, 1 wall, 2.. objects. 255 = sky (no hit).
GROUND, WALL, SKY = 0, 1, 255
BOXES = (
    Box((0.75, -0.35, 0.40), (0.40, 0.40, 0.40), 22.0, 2),
    Box((-0.75, 0.45, 0.60), (0.25, 0.28, 0.60), -15.0, 3),
    Box((0.20, 0.95, 0.16), (0.55, 0.30, 0.16), 8.0, 4),
)
SPHERES = (
    Sphere((-0.45, -0.80, 0.42), 0.42, 5),
    Sphere((0.45, 0.95, 0.32 + 0.26), 0.26, 6),  # rests on the flat box
)


# ---------------------------------------------------------------------------
# Cameras
# ---------------------------------------------------------------------------


def look_at_viewmat(center: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """World-to-camera [4, 4] for an OpenCV camera at `center` [3] looking at `target` [3]."""
    fwd = target - center
    fwd = fwd / np.linalg.norm(fwd)
    right = np.cross(fwd, up)
    right = right / np.linalg.norm(right)
    down = np.cross(fwd, right)  # right x down = forward: a right-handed camera frame
    R = np.stack([right, down, fwd])  # rows: camera axes in world coordinates
    viewmat = np.eye(4)
    viewmat[:3, :3] = R
    viewmat[:3, 3] = -R @ center
    return viewmat


def arc_for_views(num_views: int) -> float:
    """Default arc (degrees) for `num_views`: ARC_DEGREES, shortened so neighbours stay <= MAX_STEP_DEGREES apart."""
    return min(ARC_DEGREES, MAX_STEP_DEGREES * max(num_views - 1, 1))


def orbit_cameras(num_views: int, width: int, height: int, arc_degrees: float | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """(K [3, 3], viewmat [4, 4]) per view along an arc around LOOK_AT, with a gentle height wave."""
    if arc_degrees is None:
        arc_degrees = arc_for_views(num_views)
    f = FOCAL_FACTOR * width
    K = np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])
    out = []
    start = -math.radians(arc_degrees) / 2.0 - math.pi / 2.0  # arc centred on the -y side
    for i in range(num_views):
        s = i / max(num_views - 1, 1)
        a = start + s * math.radians(arc_degrees)
        z = ORBIT_HEIGHT + ORBIT_HEIGHT_SWING * math.sin(2.0 * math.pi * 1.5 * s)
        c = np.array([ORBIT_RADIUS * math.cos(a), ORBIT_RADIUS * math.sin(a), z])
        out.append((K.copy(), look_at_viewmat(c, LOOK_AT)))
    return out


# ---------------------------------------------------------------------------
# Ray casting
# ---------------------------------------------------------------------------


def _box_local(x: np.ndarray, y: np.ndarray, box: Box, is_dir: bool) -> tuple[np.ndarray, np.ndarray]:
    """World x, y [N] to the box's yawed frame (z is shared). Column-wise: numpy's
    [N, 3] @ [3, 3] and axis=1 reductions are several times slower than this."""
    c, s = math.cos(math.radians(box.yaw_deg)), math.sin(math.radians(box.yaw_deg))
    if not is_dir:
        x, y = x - box.center[0], y - box.center[1]
    return c * x + s * y, -s * x + c * y


def _t_box(o: np.ndarray, d: np.ndarray, box: Box) -> np.ndarray:
    """Entry distance [N] (inf on miss) of rays o, d [N, 3] into a yawed box (slab method)."""
    ox, oy = _box_local(o[:, 0], o[:, 1], box, False)
    dx, dy = _box_local(d[:, 0], d[:, 1], box, True)
    tmin = np.full(len(o), -np.inf)
    tmax = np.full(len(o), np.inf)
    for oc, dc, h in ((ox, dx, box.half[0]), (oy, dy, box.half[1]), (o[:, 2] - box.center[2], d[:, 2], box.half[2])):
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / dc
            t1 = (-h - oc) * inv
            t2 = (h - oc) * inv
        # A ray parallel to a slab gives +-inf (or nan when on its plane): nan_to_num keeps it harmless.
        tmin = np.maximum(tmin, np.nan_to_num(np.minimum(t1, t2), nan=-np.inf))
        tmax = np.minimum(tmax, np.nan_to_num(np.maximum(t1, t2), nan=np.inf))
    return np.where((tmax >= tmin) & (tmin > EPS), tmin, np.inf)


def _normal_box(p: np.ndarray, box: Box) -> np.ndarray:
    """Outward normal [N, 3] at surface points p [N, 3]: the face whose slab p is furthest along."""
    x, y = _box_local(p[:, 0], p[:, 1], box, False)
    rel = np.stack([x / box.half[0], y / box.half[1], (p[:, 2] - box.center[2]) / box.half[2]], axis=1)
    axis = np.argmax(np.abs(rel), axis=1)
    nl = np.zeros_like(p)
    rows = np.arange(len(p))
    nl[rows, axis] = np.sign(rel[rows, axis])
    c, s = math.cos(math.radians(box.yaw_deg)), math.sin(math.radians(box.yaw_deg))
    return np.stack([c * nl[:, 0] - s * nl[:, 1], s * nl[:, 0] + c * nl[:, 1], nl[:, 2]], axis=1)


def _t_sphere(o: np.ndarray, d: np.ndarray, sp: Sphere) -> np.ndarray:
    """Entry distance [N] (inf on miss); d is unit length."""
    ocx, ocy, ocz = o[:, 0] - sp.center[0], o[:, 1] - sp.center[1], o[:, 2] - sp.center[2]
    b = ocx * d[:, 0] + ocy * d[:, 1] + ocz * d[:, 2]
    disc = b * b - (ocx * ocx + ocy * ocy + ocz * ocz - sp.radius**2)
    t = -b - np.sqrt(np.maximum(disc, 0.0))
    return np.where((disc >= 0) & (t > EPS), t, np.inf)


def _t_ground(o: np.ndarray, d: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -o[:, 2] / d[:, 2]
    return np.where((d[:, 2] < 0) & (t > EPS), t, np.inf)


def _t_wall(o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """The inside of the cylinder x^2 + y^2 = WALL_RADIUS^2, 0 <= z <= WALL_HEIGHT (rays start inside)."""
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    b = o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1]
    c = o[:, 0] ** 2 + o[:, 1] ** 2 - WALL_RADIUS**2
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (-b + np.sqrt(np.maximum(b * b - a * c, 0.0))) / a
        z = o[:, 2] + t * d[:, 2]
    return np.where((a > 1e-12) & (t > EPS) & (z >= 0.0) & (z <= WALL_HEIGHT), t, np.inf)


def _normal(p: np.ndarray, mat: int) -> np.ndarray:
    """Surface normal [N, 3] at points p [N, 3] on the primitive carrying material `mat`."""
    if mat == GROUND:
        return np.broadcast_to(np.array([0.0, 0.0, 1.0]), p.shape)
    if mat == WALL:  # seen from inside: points to the axis
        return np.stack([-p[:, 0], -p[:, 1], np.zeros(len(p))], axis=1) / WALL_RADIUS
    for b in BOXES:
        if b.material == mat:
            return _normal_box(p, b)
    sp = next(s for s in SPHERES if s.material == mat)
    return (p - np.asarray(sp.center)) / sp.radius


def _cast(o: np.ndarray, d: np.ndarray, with_background: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hit of rays o, d [N, 3]: distance [N] (inf = none) and material [N] uint8 (SKY = none)."""
    best_t = np.full(len(o), np.inf)
    best_m = np.full(len(o), SKY, dtype=np.uint8)
    hits = [(_t_box(o, d, b), b.material) for b in BOXES]
    hits += [(_t_sphere(o, d, s), s.material) for s in SPHERES]
    if with_background:
        hits += [(_t_ground(o, d), GROUND), (_t_wall(o, d), WALL)]
    for t, m in hits:
        closer = t < best_t
        best_t = np.where(closer, t, best_t)
        best_m[closer] = m
    return best_t, best_m


# ---------------------------------------------------------------------------
# Procedural textures (solid: functions of the world position)
# ---------------------------------------------------------------------------

_TABLE = 4096  # lattice hash period in cells: > 50 world units even for the finest noise octave


@functools.cache
def _tables(salt: int) -> tuple[np.ndarray, np.ndarray]:
    """Permutation [T] int64 and uniform values [T, 8] for one salt. PCG64 is
    stable across numpy versions and platforms, so textures are too."""
    rng = np.random.default_rng(salt & 0xFFFFFFFF)
    return rng.permutation(_TABLE), rng.random((_TABLE, 8))


def _cell_index(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray, perm: np.ndarray) -> np.ndarray:
    """Pseudo-random index [N] in [0, T) per integer lattice point (Perlin's nested permutation)."""
    m = _TABLE - 1  # & m is mod T for negative ints too (two's complement)
    return perm[(perm[(perm[ix & m] + iy) & m] + iz) & m]


def _value_noise(p: np.ndarray, salt: int) -> np.ndarray:
    """Smooth value noise in [0, 1] at points p [N, 3] (lattice spacing 1)."""
    perm, vals = _tables(salt)
    m = _TABLE - 1
    fl = np.floor(p)
    i = fl.astype(np.int64)
    f = p - fl
    w = f * f * (3.0 - 2.0 * f)
    out = np.zeros(len(p))
    for dx in (0, 1):
        wx = w[:, 0] if dx else 1.0 - w[:, 0]
        hx = perm[(i[:, 0] + dx) & m]
        for dy in (0, 1):
            wxy = wx * (w[:, 1] if dy else 1.0 - w[:, 1])
            hxy = perm[(hx + i[:, 1] + dy) & m]
            for dz in (0, 1):
                wz = w[:, 2] if dz else 1.0 - w[:, 2]
                out += wxy * wz * vals[perm[(hxy + i[:, 2] + dz) & m], 0]
    return out


def _fbm(p: np.ndarray, salt: int, octaves: int, base_freq: float) -> np.ndarray:
    """Fractal sum of value noise, normalised to about [0, 1]."""
    total, amp, norm, freq = np.zeros(len(p)), 1.0, 0.0, base_freq
    for k in range(octaves):
        total += amp * _value_noise(p * freq + 17.31 * k, salt + 101 * k)
        norm += amp
        amp *= 0.55
        freq *= 2.03  # not exactly 2: keeps octaves from lining up on the lattice
    return total / norm


def _dots(p: np.ndarray, salt: int, cell: float, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Random coloured spots: coverage [N] in [0, 1] and colour [N, 3].

    One sphere per lattice cell of size `cell`, centred at a jittered point that
    keeps it inside its cell, so only the own cell needs testing. A surface cuts
    the spheres in discs of varying size -- blobs of many sizes and colours.
    """
    perm, vals = _tables(salt)
    q = p / cell
    fl = np.floor(q)
    i = fl.astype(np.int64)
    h = vals[_cell_index(i[:, 0], i[:, 1], i[:, 2], perm)]  # [N, 8] uniforms per cell
    centre = 0.3 + 0.4 * h[:, :3]
    r = radius * (0.5 + 0.5 * h[:, 3])
    keep = h[:, 4] < DOT_FILL  # some cells stay empty
    dist = np.linalg.norm(q - fl - centre, axis=1)
    cover = np.clip((r - dist) / 0.04 + 0.5, 0.0, 1.0) * keep  # soft 4%-of-cell edge
    val = 0.15 + 0.85 * h[:, 6]  # spread luminance: SIFT sees grey
    return cover, _hsv(h[:, 5], np.full(len(p), 0.75), val)


def _hsv(h: np.ndarray, s: np.ndarray, v: np.ndarray) -> np.ndarray:
    """HSV [N] each in [0, 1] to RGB [N, 3]."""
    k = (np.array([5.0, 3.0, 1.0])[None, :] + h[:, None] * 6.0) % 6.0
    return v[:, None] - v[:, None] * s[:, None] * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)


def _mix(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    return a + (b - a) * t[:, None]


@dataclass(frozen=True)
class Material:
    color_a: tuple[float, float, float]  # linear RGB of the two base tones
    color_b: tuple[float, float, float]
    noise_freq: float  # per world unit, lowest fbm octave
    pattern: str  # "checker", "stripes", "bricks", "tiles" or "none"
    pattern_scale: float  # world units per pattern period
    dot_cell: float  # world units between coloured dots
    dot_radius: float  # as a fraction of the cell


MATERIALS = {
    GROUND: Material((0.42, 0.36, 0.26), (0.16, 0.20, 0.12), 1.6, "tiles", 0.5, 0.30, 0.30),
    WALL: Material((0.55, 0.30, 0.22), (0.25, 0.28, 0.40), 1.1, "bricks", 0.45, 0.42, 0.30),
    2: Material((0.70, 0.62, 0.30), (0.30, 0.12, 0.10), 3.0, "checker", 0.2, 0.14, 0.30),
    3: Material((0.20, 0.45, 0.60), (0.85, 0.85, 0.80), 2.5, "stripes", 0.16, 0.13, 0.30),
    4: Material((0.60, 0.25, 0.45), (0.95, 0.75, 0.40), 3.5, "checker", 0.14, 0.12, 0.28),
    5: Material((0.25, 0.55, 0.25), (0.90, 0.90, 0.55), 3.0, "stripes", 0.12, 0.12, 0.30),
    6: Material((0.85, 0.40, 0.15), (0.20, 0.15, 0.45), 4.0, "checker", 0.10, 0.09, 0.30),
}


def _pattern(p: np.ndarray, kind: str, scale: float) -> np.ndarray:
    """Regular pattern value in [0, 1] at p [N, 3]."""
    q = p / scale
    if kind == "checker":
        return (np.floor(q).astype(np.int64).sum(axis=1) % 2).astype(np.float64)
    if kind == "stripes":  # diagonal stripes across x, y and z so every face shows them
        return 0.5 + 0.5 * np.sin(math.pi * (q[:, 0] + q[:, 1] + q[:, 2]))
    if kind == "tiles":  # dark grout lines between square tiles of the ground
        fx, fy = q[:, 0] - np.floor(q[:, 0]), q[:, 1] - np.floor(q[:, 1])
        grout = np.minimum(np.minimum(fx, 1 - fx), np.minimum(fy, 1 - fy))
        return np.clip(grout / 0.05, 0.0, 1.0)
    if kind == "bricks":  # the wall, in (arc length, height) coordinates, rows offset by half a brick
        ang = np.arctan2(p[:, 1], p[:, 0]) * WALL_RADIUS / scale
        row = np.floor(q[:, 2] * 2.0)
        bx = ang + 0.5 * (row % 2)
        fx = bx - np.floor(bx)
        fz = q[:, 2] * 2.0 - row
        mortar = np.minimum(np.minimum(fx, 1 - fx) * 2.0, np.minimum(fz, 1 - fz))
        return np.clip(mortar / 0.08, 0.0, 1.0)
    return np.ones(len(p))


def _albedo(p: np.ndarray, mat_id: int, seed: int) -> np.ndarray:
    """Linear RGB albedo [N, 3] of material `mat_id` at world points p [N, 3]."""
    m = MATERIALS[mat_id]
    salt = seed * 7919 + mat_id * 104729
    # Shift off the lattice: the ground plane z = 0 would otherwise sit on a cell boundary
    # of every texture lattice and cut all the dot spheres at their very edge.
    p = p + np.array([0.137, 0.291, 0.173]) * (1 + mat_id)
    base_t = _fbm(p, salt, 3, m.noise_freq)
    detail = _fbm(p, salt + 17, 3, m.noise_freq * 5.0)
    col = _mix(np.asarray(m.color_a)[None].repeat(len(p), 0), np.asarray(m.color_b)[None].repeat(len(p), 0),
               np.clip((base_t - 0.3) * 2.5, 0.0, 1.0))
    col = col * (0.65 + 0.7 * detail)[:, None]
    pat = _pattern(p, m.pattern, m.pattern_scale)
    if m.pattern in ("tiles", "bricks"):
        col = col * (0.35 + 0.65 * pat)[:, None]  # grout / mortar lines darken
    elif m.pattern != "none":
        col = col * (0.55 + 0.45 * pat)[:, None]
    # Two layers of dots: coarse ones survive at low resolution and far away, fine ones add detail up close.
    for k, cell in enumerate((m.dot_cell * 2.5, m.dot_cell)):
        cover, dot_col = _dots(p, salt + 31 + 10 * k, cell, m.dot_radius)
        col = _mix(col, dot_col, cover)
    return np.clip(col, 0.0, 1.0)


def _sky(d: np.ndarray) -> np.ndarray:
    """Smooth gradient [N, 3] by elevation of unit directions d [N, 3]."""
    t = np.clip(d[:, 2], 0.0, 1.0)
    return _mix(np.broadcast_to([0.75, 0.82, 0.95], d.shape), np.broadcast_to([0.30, 0.45, 0.80], d.shape), t)


def pixel_rays(K: np.ndarray, viewmat: np.ndarray, width: int, height: int, supersample: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """World-space ray origins and unit directions [H*ss * W*ss, 3], row-major over (v, u).

    Sub-pixel j of pixel u sits at u + (j + 0.5) / ss, so with ss = 1 the ray goes
    through the pixel centre u + 0.5, and the ss x ss samples average to it.
    """
    ss = supersample
    offs = (np.arange(ss) + 0.5) / ss
    u = (np.arange(width)[:, None] + offs[None, :]).reshape(-1)  # [W*ss]
    v = (np.arange(height)[:, None] + offs[None, :]).reshape(-1)  # [H*ss]
    uu, vv = np.meshgrid(u, v)  # [H*ss, W*ss]
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    M = np.linalg.inv(K).T @ R  # rows map (u, v, 1) to R^T K^-1 [u, v, 1]: camera ray rotated to world
    # Column-wise products: numpy's [N, 3] @ [3, 3] is several times slower than this.
    d = uu.reshape(-1, 1) * M[0] + vv.reshape(-1, 1) * M[1] + M[2]
    d /= np.sqrt(d[:, 0] ** 2 + d[:, 1] ** 2 + d[:, 2] ** 2)[:, None]
    o = np.ascontiguousarray(np.broadcast_to(-R.T @ t, d.shape))
    return o, d


def material_ids(K: np.ndarray, viewmat: np.ndarray, width: int, height: int) -> np.ndarray:
    """Material id [H, W] uint8 seen through each pixel centre (SKY where nothing is hit)."""
    o, d = pixel_rays(K, viewmat, width, height)
    return _cast(o, d)[1].reshape(height, width)


# The "object" variant: the same objects on a plain sheet of paper before a backdrop out of
# focus, as in a hand-held object capture (SfM finds nothing on the sheet or the backdrop).
PAPER = Material((0.80, 0.78, 0.72), (0.76, 0.74, 0.69), 0.8, "none", 1.0, 1.0, 0.0)
BACKDROP_BLUR = 0.03  # Gaussian defocus of the wall and sky, sigma as a fraction of the image width


def render_view(K: np.ndarray, viewmat: np.ndarray, width: int, height: int, seed: int = 0, supersample: int = 2,
                kind: str = "still-life") -> np.ndarray:
    """RGB uint8 image [H, W, 3] seen by the camera K [3, 3], viewmat [4, 4]. `kind`
    "object": the ground is plain paper and the backdrop (wall, sky) is defocused."""
    ss = supersample
    o, d = pixel_rays(K, viewmat, width, height, ss)
    dist, mat = _cast(o, d)
    rgb = np.empty_like(d)
    sky = mat == SKY
    rgb[sky] = _sky(d[sky])
    hit = ~sky
    p = o[hit] + d[hit] * dist[hit, None]
    mh = mat[hit]
    n = np.empty_like(p)
    albedo = np.empty_like(p)
    for m in np.unique(mh):
        sel = mh == m
        n[sel] = _normal(p[sel], int(m))
        albedo[sel] = _albedo(p[sel], int(m), seed)
        if kind == "object" and m == GROUND:
            albedo[sel] = _plain(p[sel], seed)
    # Hard shadows cast by the objects (the ground and the wall only receive them).
    lambert = np.clip(n[:, 0] * LIGHT_DIR[0] + n[:, 1] * LIGHT_DIR[1] + n[:, 2] * LIGHT_DIR[2], 0.0, None)
    lit = np.flatnonzero(lambert > 0)
    shadow_t, _ = _cast(p[lit] + n[lit] * 1e-4, np.broadcast_to(LIGHT_DIR, (len(lit), 3)), with_background=False)
    lambert[lit[np.isfinite(shadow_t)]] = 0.0
    shade = AMBIENT + (1.0 - AMBIENT) * lambert
    rgb[hit] = albedo * shade[:, None] * 1.25  # exposure: lit faces near the white point without clipping much

    lin = rgb.reshape(height, ss, width, ss, 3).mean(axis=(1, 3))  # box filter in linear light
    if kind == "object":
        far = ((mat == WALL) | (mat == SKY)).reshape(height, ss, width, ss).mean(axis=(1, 3))
        lin = _defocus(lin, far, BACKDROP_BLUR * width)
    srgb = np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * np.power(np.clip(lin, 0.0031308, None), 1 / 2.4) - 0.055)
    return np.clip(np.round(srgb * 255.0), 0, 255).astype(np.uint8)


def _plain(p: np.ndarray, seed: int) -> np.ndarray:
    """Albedo [N, 3] of the paper sheet: one tone with a faint large-scale shading."""
    m = PAPER
    t = _fbm(p + 0.37, seed * 7919 + 31, 2, m.noise_freq)
    return _mix(np.asarray(m.color_a)[None].repeat(len(p), 0), np.asarray(m.color_b)[None].repeat(len(p), 0), t)


def _blur(img: np.ndarray, sigma: float) -> np.ndarray:
    """Separable Gaussian blur of [H, W, C] (edges clamped)."""
    r = max(int(3 * sigma), 1)
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    k /= k.sum()
    for axis in (0, 1):
        pad = [(r, r) if a == axis else (0, 0) for a in range(img.ndim)]
        padded = np.pad(img, pad, mode="edge")
        n = img.shape[axis]
        img = sum(w * np.take(padded, np.arange(i, i + n), axis=axis) for i, w in enumerate(k))
    return img


def _defocus(lin: np.ndarray, far: np.ndarray, sigma: float) -> np.ndarray:
    """Blur the backdrop of lin [H, W, 3] (coverage far [H, W]) on its own, by normalised
    convolution, and put it back behind the sharp foreground."""
    num = _blur(lin * far[..., None], sigma)
    den = _blur(far[..., None], sigma)
    back = num / np.maximum(den, 1e-6)
    return lin * (1.0 - far[..., None]) + back * far[..., None]


def distractor_sphere(i: int, num_views: int) -> Sphere:
    """View i's distractor: a ball rolling across the floor in front of the still life
    while the photographs are taken (like someone walking through a capture): one
    straight path over the orbit, so each view sees it somewhere else. One colour."""
    t = i / max(num_views - 1, 1)
    r = 0.38
    return Sphere((-2.0 + 4.0 * t, -1.55 + 0.5 * math.sin(math.pi * t), r), r, 2)  # material 2: hue 0.74 (violet)


def add_distractor(img: np.ndarray, K: np.ndarray, viewmat: np.ndarray, sp: Sphere, supersample: int = 2
                   ) -> tuple[np.ndarray, np.ndarray]:
    """img [H, W, 3] uint8 with the brightly coloured sphere `sp` drawn where it is in
    front of the scene (hue from its material number, Lambert shading, no shadow), and its mask [H, W]
    uint8: 0 on every pixel it touches, 255 elsewhere."""
    h, w = img.shape[:2]
    ss = supersample
    o, d = pixel_rays(K, viewmat, w, h, ss)
    scene_t, _ = _cast(o, d)
    t = _t_sphere(o, d, sp)
    cover = t < scene_t
    n = (o + d * np.where(cover, t, 0.0)[:, None] - np.asarray(sp.center)) / sp.radius
    shade = AMBIENT + (1.0 - AMBIENT) * np.clip(n @ LIGHT_DIR, 0.0, None)
    colour = _hsv(np.full(len(d), (sp.material * 0.37) % 1.0), np.full(len(d), 0.9), np.ones(len(d)))
    rgb = (colour * (shade * cover)[:, None] * 255.0).reshape(h, ss, w, ss, 3).mean(axis=(1, 3))  # covered samples
    frac = cover.reshape(h, ss, w, ss).mean(axis=(1, 3))
    out = np.clip(np.round(img * (1.0 - frac[..., None]) + rgb), 0, 255)  # the scene's samples replaced where covered
    return out.astype(np.uint8), np.where(frac > 0, 0, 255).astype(np.uint8)


# ---------------------------------------------------------------------------
# Output
# ---------------------------------------------------------------------------


def _atomic_write(path: Path, data: bytes) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, 0o644)  # mkstemp makes 0600 files
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def render_scene(
    out_dir: str | os.PathLike[str],
    *,
    num_views: int = 28,
    width: int = 320,
    height: int = 240,
    seed: int = 0,
    arc_degrees: float | None = None,
    jpeg_quality: int = 92,
    kind: str = "still-life",
    distractor: bool = False,
) -> Path:
    """Render the scene into `out_dir`: images/NNN.jpg and ground_truth.json. Returns out_dir.

    Deterministic: the same arguments give the same bytes. `seed` changes the
    textures only; the geometry and the cameras depend on the sizes and views.
    `arc_degrees` None: 270 degrees, or 10 degrees per step when there are fewer
    than 28 views (so that small test scenes still register in SfM). `kind` "object":
    the objects on plain paper before a defocused backdrop (render_view).
    `distractor`: views whose number is not a multiple of 4 show a rolling ball
    (distractor_sphere, add_distractor), and every view gets a mask in masks/.
    """
    import cv2  # only to encode JPEGs

    out = Path(out_dir)
    images = out / "images"
    images.mkdir(parents=True, exist_ok=True)
    if arc_degrees is None:
        arc_degrees = arc_for_views(num_views)
    cams = []
    moved: list[str] = []
    for i, (K, viewmat) in enumerate(orbit_cameras(num_views, width, height, arc_degrees)):
        name = f"{i:03d}.jpg"
        img = render_view(K, viewmat, width, height, seed, kind=kind)
        if distractor:
            mask = np.full((height, width), 255, np.uint8)
            if i % 4 != 0:
                img, mask = add_distractor(img, K, viewmat, distractor_sphere(i, num_views))
                if (mask == 0).any():
                    moved.append(name)
            (out / "masks").mkdir(exist_ok=True)
            ok, mbuf = cv2.imencode(".png", mask)
            _atomic_write(out / "masks" / f"{name}.png", mbuf.tobytes())
        ok, buf = cv2.imencode(".jpg", img[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
        if not ok:
            raise RuntimeError(f"OpenCV could not encode {name}")
        _atomic_write(images / name, buf.tobytes())
        cams.append({"name": name, "width": width, "height": height, "K": K.tolist(), "viewmat": viewmat.tolist()})
    gt = {
        "frame": "opencv",
        "source": "splatcli sample_data/make_scene.py",
        "seed": seed,
        **({"kind": kind} if kind != "still-life" else {}),
        "arc_degrees": arc_degrees,
        "world_up": [0.0, 0.0, 1.0],
        "look_at": LOOK_AT.tolist(),
        "cameras": cams,
    }
    if distractor:
        gt["distractor_views"] = moved
    _atomic_write(out / "ground_truth.json", (json.dumps(gt, indent=1) + "\n").encode())
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "scene"), help="output directory")
    ap.add_argument("--views", type=int, default=28, help="number of views along the orbit")
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--seed", type=int, default=0, help="texture seed")
    ap.add_argument("--kind", choices=("still-life", "object"), default="still-life",
                    help="object: the objects on plain paper before a backdrop out of focus (a hand-held object capture)")
    ap.add_argument("--distractor", action="store_true",
                    help="a ball rolling through the scene in views not numbered a multiple of 4, "
                         "with masks in out/masks/NNN.jpg.png")
    args = ap.parse_args(argv)
    out = render_scene(args.out, num_views=args.views, width=args.width, height=args.height, seed=args.seed,
                       kind=args.kind, distractor=args.distractor)
    print(f"wrote {args.views} views to {out}")


if __name__ == "__main__":
    main()
