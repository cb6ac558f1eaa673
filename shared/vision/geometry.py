"""Geometry conventions every accuracy figure stands on (documented in docs/geometry.md).

- Pixels: OpenCV convention, pixel centres at integer coordinates; pixel (u, v) covers
  [u - 0.5, u + 0.5) x [v - 0.5, v + 0.5).
- Camera: pinhole K from a ROS camera_info YAML; default = the paper's onboard camera.
- Tag frame: origin at the tag centre, x right, y down, z into the tag as seen when looking at the
  printed tag (AprilTag 3's pose frame). `camera_from_tag` maps tag points to the camera frame.
- Tag size: side of the outer black square. Canonical orientation: AprilTag's own.
- Keypoints: 4x4 lattice over the black square at fractions {0, 1/3, 2/3, 1}, row-major from the
  tag's top-left; 0, 3, 15, 12 are the TL, TR, BR, BL corners. Corner order everywhere: TL, TR,
  BR, BL.
- ROI: the quad is mapped onto the square [m, 1-m]^2 of a 256x256 patch (m = ROI_MARGIN).
  Normalised ROI coordinates: (u_roi + 0.5) / 256, so [0, 1] spans the patch's full area.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Final

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

from shared.vision.camera import DISTORTION_LENGTHS, CameraIntrinsics

ROI_SIZE: Final[int] = 256
# Margin of the ROI square, as a fraction of the patch side. The black square spans 0.6 of the
# patch (153.6 px): the tag's white border (1/8 of the side, 19 px) and ~32 px of surroundings
# stay visible on every side, and a quad perturbed by up to 8 % of its side keeps every keypoint
# more than 0.15 of the patch from the edge.
ROI_MARGIN: Final[float] = 0.2
LATTICE_FRACTIONS: Final[tuple[float, ...]] = (0.0, 1 / 3, 2 / 3, 1.0)
CORNER_KEYPOINTS: Final[tuple[int, int, int, int]] = (0, 3, 15, 12)  # TL, TR, BR, BL

Array = NDArray[Any]


class GeometryError(ValueError):
    """Bad geometric input: malformed camera file, degenerate quad, wrong image type."""


class CameraFileError(GeometryError):
    """A camera_info file that cannot be read or says no usable camera (a user's file, not maths)."""


# ----------------------------------------------------------------------------------------------
# Camera
# ----------------------------------------------------------------------------------------------


def default_camera() -> CameraIntrinsics:
    """The paper's onboard camera: 1280x720, fx = fy = 1045, principal point at the centre."""
    return CameraIntrinsics(
        width=1280,
        height=720,
        fx=1045.0,
        fy=1045.0,
        cx=639.5,
        cy=359.5,
        distortion_model="none",
        distortion=[],
    )


_CAMERA_FIELDS = ("image_width", "image_height", "camera_matrix")


def camera_from_yaml(path: Path) -> CameraIntrinsics:
    """Read a ROS camera_info YAML (image_width, image_height, camera_matrix, distortion_*)."""
    try:
        doc = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise CameraFileError(f"cannot read camera file {path}: {exc}") from exc
    if not isinstance(doc, dict):
        raise CameraFileError(f"camera file {path}: expected a mapping, got {type(doc).__name__}")
    missing = [f for f in _CAMERA_FIELDS if f not in doc]
    if missing:
        raise CameraFileError(f"camera file {path}: missing fields {missing}")
    data = doc["camera_matrix"].get("data") if isinstance(doc["camera_matrix"], dict) else None
    if not isinstance(data, list) or len(data) != 9:
        raise CameraFileError(f"camera file {path}: camera_matrix.data must list 9 numbers, got {data!r}")
    try:
        k = np.asarray(data, dtype=np.float64).reshape(3, 3)
    except (TypeError, ValueError) as exc:
        raise CameraFileError(f"camera file {path}: camera_matrix.data must be numbers: {exc}") from exc
    model = str(doc.get("distortion_model", "none") or "none")
    coeffs_doc = doc.get("distortion_coefficients", {"data": []}) or {"data": []}
    coeffs = list(coeffs_doc.get("data", []) if isinstance(coeffs_doc, dict) else [])
    coeffs = _distortion_for(path, model, coeffs)
    if k[0, 1] != 0 or k[1, 0] != 0 or k[2, 0] != 0 or k[2, 1] != 0 or k[2, 2] != 1:
        raise CameraFileError(f"camera file {path}: camera_matrix is not a pinhole K: {k.tolist()}")
    if not (k[0, 0] >= 1 and k[1, 1] >= 1):
        raise CameraFileError(
            f"camera file {path}: fx = {k[0, 0]:g}, fy = {k[1, 1]:g}: camera_matrix is in pixels "
            "(a focal length below 1 px looks like metres or a normalised camera matrix)"
        )
    try:
        return CameraIntrinsics(
            width=int(doc["image_width"]),
            height=int(doc["image_height"]),
            fx=float(k[0, 0]),
            fy=float(k[1, 1]),
            cx=float(k[0, 2]),
            cy=float(k[1, 2]),
            distortion_model="plumb_bob" if coeffs else "none",
            distortion=coeffs,
        )
    except (ValueError, TypeError) as exc:
        raise CameraFileError(f"camera file {path}: {exc}") from exc


_FISHEYE_MODELS = ("equidistant", "fisheye", "kannala_brandt")


def _distortion_for(path: Path, model: str, data: list[Any]) -> list[float]:
    """The OpenCV coefficients a camera file's distortion_model and coefficients stand for ([] for none).

    ROS's rational_polynomial (k1 k2 p1 p2 k3 k4 k5 k6) is OpenCV's 8-coefficient model, which the wire
    calls plumb_bob like OpenCV's other lengths; none with non-zero coefficients is refused (a typo
    either way: used or not, someone is surprised)."""
    try:
        coeffs = [float(c) for c in data]
    except (TypeError, ValueError) as exc:
        raise CameraFileError(f"camera file {path}: distortion_coefficients.data must be numbers: {exc}") from exc
    plumb_bob_lengths = tuple(n for n in DISTORTION_LENGTHS if n)
    if model == "none":
        if any(coeffs):
            raise CameraFileError(
                f"camera file {path}: distortion_model none with non-zero coefficients {coeffs}: "
                "say plumb_bob (or rational_polynomial) to use them, or leave them out"
            )
        return []
    if model == "plumb_bob":
        if len(coeffs) not in plumb_bob_lengths:
            raise CameraFileError(
                f"camera file {path}: plumb_bob has {len(coeffs)} coefficients; OpenCV takes {plumb_bob_lengths}"
            )
        return coeffs
    if model == "rational_polynomial":
        if len(coeffs) != 8:
            raise CameraFileError(
                f"camera file {path}: rational_polynomial has {len(coeffs)} coefficients, 8 expected "
                "(k1 k2 p1 p2 k3 k4 k5 k6)"
            )
        return coeffs
    if model in _FISHEYE_MODELS:
        raise CameraFileError(
            f"camera file {path}: distortion_model {model!r} (a fisheye lens) not supported: rectify the "
            "images first (e.g. cv2.fisheye.initUndistortRectifyMap, or ROS image_proc) and give the "
            "rectified camera's camera_info (distortion_model none)"
        )
    raise CameraFileError(
        f"camera file {path}: distortion_model {model!r} not supported "
        "(plumb_bob, rational_polynomial or none; rectify the images first for another model)"
    )


def camera_to_yaml(camera: CameraIntrinsics) -> str:
    """ROS camera_info YAML text for `camera`."""
    doc: dict[str, Any] = {
        "image_width": camera.width,
        "image_height": camera.height,
        "camera_name": "splittag",
        "camera_matrix": {"rows": 3, "cols": 3, "data": camera.matrix().ravel().tolist()},
        "distortion_model": camera.distortion_model,
        "distortion_coefficients": {
            "rows": 1,
            "cols": len(camera.distortion),
            "data": list(camera.distortion),
        },
    }
    return yaml.safe_dump(doc, sort_keys=False)


def project(camera: CameraIntrinsics, camera_from_x: Array, points_in_x: Array) -> Array:
    """Project Nx3 points given in frame x to Nx2 pixels (with the camera's distortion)."""
    rvec, _ = cv2.Rodrigues(camera_from_x[:3, :3])
    out, _ = cv2.projectPoints(
        np.asarray(points_in_x, np.float64).reshape(-1, 1, 3),
        rvec,
        camera_from_x[:3, 3],
        camera.matrix(),
        camera.dist_coeffs(),
    )
    return out.reshape(-1, 2)


# ----------------------------------------------------------------------------------------------
# Tag frame and keypoints
# ----------------------------------------------------------------------------------------------


def lattice_in_tag(tag_size_m: float) -> Array:
    """The 16 keypoints in the tag frame (metres, z = 0), row-major from the top-left."""
    half = tag_size_m / 2
    fr = np.asarray(LATTICE_FRACTIONS)
    xs = -half + tag_size_m * fr
    gx, gy = np.meshgrid(xs, xs)
    return np.stack([gx.ravel(), gy.ravel(), np.zeros(16)], axis=1)


def corners_in_tag(tag_size_m: float) -> Array:
    """The black square's corners TL, TR, BR, BL in the tag frame (metres)."""
    return lattice_in_tag(tag_size_m)[list(CORNER_KEYPOINTS)]


def roi_square(margin: float = ROI_MARGIN) -> Array:
    """Where the quad corners TL, TR, BR, BL land in the ROI, OpenCV pixel coordinates."""
    lo, hi = margin * ROI_SIZE - 0.5, (1 - margin) * ROI_SIZE - 0.5
    return np.array([[lo, lo], [hi, lo], [hi, hi], [lo, hi]])


def normalise_roi(points_roi_px: Array) -> Array:
    """ROI pixel coordinates -> normalised [0, 1] coordinates."""
    return (np.asarray(points_roi_px, np.float64) + 0.5) / ROI_SIZE


def denormalise_roi(points_norm: Array) -> Array:
    """Normalised ROI coordinates -> ROI pixel coordinates."""
    return np.asarray(points_norm, np.float64) * ROI_SIZE - 0.5


# ----------------------------------------------------------------------------------------------
# Quads and homographies
# ----------------------------------------------------------------------------------------------


def check_quad(corners_px: Array, *, min_side_px: float = 4.0) -> Array:
    """Validate a TL, TR, BR, BL quad: finite, convex, clockwise in the image, not tiny."""
    q = np.asarray(corners_px, dtype=np.float64)
    if q.shape != (4, 2):
        raise GeometryError(f"quad must have shape (4, 2), got {q.shape}")
    if not np.isfinite(q).all():
        raise GeometryError(f"quad has non-finite corners: {q.tolist()}")
    edges = np.roll(q, -1, axis=0) - q
    sides = np.linalg.norm(edges, axis=1)
    if sides.min() < min_side_px:
        raise GeometryError(f"degenerate quad: a side is {sides.min():.2f} px (< {min_side_px})")
    nxt = np.roll(edges, -1, axis=0)
    cross = edges[:, 0] * nxt[:, 1] - edges[:, 1] * nxt[:, 0]
    # TL->TR->BR->BL turns clockwise on screen, i.e. positive cross products with y down.
    if not (cross > 0).all():
        raise GeometryError(f"quad is not convex and clockwise (TL, TR, BR, BL): {q.tolist()}")
    return q


def homography(src: Array, dst: Array) -> Array:
    """Exact homography mapping 4 source points onto 4 destination points (float64 solve)."""
    s = np.asarray(src, np.float64).reshape(4, 2)
    d = np.asarray(dst, np.float64).reshape(4, 2)
    a = np.zeros((8, 8))
    b = d.reshape(8)
    for i, ((x, y), (u, v)) in enumerate(zip(s, d, strict=True)):
        a[2 * i] = [x, y, 1, 0, 0, 0, -u * x, -u * y]
        a[2 * i + 1] = [0, 0, 0, x, y, 1, -v * x, -v * y]
    try:
        h = np.append(np.linalg.solve(a, b), 1.0).reshape(3, 3)
    except np.linalg.LinAlgError as exc:
        raise GeometryError(f"degenerate homography from {s.tolist()}") from exc
    if not np.isfinite(h).all() or abs(np.linalg.det(h)) < 1e-12:
        raise GeometryError(f"degenerate homography from {s.tolist()}")
    return h


def apply_homography(h: Array, points: Array) -> Array:
    """Map Nx2 points through a 3x3 homography."""
    p = np.asarray(points, np.float64).reshape(-1, 2)
    ph = np.hstack([p, np.ones((len(p), 1))]) @ np.asarray(h, np.float64).T
    return ph[:, :2] / ph[:, 2:3]


def image_to_roi_homography(corners_px: Array, margin: float = ROI_MARGIN) -> Array:
    """Homography from image pixels to ROI pixels that maps the quad onto the ROI square."""
    return homography(check_quad(corners_px), roi_square(margin))


def check_image(image: Any) -> NDArray[np.uint8]:
    """A 2-D uint8 grayscale image, or GeometryError saying what was received."""
    if not isinstance(image, np.ndarray):
        raise GeometryError(f"image must be a numpy array, got {type(image).__name__}")
    if image.dtype != np.uint8:
        raise GeometryError(f"image must be uint8 grayscale, got dtype {image.dtype}")
    if image.ndim != 2 or min(image.shape) < 8:
        raise GeometryError(f"image must be 2-D (H, W) grayscale of at least 8x8, got shape {image.shape}")
    return image


def warp_roi(image: NDArray[np.uint8], image_to_roi: Array) -> NDArray[np.uint8]:
    """Warp the 256x256 ROI out of a grayscale image.

    When the ROI shrinks the tag by more than 2x, the image is first reduced with pyrDown (exact
    coordinate mapping: output pixel i sits at input pixel 2i), so the bilinear warp never aliases.
    """
    check_image(image)
    h = np.asarray(image_to_roi, np.float64)
    # Local scale of the mapping around the ROI centre: image px per ROI px.
    centre = apply_homography(np.linalg.inv(h), np.array([[ROI_SIZE / 2 - 0.5, ROI_SIZE / 2 - 0.5]]))
    jac_scale = _image_px_per_roi_px(h, centre[0])
    src = image
    while jac_scale > 2.0 and min(src.shape) >= 16:
        src = np.asarray(cv2.pyrDown(src), np.uint8)
        h = h @ np.diag([2.0, 2.0, 1.0])  # level coords x' -> original coords 2x'
        jac_scale /= 2.0
    roi = cv2.warpPerspective(src, h, (ROI_SIZE, ROI_SIZE), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return np.asarray(roi, np.uint8)


def _image_px_per_roi_px(image_to_roi: Array, at_image_px: Array) -> float:
    eps = 0.5
    p = np.array([at_image_px, at_image_px + np.array([eps, 0.0]), at_image_px + np.array([0.0, eps])])
    q = apply_homography(image_to_roi, p)
    du = np.linalg.norm(q[1] - q[0]) / eps
    dv = np.linalg.norm(q[2] - q[0]) / eps
    return float(1.0 / max(1e-9, np.sqrt(du * dv)))


def keypoints_to_image(keypoints_norm: Array, roi_to_image: Array) -> Array:
    """Normalised ROI keypoints -> image pixels through the ROI->image homography."""
    return apply_homography(roi_to_image, denormalise_roi(keypoints_norm))


# ----------------------------------------------------------------------------------------------
# Poses
# ----------------------------------------------------------------------------------------------


def check_rigid(m: Array, what: str, *, max_translation_m: float = 1e3) -> None:
    """Raise GeometryError unless `m` is a finite 4x4 rigid transform (rotation orthonormal and
    right-handed, bottom row 0 0 0 1) with a translation of at most max_translation_m."""
    m = np.asarray(m, np.float64)
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise GeometryError(f"{what} is not a finite 4x4 matrix")
    r = m[:3, :3]
    if not np.allclose(m[3], [0, 0, 0, 1]) or not np.allclose(r @ r.T, np.eye(3), atol=1e-4) or np.linalg.det(r) < 0:
        raise GeometryError(f"{what} is not a rigid transform")
    t = m[:3, 3]
    if np.abs(t).max() > max_translation_m or np.linalg.norm(t) > max_translation_m:  # no overflow on 1e300
        raise GeometryError(f"{what} translates by more than {max_translation_m} m")


def make_pose(rotation: Array, translation: Array | list[float]) -> Array:
    """4x4 rigid transform from a 3x3 rotation and a translation."""
    pose = np.eye(4)
    pose[:3, :3] = rotation
    pose[:3, 3] = np.asarray(translation, np.float64).ravel()
    return pose


def tilt_deg(camera_from_tag: Array) -> float:
    """Angle between the tag's normal and the viewing ray to its centre, degrees."""
    t = camera_from_tag[:3, 3]
    normal = camera_from_tag[:3, 2]  # tag z axis (into the tag) in the camera frame
    c = float(np.dot(normal, t) / max(1e-12, np.linalg.norm(t)))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def clear_of_border(corners_px: NDArray[np.float64], shape: tuple[int, ...], margin_px: float) -> bool:
    """Whether every corner (OpenCV pixels: centres at integers, the image spans -0.5 .. size - 0.5) lies
    at least `margin_px` inside the image's edge."""
    height, width = shape[:2]
    c = np.asarray(corners_px, np.float64)
    lo, hi = c.min(axis=0), c.max(axis=0)
    edge = margin_px - 0.5
    return bool(lo[0] >= edge and lo[1] >= edge and hi[0] <= width - 1 - edge and hi[1] <= height - 1 - edge)
