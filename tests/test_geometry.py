"""Geometry conventions proven against exact renders: orientation, detector bias, ROI round trip."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pupil_apriltags
import pytest

from shared.datasets.synth import pose_facing
from shared.vision.camera import CameraIntrinsics
from shared.vision.detector import CORNER_OFFSET_PX, DetectorSettings, TagDetector, destroy_detector
from shared.vision.geometry import (
    CORNER_KEYPOINTS,
    GeometryError,
    apply_homography,
    camera_from_yaml,
    camera_to_yaml,
    check_image,
    check_quad,
    corners_in_tag,
    default_camera,
    image_to_roi_homography,
    lattice_in_tag,
    make_pose,
    normalise_roi,
    project,
    roi_square,
    warp_roi,
)
from shared.vision.tags import render_tag, tag_cells, to_uint8

CAM = default_camera()


def _render(pose: np.ndarray, tag_id: int, size: float) -> np.ndarray:
    canvas = np.full((CAM.height, CAM.width), 0.5, np.float32)
    h = CAM.matrix() @ np.column_stack([pose[:3, 0], pose[:3, 1], pose[:3, 3]])
    render_tag(canvas, tag_id=tag_id, tag_size_m=size, tag_plane_to_image=h)
    return to_uint8(canvas)


def _random_poses(n: int, seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        centre = np.array([rng.uniform(300, 980), rng.uniform(200, 520)])
        out.append(
            pose_facing(
                CAM,
                centre,
                rng.uniform(0.8, 2.0),
                math.radians(rng.uniform(0, 50)),
                rng.uniform(0, 2 * np.pi),
                rng.uniform(0, 2 * np.pi),
            )
        )
    return out


def test_canonical_orientation_matches_apriltag3_pose_frame() -> None:
    """A tag rendered upright in our frame gives AprilTag 3's pose R = I: same tag frame."""
    pose = make_pose(np.eye(3), [0.05, -0.03, 1.2])
    img = _render(pose, 42, 0.2)
    det = pupil_apriltags.Detector(families="tag36h11", quad_decimate=1.0)
    (r,) = det.detect(img, estimate_tag_pose=True, camera_params=(CAM.fx, CAM.fy, CAM.cx, CAM.cy), tag_size=0.2)
    destroy_detector(det)
    assert r.tag_id == 42
    np.testing.assert_allclose(r.pose_R, np.eye(3), atol=0.02)
    np.testing.assert_allclose(r.pose_t.ravel(), pose[:3, 3], atol=0.01)


def test_tag_cells_have_black_border_and_white_quiet_zone() -> None:
    cells = tag_cells(0)
    assert cells.shape == (10, 10)
    assert cells[0].all() and cells[-1].all() and cells[:, 0].all() and cells[:, -1].all()
    assert not cells[1, 1:-1].any() and not cells[-2, 1:-1].any()


def test_detector_corners_match_projection_after_measured_bias() -> None:
    """On noise-free renders: raw pupil corners sit ~+0.5 px off; corrected mean error < 0.3 px."""
    raw = pupil_apriltags.Detector(families="tag36h11", quad_decimate=1.0)
    ours = TagDetector(DetectorSettings(quad_decimate=1.0))
    raw_res, errs = [], []
    for i, pose in enumerate(_random_poses(12, seed=5)):
        img = _render(pose, 100 + i, 0.16)
        gt = project(CAM, pose, corners_in_tag(0.16))
        (r,) = raw.detect(img)
        raw_res.append(np.asarray(r.corners)[[3, 2, 1, 0]] - gt)
        (d,) = ours.detect(img)
        assert d.tag_id == 100 + i
        errs.append(d.corners_px - gt)
    destroy_detector(raw)  # upstream __del__ frees in the wrong order; this makes it a no-op
    bias = np.concatenate(raw_res).mean(axis=0)
    print(f"measured pupil-apriltags corner bias (x, y) = {bias[0]:+.3f}, {bias[1]:+.3f} px")
    np.testing.assert_allclose(bias, [CORNER_OFFSET_PX, CORNER_OFFSET_PX], atol=0.1)
    err = np.linalg.norm(np.concatenate(errs), axis=1)
    print(f"corrected corner error: mean {err.mean():.3f} px, max {err.max():.3f} px")
    assert err.mean() < 0.3


def test_roi_round_trip_is_exact() -> None:
    rng = np.random.default_rng(0)
    pose = _random_poses(1, seed=1)[0]
    quad = project(CAM, pose, corners_in_tag(0.2))
    h = image_to_roi_homography(quad)
    np.testing.assert_allclose(apply_homography(h, quad), roi_square(), atol=1e-9)
    pts_roi = rng.uniform(-10, 266, (100, 2))
    back = apply_homography(h, apply_homography(np.linalg.inv(h), pts_roi))
    assert np.abs(back - pts_roi).max() < 1e-6


def test_lattice_layout() -> None:
    lat = lattice_in_tag(0.3)
    np.testing.assert_allclose(
        lat[list(CORNER_KEYPOINTS), :2], [[-0.15, -0.15], [0.15, -0.15], [0.15, 0.15], [-0.15, 0.15]]
    )
    np.testing.assert_allclose(lat[1, :2], [-0.05, -0.15])  # row-major, x first
    np.testing.assert_allclose(lat[4, :2], [-0.15, -0.05])


def test_warped_roi_puts_black_square_where_the_keypoints_say() -> None:
    pose = make_pose(np.eye(3), [0.0, 0.0, 1.0])
    img = _render(pose, 7, 0.2)
    quad = project(CAM, pose, corners_in_tag(0.2))
    h = image_to_roi_homography(quad)
    roi = warp_roi(img, h)
    kp = normalise_roi(apply_homography(h, project(CAM, pose, lattice_in_tag(0.2))))
    np.testing.assert_allclose(kp[0], [0.2, 0.2], atol=1e-9)
    np.testing.assert_allclose(kp[15], [0.8, 0.8], atol=1e-9)
    # Just inside the corner keypoint the square is black; just outside it is the white border.
    assert roi[int(0.2 * 256) + 3, int(0.2 * 256) + 3] < 60
    assert roi[int(0.2 * 256) - 6, int(0.2 * 256) - 6] > 180


def test_camera_yaml_round_trip_and_errors(tmp_path: Path) -> None:
    path = tmp_path / "cam.yaml"
    path.write_text(camera_to_yaml(CAM))
    assert camera_from_yaml(path) == CAM
    path.write_text("image_width: 640\ncamera_matrix: {data: [1, 0, 1, 0, 1, 1, 0, 0, 1]}\n")
    with pytest.raises(GeometryError, match=r"missing fields \['image_height'\]"):
        camera_from_yaml(path)
    path.write_text("image_width: 640\nimage_height: 480\ncamera_matrix: {data: [1, 2, 3]}\n")
    with pytest.raises(GeometryError, match="9 numbers"):
        camera_from_yaml(path)
    with pytest.raises(GeometryError, match="cannot read"):
        camera_from_yaml(tmp_path / "absent.yaml")


_K = "camera_matrix: {data: [905, 0, 652.3, 0, 898, 391.7, 0, 0, 1]}\n"


def _camera_file(tmp_path: Path, model: str, coeffs: list[float], k: str = _K) -> Path:
    path = tmp_path / "cam.yaml"
    path.write_text(
        f"image_width: 1280\nimage_height: 800\n{k}distortion_model: {model}\n"
        f"distortion_coefficients: {{data: {coeffs}}}\n"
    )
    return path


def test_camera_file_distortion_models(tmp_path: Path) -> None:
    """What ROS calibrators write is read as OpenCV's model; what would silently mislead is refused."""
    eight = [-0.28, 0.08, 1e-3, -5e-4, 0.01, 0.002, 0.003, 0.004]
    rational = camera_from_yaml(_camera_file(tmp_path, "rational_polynomial", eight))
    assert (rational.distortion_model, rational.distortion) == ("plumb_bob", eight)
    np.testing.assert_array_equal(rational.dist_coeffs(), eight)
    assert camera_from_yaml(_camera_file(tmp_path, "plumb_bob", eight[:5])).distortion == eight[:5]
    # ROS writes plumb_bob with zeros for a rectified camera; none with zeros is the same camera.
    assert camera_from_yaml(_camera_file(tmp_path, "none", [0.0] * 5)).distortion == []
    with pytest.raises(GeometryError, match="none with non-zero coefficients"):
        camera_from_yaml(_camera_file(tmp_path, "none", eight[:5]))
    with pytest.raises(GeometryError, match=r"rational_polynomial has 5 coefficients, 8 expected"):
        camera_from_yaml(_camera_file(tmp_path, "rational_polynomial", eight[:5]))
    with pytest.raises(GeometryError, match=r"plumb_bob has 3 coefficients; OpenCV takes \(4, 5, 8, 12, 14\)"):
        camera_from_yaml(_camera_file(tmp_path, "plumb_bob", eight[:3]))
    with pytest.raises(GeometryError, match=r"fisheye lens.*rectify the images first"):
        camera_from_yaml(_camera_file(tmp_path, "equidistant", eight[:4]))
    metres = "camera_matrix: {data: [0.905, 0, 0.65, 0, 0.898, 0.39, 0, 0, 1]}\n"
    with pytest.raises(GeometryError, match="camera_matrix is in pixels"):
        camera_from_yaml(_camera_file(tmp_path, "plumb_bob", eight[:5], metres))
    with pytest.raises(GeometryError, match="must be numbers"):
        camera_from_yaml(_camera_file(tmp_path, "plumb_bob", ["a", 1, 2, 3]))  # type: ignore[list-item]


def test_intrinsics_refuse_coefficients_under_none() -> None:
    """The wire type too: 'none' with coefficients would be undistorted by some readers and not others."""
    fields = CAM.model_dump() | {"distortion_model": "none"}
    with pytest.raises(ValueError, match="'none' with non-zero coefficients"):
        CameraIntrinsics(**fields | {"distortion": [0.1, 0.0, 0.0, 0.0]})
    assert CameraIntrinsics(**fields | {"distortion": [0.0] * 4}).distortion == [0.0] * 4


@pytest.mark.parametrize(
    ("quad", "match"),
    [
        (np.zeros((4, 2)), "degenerate"),
        (np.array([[0, 0], [10, 0], [10, 10], [np.nan, 10]]), "non-finite"),
        (np.array([[0, 0], [10, 0], [0, 10], [10, 10]]), "convex"),
        (np.array([[0, 0], [0, 10], [10, 10], [10, 0]]), "clockwise"),
        (np.zeros((3, 2)), "shape"),
    ],
)
def test_bad_quads(quad: np.ndarray, match: str) -> None:
    with pytest.raises(GeometryError, match=match):
        check_quad(quad)


@pytest.mark.parametrize(
    ("image", "match"),
    [
        (np.zeros((20, 20), np.float32), "uint8"),
        (np.zeros((20, 20, 3), np.uint8), "2-D"),
        (np.zeros((4, 4), np.uint8), "at least 8x8"),
        ([[0]], "numpy array"),
    ],
)
def test_bad_images(image: object, match: str) -> None:
    with pytest.raises(GeometryError, match=match):
        check_image(image)
    with pytest.raises(GeometryError, match=match):
        TagDetector().detect(image)  # type: ignore[arg-type]


def test_nearest_texture_sampling_gives_exact_area_coverage() -> None:
    """A fronto-parallel tag whose black square's left edge sits at x = 100.3 (pixel i covers
    [i - 0.5, i + 0.5]): column 100 is 20 % black, to within the 1/8-pixel supersampling."""
    size_m, px_per_m = 0.16, 1000.0  # 20 px per cell
    left_px, top_px = 100.3, 60.0  # the black square's top-left corner in the image
    h = np.array(
        [[px_per_m, 0, left_px + size_m / 2 * px_per_m], [0, px_per_m, top_px + size_m / 2 * px_per_m], [0, 0, 1]]
    )
    canvas = np.ones((260, 300), np.float32)
    render_tag(
        canvas,
        tag_id=0,
        tag_size_m=size_m,
        tag_plane_to_image=h,
        supersample=8,
        albedo=(0.0, 1.0),
        texture_sampling="nearest",
    )
    # Rows inside the black border (its first cell is black all along the left edge).
    column = canvas[70:210, 100]
    np.testing.assert_allclose(column, 0.8, atol=1 / 16)
    assert (canvas[70:210, 99] == 1.0).all() and (canvas[70:210, 101:118] == 0.0).all()
