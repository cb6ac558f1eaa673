"""The synthetic data set (paper section IV-A2): planar tags under random 6-DoF poses.

Per sample (deterministic from (seed, index)): a random tag36h11 id and size, a distance
(log-uniform) and a tilt (uniform) sampled independently, a random in-plane rotation and image
position; the tag is rendered anti-aliased (4x supersampling) over a procedural background,
then lit, blurred (Gaussian or motion), noised, gamma-corrected and JPEG-compressed. The stage-1
detector runs on the rendered image; a sample whose tag it misses is counted as a failure (never
replaced by ground truth). The detected quad is perturbed (DeepTag's stage-2 strategy), warped to
the 256x256 ROI, and the 16 keypoints are labelled by exact projection through the same
homography. Only a window around the tag is materialised; coordinates stay full-image.
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from shared.sim.backgrounds import procedural_background
from shared.vision.camera import CameraIntrinsics
from shared.vision.detector import DetectorSettings, TagDetector
from shared.vision.geometry import (
    ROI_MARGIN,
    Array,
    GeometryError,
    apply_homography,
    check_quad,
    corners_in_tag,
    image_to_roi_homography,
    lattice_in_tag,
    make_pose,
    normalise_roi,
    project,
    tilt_deg,
    warp_roi,
)
from shared.vision.tags import BLACK_CELLS, CELLS, NUM_TAG36H11, render_tag, to_uint8

Image = NDArray[Any]


class SynthSettings(BaseModel):
    """Generator settings; saved into info.json so a data set can be reproduced."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    seed: int = 0
    tag_size_m: tuple[float, float] = (0.10, 0.30)
    distance_m: tuple[float, float] = (0.3, 6.0)
    max_tilt_deg: float = Field(default=70.0, ge=0, lt=89)
    perturb_frac: float = Field(default=0.06, ge=0, le=0.15)  # of the quad's mean side, per corner
    roi_margin: float = ROI_MARGIN
    supersample: int = Field(default=4, ge=1, le=8)
    p_gaussian_blur: float = 0.5
    p_motion_blur: float = 0.25
    p_jpeg: float = 0.5
    max_noise_sigma: float = 0.03
    detector: DetectorSettings = DetectorSettings()


# ----------------------------------------------------------------------------------------------
# Procedural backgrounds and augmentations (all float32 images in [0, 1])
# ----------------------------------------------------------------------------------------------


def _motion_kernel(rng: np.random.Generator) -> NDArray[np.float32]:
    length = int(rng.integers(3, 10))
    k = np.zeros((length, length), np.float32)
    k[length // 2, :] = 1.0
    rot = cv2.getRotationMatrix2D(((length - 1) / 2, (length - 1) / 2), float(rng.uniform(0, 180)), 1.0)
    k = np.asarray(cv2.warpAffine(k, rot, (length, length)), np.float32)
    return k / max(1e-6, float(k.sum()))


def augment(rng: np.random.Generator, img: Image, s: SynthSettings) -> NDArray[np.uint8]:
    """Lighting gradient, brightness/contrast, gamma, blur, noise, JPEG; returns uint8."""
    h, w = img.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    theta = rng.uniform(0, 2 * np.pi)
    grad = 1.0 + rng.uniform(0, 0.6) * ((xx * math.cos(theta) + yy * math.sin(theta)) / max(h, w) - 0.5)
    img = (img * grad * rng.uniform(0.5, 1.3) + rng.uniform(-0.15, 0.15)).astype(np.float32)
    img = (np.clip(img, 0, 1) ** rng.uniform(0.6, 1.6)).astype(np.float32)
    if rng.random() < s.p_gaussian_blur:
        img = cv2.GaussianBlur(img, (0, 0), float(rng.uniform(0.3, 1.5)))
    if rng.random() < s.p_motion_blur:
        img = cv2.filter2D(img, -1, _motion_kernel(rng), borderType=cv2.BORDER_REFLECT)
    noisy = img + rng.normal(0, rng.uniform(0, s.max_noise_sigma), img.shape).astype(np.float32)
    out = to_uint8(np.clip(noisy, 0, 1).astype(np.float32))
    if rng.random() < s.p_jpeg:
        ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(30, 95))])
        assert ok
        out = np.asarray(cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE), dtype=np.uint8)
    return out


# ----------------------------------------------------------------------------------------------
# Poses
# ----------------------------------------------------------------------------------------------


def _axis_angle(axis: Array, angle: float) -> Array:
    rvec = np.asarray(axis, np.float64) / np.linalg.norm(axis) * angle
    r, _ = cv2.Rodrigues(rvec)
    return np.asarray(r, np.float64)


def pose_facing(
    camera: CameraIntrinsics, centre_px: Array, distance_m: float, tilt: float, azimuth: float, roll: float
) -> Array:
    """camera_from_tag with the tag centre on the ray through `centre_px`, `distance_m` away,
    its normal tilted by `tilt` rad from the ray (about an in-plane axis at `azimuth`), and rolled."""
    ray = np.linalg.solve(camera.matrix(), np.array([centre_px[0], centre_px[1], 1.0]))
    z = ray / np.linalg.norm(ray)  # tag z (into the tag) looks away from the camera
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    facing = np.column_stack([x, y, z])
    axis = np.array([math.cos(azimuth), math.sin(azimuth), 0.0])
    rot = facing @ _axis_angle(axis, tilt) @ _axis_angle(np.array([0.0, 0.0, 1.0]), roll)
    return make_pose(rot, z * distance_m)


def _white_border_in_tag(tag_size_m: float) -> Array:
    return corners_in_tag(tag_size_m * CELLS / BLACK_CELLS)


# ----------------------------------------------------------------------------------------------
# One sample
# ----------------------------------------------------------------------------------------------


def sample_pose(rng: np.random.Generator, camera: CameraIntrinsics, s: SynthSettings) -> tuple[Array, float]:
    """(camera_from_tag, tag size) with the tag and its white border in view."""
    for _ in range(200):
        size = float(rng.uniform(*s.tag_size_m))
        dist = float(math.exp(rng.uniform(math.log(s.distance_m[0]), math.log(s.distance_m[1]))))
        tilt = float(math.radians(rng.uniform(0.0, s.max_tilt_deg)))
        centre = np.array([rng.uniform(0, camera.width - 1), rng.uniform(0, camera.height - 1)])
        pose = pose_facing(camera, centre, dist, tilt, rng.uniform(0, 2 * np.pi), rng.uniform(0, 2 * np.pi))
        border = (pose[:3, :3] @ _white_border_in_tag(size).T).T + pose[:3, 3]
        if (border[:, 2] < 0.05).any():
            continue
        px = project(camera, pose, _white_border_in_tag(size))
        if (px >= 2).all() and (px[:, 0] <= camera.width - 3).all() and (px[:, 1] <= camera.height - 3).all():
            return pose, size
    raise RuntimeError("could not place a visible tag in 200 tries; check the distance range")


def perturb_quad(rng: np.random.Generator, corners_px: Array, frac: float) -> Array:
    """Move each corner by up to `frac` of the quad's mean side per axis (uniform), staying valid."""
    side = float(np.mean(np.linalg.norm(np.roll(corners_px, -1, 0) - corners_px, axis=1)))
    for _ in range(50):
        q = corners_px + rng.uniform(-frac, frac, (4, 2)) * side
        try:
            return check_quad(q)
        except GeometryError:
            continue
    return corners_px


def make_sample(
    index: int, camera: CameraIntrinsics, s: SynthSettings, detector: TagDetector
) -> tuple[dict[str, Any] | None, dict[str, float]]:
    """Generate sample `index`; returns (sample or None if stage 1 missed the tag, its meta)."""
    if camera.distortion_model != "none" and any(camera.distortion):
        raise GeometryError("the synthetic renderer supports undistorted cameras only")
    rng = np.random.default_rng([s.seed, index])
    tag_id = int(rng.integers(0, NUM_TAG36H11))
    pose, size = sample_pose(rng, camera, s)
    meta = {"distance_m": float(np.linalg.norm(pose[:3, 3])), "tilt_deg": tilt_deg(pose)}
    h_plane = camera.matrix() @ np.column_stack([pose[:3, 0], pose[:3, 1], pose[:3, 3]])
    border_px = project(camera, pose, _white_border_in_tag(size))
    span = float(np.ptp(border_px, axis=0).max())
    pad = max(24.0, 0.3 * span)
    x0 = int(max(0, math.floor(border_px[:, 0].min() - pad)))
    y0 = int(max(0, math.floor(border_px[:, 1].min() - pad)))
    x1 = int(min(camera.width, math.ceil(border_px[:, 0].max() + pad) + 1))
    y1 = int(min(camera.height, math.ceil(border_px[:, 1].max() + pad) + 1))
    canvas = procedural_background(rng, y1 - y0, x1 - x0)
    albedo = (float(rng.uniform(0.0, 0.15)), float(rng.uniform(0.8, 1.0)))
    render_tag(
        canvas,
        tag_id=tag_id,
        tag_size_m=size,
        tag_plane_to_image=h_plane,
        origin_px=(x0, y0),
        supersample=s.supersample,
        albedo=albedo,
    )
    window = augment(rng, canvas, s)
    found = [d for d in detector.detect(window) if d.tag_id == tag_id]
    if not found:
        return None, meta
    return label_sample(
        rng,
        window,
        (x0, y0),
        found[0].corners_px,
        camera=camera,
        pose=pose,
        size_m=size,
        tag_id=tag_id,
        index=index,
        perturb_frac=s.perturb_frac,
        roi_margin=s.roi_margin,
    ), meta


def label_sample(
    rng: np.random.Generator,
    window: NDArray[np.uint8],
    origin_px: tuple[int, int],
    corners_in_window: Array,
    *,
    camera: CameraIntrinsics,
    pose: Array,
    size_m: float,
    tag_id: int,
    index: int,
    perturb_frac: float,
    roi_margin: float,
) -> dict[str, Any]:
    """Perturb the detected quad, warp the ROI and label the keypoints by exact projection."""
    x0, y0 = origin_px
    corners = corners_in_window + np.array([x0, y0])
    perturbed = perturb_quad(rng, corners, perturb_frac)
    img_to_roi = image_to_roi_homography(perturbed, roi_margin)
    window_to_roi = img_to_roi @ np.array([[1, 0, x0], [0, 1, y0], [0, 0, 1.0]])
    roi = warp_roi(window, window_to_roi)
    keypoints_px = project(camera, pose, lattice_in_tag(size_m))
    keypoints = normalise_roi(apply_homography(img_to_roi, keypoints_px))
    return {
        "roi": roi,
        "keypoints": keypoints,
        "roi_to_image": np.linalg.inv(img_to_roi),
        "camera_from_tag": pose,
        "corners_px": corners,
        "keypoints_px": keypoints_px,
        "tag_id": tag_id,
        "tag_size_m": size_m,
        "distance_m": float(np.linalg.norm(pose[:3, 3])),
        "tilt_deg": tilt_deg(pose),
        "index": index,
    }


class SynthMaker:
    """Picklable per-process sample maker (owns its own detector)."""

    def __init__(self, camera: CameraIntrinsics, settings: SynthSettings) -> None:
        self.camera = camera
        self.settings = settings
        self._detector: TagDetector | None = None

    def __call__(self, index: int) -> tuple[dict[str, Any] | None, dict[str, float]]:
        if self._detector is None:
            self._detector = TagDetector(self.settings.detector)
        return make_sample(index, self.camera, self.settings, self._detector)
