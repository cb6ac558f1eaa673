"""One tag's 16 keypoints from every estimate of them: a weighted fit of the tag's homography.

A tag is a plane, so its 16 lattice points are one homography of the canonical lattice (8 degrees of
freedom). The network predicts 16 points with an error that is roughly constant in ROI pixels, so in
image pixels it scales with the ROI's zoom; AprilTag's refined corners have an error roughly
constant in image pixels. `fuse_lattice` fits the homography to both, each point weighted by
1/sigma^2 (Gauss-Newton on the 8 parameters, started from the unweighted least-squares fit), and
returns the lattice the fitted homography predicts: a large tag (ROI downsampled) leans on the
corners, a small or blurred one on the network, and the 16 points are always consistent with a plane.
Both sigmas grow with the image's blur, AprilTag's much faster (its corners come from edges fitted
in the image): `edge_width_px` measures how wide the tag's border edge is (contrast over the steepest
gradient across it, in image pixels) from the ROI, on the robot, and the Features carry it; the
calibrated model is sigma^2 = sigma_0^2 + (slope * width)^2 per estimate. Pure numpy; well under a
millisecond per tag.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from shared.vision.geometry import CORNER_KEYPOINTS, LATTICE_FRACTIONS, Array, GeometryError, roi_square

_UNIT_LATTICE: Array = np.array([[x, y] for y in LATTICE_FRACTIONS for x in LATTICE_FRACTIONS], np.float64)


@dataclass(frozen=True)
class FusedLattice:
    """The fitted lattice (16, 2) in image pixels and the weighted RMS residual of the inputs (in
    sigmas: about 1 when the sigmas are right)."""

    keypoints_px: Array
    residual_sigmas: float


def roi_zoom(roi_to_image: Array, at_roi_px: tuple[float, float] = (127.5, 127.5)) -> float:
    """Image pixels per ROI pixel near `at_roi_px` (the square root of the Jacobian's determinant)."""
    h = np.asarray(roi_to_image, np.float64)
    x, y = at_roi_px
    w = h[2, 0] * x + h[2, 1] * y + h[2, 2]
    u = (h[0, 0] * x + h[0, 1] * y + h[0, 2]) / w
    v = (h[1, 0] * x + h[1, 1] * y + h[1, 2]) / w
    jac = np.array([[h[0, 0] - u * h[2, 0], h[0, 1] - u * h[2, 1]], [h[1, 0] - v * h[2, 0], h[1, 1] - v * h[2, 1]]]) / w
    return float(np.sqrt(abs(np.linalg.det(jac))))


def _project(params: Array, pts: Array) -> tuple[Array, Array]:
    h = np.append(params, 1.0).reshape(3, 3)
    x, y = pts[:, 0], pts[:, 1]
    w = h[2, 0] * x + h[2, 1] * y + 1.0
    u = (h[0, 0] * x + h[0, 1] * y + h[0, 2]) / w
    v = (h[1, 0] * x + h[1, 1] * y + h[1, 2]) / w
    return np.stack([u, v], axis=1), w


def _jacobian(uv: Array, w: Array, pts: Array) -> Array:
    x, y = pts[:, 0], pts[:, 1]
    n = len(pts)
    jac = np.zeros((2 * n, 8))
    jac[0::2, 0], jac[0::2, 1], jac[0::2, 2] = x / w, y / w, 1 / w
    jac[1::2, 3], jac[1::2, 4], jac[1::2, 5] = x / w, y / w, 1 / w
    jac[0::2, 6], jac[0::2, 7] = -uv[:, 0] * x / w, -uv[:, 0] * y / w
    jac[1::2, 6], jac[1::2, 7] = -uv[:, 1] * x / w, -uv[:, 1] * y / w
    return jac


def _dlt(src: Array, dst: Array, weights: Array) -> Array:
    x, y = src[:, 0], src[:, 1]
    u, v = dst[:, 0], dst[:, 1]
    one, zero = np.ones_like(x), np.zeros_like(x)
    wt = np.sqrt(weights)[:, None]
    rows_u = np.stack([x, y, one, zero, zero, zero, -u * x, -u * y, -u], axis=1) * wt
    rows_v = np.stack([zero, zero, zero, x, y, one, -v * x, -v * y, -v], axis=1) * wt
    _, _, vt = np.linalg.svd(np.concatenate([rows_u, rows_v]))
    h = vt[-1]
    if abs(h[8]) < 1e-12:
        raise GeometryError("degenerate homography")
    return np.asarray(h[:8] / h[8], np.float64)


def fuse_lattice(
    keypoints_px: Array,
    keypoint_sigma_px: Array | float,
    corners_px: Array | None = None,
    corner_sigma_px: float = 0.1,
    iterations: int = 6,
) -> FusedLattice:
    """Weighted homography fit of the 16 lattice points (row-major) and, if given, the 4 corners
    TL, TR, BR, BL (the lattice's points 0, 3, 15, 12) with their sigmas in image pixels."""
    kp = np.asarray(keypoints_px, np.float64).reshape(16, 2)
    sig = np.broadcast_to(np.asarray(keypoint_sigma_px, np.float64), (16,))
    src, dst, sigmas = [_UNIT_LATTICE], [kp], [sig]
    if corners_px is not None:
        src.append(_UNIT_LATTICE[list(CORNER_KEYPOINTS)])
        dst.append(np.asarray(corners_px, np.float64).reshape(4, 2))
        sigmas.append(np.full(4, corner_sigma_px))
    s_all, d_all, sg = np.concatenate(src), np.concatenate(dst), np.concatenate(sigmas)
    if not (np.isfinite(d_all).all() and np.isfinite(sg).all() and (sg > 0).all()):
        raise GeometryError("fusion needs finite points and positive sigmas")
    # Condition: image points centred and scaled to unit spread.
    centre = d_all.mean(axis=0)
    scale = float(np.sqrt(((d_all - centre) ** 2).sum(axis=1).mean())) or 1.0
    d_n = (d_all - centre) / scale
    w = 1.0 / (sg / scale) ** 2
    params = _dlt(s_all, d_n, w)
    sw = np.repeat(np.sqrt(w), 2)
    for _ in range(iterations):
        uv, wp = _project(params, s_all)
        r = (uv - d_n).ravel() * sw
        jac = _jacobian(uv, wp, s_all) * sw[:, None]
        step, *_ = np.linalg.lstsq(jac, -r, rcond=None)
        params = params + step
        if float(np.abs(step).max()) < 1e-12:
            break
    uv, _ = _project(params, s_all)
    resid = float(np.sqrt(np.mean(((uv - d_n) ** 2).sum(axis=1) * w)))
    norm = np.array([[scale, 0, centre[0]], [0, scale, centre[1]], [0, 0, 1.0]])
    h = norm @ np.append(params, 1.0).reshape(3, 3)
    fitted, _ = _project((h / h[2, 2]).ravel()[:8], _UNIT_LATTICE)
    return FusedLattice(fitted, resid)


def _edge_profiles(
    n_along: int = 9, half_px: float = 9.0, step_px: float = 0.5
) -> tuple[NDArray[np.float32], NDArray[np.float32], float]:
    """ROI sample points of profiles across the black square's four edges, outside -> inside."""
    lo, hi = roi_square()[0, 0], roi_square()[2, 0]
    offs = np.arange(-half_px, half_px + 1e-9, step_px)
    xs, ys = [], []
    for t in np.linspace(0.2, 0.8, n_along):
        pos = lo + t * (hi - lo)
        along = np.full_like(offs, pos)
        for x, y in ((along, lo + offs), (hi - offs, along), (along, hi - offs), (lo + offs, along)):
            xs.append(x)
            ys.append(y)
    return np.asarray(xs, np.float32), np.asarray(ys, np.float32), step_px


_PROFILES = _edge_profiles()


def edge_width_px(roi: NDArray[np.uint8], roi_to_image: Array) -> float | None:
    """How wide the tag's border edge is in the image, pixels: the median over 36 profiles across
    the black square's edges of (outer - inner level) / steepest gradient, scaled by the ROI's zoom.
    About 1 for a sharp edge; grows with motion blur and defocus. None when the ROI shows no edge
    (no contrast: occluded, saturated). The ROI must be warped from stage 1's quad (as at inference)."""
    xs, ys, step = _PROFILES
    prof = cv2.remap(np.asarray(roi, np.float32), xs, ys, cv2.INTER_LINEAR)
    outer, inner = np.median(prof[:, :5], axis=1), np.median(prof[:, -5:], axis=1)
    contrast = outer - inner
    steepest = np.abs(np.diff(prof, axis=1)).max(axis=1) / step
    ok = (contrast > 10.0) & (steepest > 0)
    if ok.sum() < 6:
        return None
    return float(np.median(contrast[ok] / steepest[ok]) * roi_zoom(roi_to_image))


class KeypointFusion(BaseModel):
    """How much to trust each estimate, calibrated per model (config.json's `keypoint_fusion`).

    The network's per-coordinate sigma is sqrt((keypoint_sigma_roi_px * zoom)^2 + (keypoint_sigma_per_blur
    * width)^2) in image pixels (zoom: image pixels per ROI pixel), AprilTag's corners'
    sqrt(corner_sigma_px^2 + (corner_sigma_per_blur * width)^2); width = `edge_width_px`, or
    `nominal_width_px` when the robot did not measure it.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    keypoint_sigma_roi_px: float = Field(gt=0, le=100)
    keypoint_sigma_per_blur: float = Field(default=0.0, ge=0, le=10)
    corner_sigma_px: float = Field(gt=0, le=100)
    corner_sigma_per_blur: float = Field(default=0.0, ge=0, le=10)
    nominal_width_px: float = Field(default=2.0, gt=0, le=100)
    calibrated_on: str = Field(default="", max_length=500, description="data and command the sigmas come from")

    def sigmas_px(self, roi_to_image: Array, width_px: float | None) -> tuple[float, float]:
        """(network keypoint sigma, stage-1 corner sigma) in image pixels for one tag."""
        w = self.nominal_width_px if width_px is None else width_px
        zoom = roi_zoom(roi_to_image)
        net = float(np.hypot(self.keypoint_sigma_roi_px * zoom, self.keypoint_sigma_per_blur * w))
        corner = float(np.hypot(self.corner_sigma_px, self.corner_sigma_per_blur * w))
        return net, corner

    def apply(
        self, keypoints_px: Array, corners_px: Array, roi_to_image: Array, width_px: float | None = None
    ) -> Array:
        """The fused 16 lattice points in image pixels for one tag."""
        net, corner = self.sigmas_px(roi_to_image, width_px)
        return fuse_lattice(keypoints_px, net, corners_px, corner).keypoints_px
