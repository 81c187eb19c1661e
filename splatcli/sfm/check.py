"""Does a model place its cameras where the photos' own pair geometry says they are?

Matching already measured each verified pair of images: its inlier matches and, for all but
planar or purely rotating pairs, its own relative pose (an E or F matrix). A model places the
two cameras. Under that placement each inlier match has an epipolar (Sampson) error, and the
model's relative rotation differs from the pair's own by some angle. A pair *agrees* when its
inliers' median error is under `MAX_ERROR_PX`. The rotation is measured and reported but decides
nothing: a pair's own rotation comes from its E, or its F with the model's intrinsics, and F is
degenerate for a planar scene (40 photos of a church front: pairs with 0.3 px of error, whose own
rotations were 5-37 degrees off the model's).

A correct model disagrees only with false pairs (look-alike views matched wrongly), and those
are weak: few inliers beside each image's best pair. A model with an arc of cameras placed at
the wrong position or scale disagrees with the strongest pairs there are, those between
neighbouring views at the two ends of the arc. So each pair weighs its *strength* (its inliers
over those of the better pair of its weaker image), and the registered images are grouped
greedily, joining the two groups whose pairs agree most on balance, until no two groups agree
more than they disagree. A consistent model is one group; a broken one falls apart at the
broken joins, and the groups name which cameras belong together.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .colmap import Model, VerifiedPair, View, read_verified_pairs

MAX_ERROR_PX = 4.0  # COLMAP's own RANSAC threshold in two-view verification
STRONG = 0.3  # a pair is strong when it has at least this share of its weaker image's best pair's inliers
SHOWN = 12  # images named in the one line


@dataclass(frozen=True)
class PairCheck:
    a: str
    b: str
    inliers: int
    strength: float  # inliers / the best pair's inliers, of the image (a or b) whose best pair is weaker
    error_px: float  # median Sampson error of the inliers under the model's poses
    rotation_deg: float | None  # the model's relative rotation against the pair's own (None: no own pose)

    @property
    def agrees(self) -> bool:
        return self.error_px <= MAX_ERROR_PX

    @property
    def strong(self) -> bool:
        return self.strength >= STRONG


@dataclass
class Consistency:
    """The check of one model: its pairs, and its images grouped by agreement."""

    pairs: list[PairCheck]  # every verified pair of two registered images
    parts: list[list[str]]  # registered images in groups, largest first: one for a consistent model
    seconds: float

    @property
    def strong(self) -> list[PairCheck]:
        return [p for p in self.pairs if p.strong]

    @property
    def share(self) -> float:
        """The share of strong pairs that agree (1 when there are none)."""
        strong = self.strong
        return sum(p.agrees for p in strong) / len(strong) if strong else 1.0

    @property
    def consistent(self) -> bool:
        """No strong pair disagrees across two groups (groups apart on weak evidence alone stay)."""
        return not self.breaks

    @property
    def breaks(self) -> list[PairCheck]:
        """The strong pairs that disagree across two groups, strongest first."""
        part = {n: k for k, names in enumerate(self.parts) for n in names}
        return sorted((p for p in self.strong if not p.agrees and part.get(p.a) != part.get(p.b)),
                      key=lambda p: -p.strength)

    def named(self) -> list[str]:
        """The images outside the largest group; for a consistent model, those of its disagreeing strong pairs."""
        if not self.consistent:
            return sorted(n for part in self.parts[1:] for n in part)
        return sorted({n for p in self.strong if not p.agrees for n in (p.a, p.b)})

    def line(self) -> str:
        strong = self.strong
        head = (f"{round(100 * self.share, 1):g}% of {len(strong):,} strong image pairs agree with the poses "
                f"(median error {np.median([p.error_px for p in strong]) if strong else 0:.2f} px)")
        if self.consistent:
            return head
        sizes = ", ".join(str(len(p)) for p in self.parts)
        out = self.named()
        shown = ", ".join(out[:SHOWN]) + (f" and {len(out) - SHOWN} more" if len(out) > SHOWN else "")
        return (f"{head}; {len(self.breaks)} strong pair(s) disagree where the model joins groups of "
                f"{sizes} images: placed apart from the rest: {shown}")

    def summary(self) -> dict[str, Any]:
        strong = self.strong
        rots = [p.rotation_deg for p in strong if p.rotation_deg is not None]
        return {
            "consistent": self.consistent,
            "line": self.line(),
            "pairs": len(self.pairs),
            "strong_pairs": len(strong),
            "strong_agree": sum(p.agrees for p in strong),
            "share": round(self.share, 4),
            "median_error_px": round(float(np.median([p.error_px for p in strong])), 3) if strong else None,
            "median_rotation_deg": round(float(np.median(rots)), 3) if rots else None,
            "parts": [len(p) for p in self.parts],
            "placed_apart": self.named() if not self.consistent else [],
            "disagreeing": [{"a": p.a, "b": p.b, "inliers": p.inliers, "strength": round(p.strength, 3),
                             "error_px": round(p.error_px, 2),
                             "rotation_deg": None if p.rotation_deg is None else round(p.rotation_deg, 2)}
                            for p in sorted((p for p in strong if not p.agrees), key=lambda p: -p.strength)[:50]],
            "seconds": round(self.seconds, 3),
        }


def check_model(db: Path, model: Model) -> Consistency:
    """Check `model` against the verified pairs of the database it was mapped from."""
    t0 = time.perf_counter()
    pairs, keypoints = read_verified_pairs(db)
    views = model.views()
    rays: dict[str, np.ndarray] = {}  # image -> [n, 2] its keypoints normalised by its camera

    def ray(name: str) -> np.ndarray:
        if name not in rays:
            rays[name] = views[name].normalised(keypoints[name])
        return rays[name]

    posed = [p for p in pairs if p.a in views and p.b in views]
    best: dict[str, int] = {}
    for p in posed:
        for n in (p.a, p.b):
            best[n] = max(best.get(n, 0), len(p.matches))
    checks = [_check_pair(p, views[p.a], views[p.b], ray(p.a), ray(p.b), min(best[p.a], best[p.b]))
              for p in posed]
    parts = group(sorted(views), checks)
    return Consistency(pairs=checks, parts=parts, seconds=time.perf_counter() - t0)


def _check_pair(p: VerifiedPair, va: View, vb: View, ra: np.ndarray, rb: np.ndarray, best: int) -> PairCheck:
    R = vb.pose[:, :3] @ va.pose[:, :3].T  # [3, 3] b_from_a
    t = vb.pose[:, 3] - R @ va.pose[:, 3]
    xa = np.c_[ra[p.matches[:, 0].astype(np.int64)], np.ones(len(p.matches))]  # [M, 3]
    xb = np.c_[rb[p.matches[:, 1].astype(np.int64)], np.ones(len(p.matches))]
    norm = np.linalg.norm(t)
    if norm < 1e-12:  # one centre for both (a pure rotation): the rays themselves must agree
        d = xb[:, :2] - (xa @ R.T)[:, :2] / (xa @ R.T)[:, 2:]
        err = np.linalg.norm(d, axis=1)
    else:
        E = _skew(t / norm) @ R
        Ex, Etx = xa @ E.T, xb @ E  # [M, 3]
        den = Ex[:, 0] ** 2 + Ex[:, 1] ** 2 + Etx[:, 0] ** 2 + Etx[:, 1] ** 2
        err = np.abs(np.sum(xb * Ex, axis=1)) / np.sqrt(np.maximum(den, 1e-30))  # Sampson distance, normalised units
    own = _own_rotation(p, va.K, vb.K)
    rot = None if own is None else min(_angle_deg(R.T @ c) for c in own)
    return PairCheck(p.a, p.b, len(p.matches), len(p.matches) / max(best, 1),
                     float(np.median(err)) * 0.5 * (va.focal + vb.focal), rot)


def _own_rotation(p: VerifiedPair, Ka: np.ndarray, Kb: np.ndarray) -> list[np.ndarray] | None:
    """The two rotations the pair's own E (or F with the model's intrinsics) allows; the other
    two of E's four decompositions are these turned by 180 degrees about the baseline."""
    if p.matrix is None:
        return None
    E = p.matrix if p.kind == "E" else Kb.T @ p.matrix @ Ka
    U, _, Vt = np.linalg.svd(E)
    if np.linalg.det(U) < 0:
        U = -U
    if np.linalg.det(Vt) < 0:
        Vt = -Vt
    W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    return [U @ W @ Vt, U @ W.T @ Vt]


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _angle_deg(Q: np.ndarray) -> float:
    s = 0.5 * np.linalg.norm([Q[2, 1] - Q[1, 2], Q[0, 2] - Q[2, 0], Q[1, 0] - Q[0, 1]])
    return float(np.degrees(np.arctan2(s, 0.5 * (np.trace(Q) - 1.0))))


def group(names: list[str], checks: list[PairCheck]) -> list[list[str]]:
    """`names` in groups: each pair weighs its strength, for (agrees) or against (disagrees)
    its two images belonging together; the two groups with the most weight for on balance
    join, until no two have more for than against. Images without a pair join the largest
    group (nothing says they are misplaced). Largest group first."""
    of = {n: i for i, n in enumerate(names)}
    links: dict[int, dict[int, float]] = {i: {} for i in range(len(names))}
    for c in checks:
        i, j = of[c.a], of[c.b]
        w = c.strength if c.agrees else -c.strength
        links[i][j] = links[i].get(j, 0.0) + w
        links[j][i] = links[j].get(i, 0.0) + w
    members = {i: [i] for i in range(len(names))}
    while True:
        best, pick = 0.0, None
        for i, row in links.items():
            for j, w in row.items():
                if i < j and w > best:
                    best, pick = w, (i, j)
        if pick is None:
            break
        i, j = pick  # j joins i
        members[i] += members.pop(j)
        for k, w in links.pop(j).items():
            del links[k][j]
            if k != i:
                links[i][k] = links[i].get(k, 0.0) + w
                links[k][i] = links[i][k]
        links[i].pop(i, None)
    lone = [m[0] for m in members.values() if len(m) == 1 and not links[m[0]]]
    groups = sorted((m for m in members.values() if not (len(m) == 1 and m[0] in lone)), key=len, reverse=True)
    if not groups:
        return [sorted(names)] if names else []
    groups[0] += lone
    return [sorted(names[i] for i in g) for g in groups]
