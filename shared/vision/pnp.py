"""Planar PnP with both IPPE branches, chosen by reprojection error.

A planar target seen small or nearly frontal has two poses that explain its image almost equally
well. IPPE returns both; we keep both (the SLAM ambiguity guard needs the second) and choose the
one with the lower RMS reprojection error over all the points used.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from shared.vision.camera import CameraIntrinsics
from shared.vision.geometry import Array, GeometryError, make_pose


@dataclass(frozen=True)
class PoseCandidates:
    """The chosen camera_from_tag and the other IPPE branch, with RMS reprojection errors (px)."""

    camera_from_tag: Array
    reprojection_error_px: float
    alt_camera_from_tag: Array
    alt_reprojection_error_px: float

    @property
    def ambiguity_ratio(self) -> float:
        """alt error / chosen error: close to 1 means the two branches are hard to tell apart."""
        return self.alt_reprojection_error_px / max(1e-9, self.reprojection_error_px)


def _rms_error(camera: CameraIntrinsics, pose: Array, obj: Array, img: Array) -> float:
    rvec, _ = cv2.Rodrigues(pose[:3, :3])
    proj, _ = cv2.projectPoints(obj.reshape(-1, 1, 3), rvec, pose[:3, 3], camera.matrix(), camera.dist_coeffs())
    return float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=1))))


def solve_planar_pnp(camera: CameraIntrinsics, points_in_tag: Array, points_px: Array) -> PoseCandidates:
    """camera_from_tag from >= 4 coplanar tag points (z = 0) and their image pixels."""
    obj = np.ascontiguousarray(points_in_tag, np.float64).reshape(-1, 3)
    img = np.ascontiguousarray(points_px, np.float64).reshape(-1, 2)
    if len(obj) < 4 or len(obj) != len(img):
        raise GeometryError(f"PnP needs >= 4 matching points, got {len(obj)} and {len(img)}")
    if not np.isfinite(img).all():
        raise GeometryError("PnP image points are not finite")
    n, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, img, camera.matrix(), camera.dist_coeffs(), flags=cv2.SOLVEPNP_IPPE)
    if n < 1:
        raise GeometryError("IPPE found no pose")
    poses = [make_pose(cv2.Rodrigues(r)[0], t) for r, t in zip(rvecs, tvecs, strict=True)]
    errors = [_rms_error(camera, p, obj, img) for p in poses]
    if len(poses) == 1:
        poses.append(poses[0])
        errors.append(errors[0])
    order = np.argsort(errors)
    best, alt = int(order[0]), int(order[1])
    return PoseCandidates(poses[best], errors[best], poses[alt], errors[alt])
