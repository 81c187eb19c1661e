"""Compare two sets of camera poses after a similarity alignment.

SfM recovers poses up to a similarity (scale, rotation, translation), so poses
are compared with ground truth only after the best such transform is found.
The alignment is Umeyama's closed-form least squares on the camera centres.

A helper for the tests, which bench/process.py borrows; not part of the installed package.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from splatcli.camera import Camera, scene_extent


@dataclass(frozen=True)
class Sim3:
    """x_target = scale * R @ x_source + t."""

    scale: float
    R: np.ndarray  # [3, 3]
    t: np.ndarray  # [3]

    def apply(self, x: np.ndarray) -> np.ndarray:  # [N, 3] -> [N, 3]
        return self.scale * x @ self.R.T + self.t


@dataclass(frozen=True)
class PoseErrors:
    """Errors of aligned poses against the reference, per matched camera."""

    names: list[str]
    rotation_deg: np.ndarray  # [N] angle of R_est^T R_ref, degrees
    center_error: np.ndarray  # [N] camera-centre distance, reference world units
    extent: float  # the reference scene's extent (camera.scene_extent: 1.1 x max centre distance from their mean)

    @property
    def max_rotation_deg(self) -> float:
        return float(self.rotation_deg.max())

    @property
    def max_center_error_rel(self) -> float:
        """Largest centre error as a fraction of the scene's extent."""
        return float(self.center_error.max() / self.extent)


def umeyama(src: np.ndarray, dst: np.ndarray) -> Sim3:
    """The similarity minimising sum |dst - (s R src + t)|^2.

    src, dst: [N, 3] corresponding points, N >= 3 and not collinear.
    """
    src = np.asarray(src, np.float64)
    dst = np.asarray(dst, np.float64)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    var_s = (xs**2).sum() / len(src)
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:  # keep a proper rotation, not a reflection
        S[2, 2] = -1
    R = U @ S @ Vt
    scale = float(np.trace(np.diag(D) @ S) / max(var_s, 1e-300))
    t = mu_d - scale * R @ mu_s
    return Sim3(scale=scale, R=R, t=t)


def rotation_angle(Q: np.ndarray) -> float:
    """Angle of rotation Q [3, 3], radians. atan2 keeps precision near 0, where
    arccos of the trace loses half the digits."""
    sin = 0.5 * np.linalg.norm([Q[2, 1] - Q[1, 2], Q[0, 2] - Q[2, 0], Q[1, 0] - Q[0, 1]])
    cos = 0.5 * (np.trace(Q) - 1.0)
    return float(np.arctan2(sin, cos))


def compare_poses(estimated: list[Camera], reference: list[Camera]) -> PoseErrors:
    """Align `estimated` to `reference` on the cameras both have (by name) and
    measure rotation and centre errors in the reference frame."""
    ref = {c.name: c for c in reference}
    pairs = [(c, ref[c.name]) for c in estimated if c.name in ref]
    if len(pairs) < 3:
        raise ValueError(f"need at least 3 cameras in common to align, got {len(pairs)}")
    est_c = np.stack([e.center for e, _ in pairs])
    ref_c = np.stack([r.center for _, r in pairs])
    sim = umeyama(est_c, ref_c)
    aligned = sim.apply(est_c)
    center_err = np.linalg.norm(aligned - ref_c, axis=1)
    rot_err = []
    for e, r in pairs:
        # World rotation of the estimated camera after alignment: R_cw_est @ R^T.
        R_est = e.viewmat[:3, :3] @ sim.R.T
        R_ref = r.viewmat[:3, :3]
        rot_err.append(np.degrees(rotation_angle(R_est.T @ R_ref)))
    _, extent = scene_extent([r for _, r in pairs])
    return PoseErrors(
        names=[e.name for e, _ in pairs],
        rotation_deg=np.asarray(rot_err),
        center_error=center_err,
        extent=max(extent, 1e-12),
    )
