"""The independent renderer (bench/tagrender.py): proven against AprilTag 3, deterministic, exact truth."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace

import cv2
import numpy as np
import pupil_apriltags
import pytest

from bench.tagrender import (
    CORNER_INDICES,
    RenderSettings,
    clean_settings,
    render_sample,
)
from shared.vision.detector import destroy_detector

# pupil-apriltags reports corners p0..p3 = BL, BR, TR, TL, with pixel centres at +0.5 against OpenCV's.
APRILTAG_TO_TL_TR_BR_BL = [3, 2, 1, 0]
APRILTAG_OFFSET_PX = 0.5
PROOF_IMAGES = 30
PROOF_SEED = 11


@pytest.fixture(scope="module")
def detector() -> Iterator[pupil_apriltags.Detector]:
    """One full-resolution AprilTag 3 detector for the module, freed in a safe order at teardown.

    pupil-apriltags 1.0.4's own __del__ frees the tag family before the detector (a use-after-free
    that can crash at interpreter exit), so free it here explicitly while everything is alive.
    """
    det = pupil_apriltags.Detector(families="tag36h11", quad_decimate=1.0, refine_edges=True)
    yield det
    destroy_detector(det)
    del det


def test_clean_renders_agree_with_apriltag(detector: pupil_apriltags.Detector) -> None:
    """AprilTag 3 finds every clean tag with the right id; its corners match the truth to < 0.1 px median."""
    settings = clean_settings()  # the full span (40-360 px) and tilt (0-65 deg) ranges
    errors: list[float] = []
    for index in range(PROOF_IMAGES):
        sample = render_sample(index, PROOF_SEED, settings)
        truth = sample.tags[0]
        found = detector.detect(sample.image)
        assert [d.tag_id for d in found] == [truth.tag_id], f"image {index}: {sample.meta}"
        corners = np.asarray(found[0].corners, np.float64)[APRILTAG_TO_TL_TR_BR_BL] - APRILTAG_OFFSET_PX
        errors.extend(np.linalg.norm(corners - truth.corners_px, axis=1).tolist())
    err = np.asarray(errors)
    median, p90 = float(np.median(err)), float(np.percentile(err, 90))
    print(
        f"\nclean renders vs AprilTag 3 ({PROOF_IMAGES} images): corner error median {median:.3f} px, p90 {p90:.3f} px"
    )
    assert median <= 0.1
    assert p90 <= 0.25


def test_frontal_tag_is_apriltag_canonical(detector: pupil_apriltags.Detector) -> None:
    """A tag facing the camera upright: AprilTag 3's own pose is R = I (the bits are not rotated)."""
    settings = clean_settings(tilt_deg=(0.0, 0.0), span_px=(200.0, 200.0))
    for index in range(20):
        sample = render_sample(index, 3, settings)
        r = sample.tags[0].camera_from_tag[:3, :3]
        if abs(np.degrees(np.arctan2(r[1, 0], r[0, 0]))) > 20:
            continue  # look for a sample rolled less than 20 deg
        s = settings
        found = detector.detect(
            sample.image,
            estimate_tag_pose=True,
            camera_params=(s.fx, s.fy, s.cx + APRILTAG_OFFSET_PX, s.cy + APRILTAG_OFFSET_PX),
            tag_size=sample.tags[0].size_m,
        )
        assert len(found) == 1
        rel = np.asarray(found[0].pose_R).T @ r
        angle = np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1, 1)))
        assert angle < 2.0
        return
    pytest.fail("no upright sample among 20")


def test_same_seed_and_index_give_identical_bytes() -> None:
    """Every degradation is drawn from the (seed, index) stream: a re-render is byte-identical."""
    settings = RenderSettings()
    for index in (0, 6, 10):
        a, b = render_sample(index, 5, settings), render_sample(index, 5, settings)
        assert a.image.tobytes() == b.image.tobytes()
        assert a.meta == b.meta
        np.testing.assert_array_equal(a.tags[0].keypoints_px, b.tags[0].keypoints_px)
    assert render_sample(0, 5, settings).image.tobytes() != render_sample(0, 6, settings).image.tobytes()


def test_occluders_keep_the_corners_visible() -> None:
    """An occluder crosses the tag, reports the covered fraction, and leaves the four corners clear."""
    settings = replace(RenderSettings(), p_occluder=1.0, p_motion_blur=0.0)
    with_occluder = 0
    for index in range(8):
        sample = render_sample(index, 21, settings)
        assert sample.image.dtype == np.uint8
        assert sample.image.shape == (settings.height, settings.width)
        if "occluder" not in sample.meta:
            continue
        with_occluder += 1
        assert 0.0 < sample.meta["occluded_fraction"] < 0.6
        assert any(name.startswith("occluder_") for name in sample.meta["applied"])
        polygon = np.asarray(sample.meta["occluder_polygon_px"], np.float32)
        for corner in sample.tags[0].corners_px:
            signed = cv2.pointPolygonTest(polygon, (float(corner[0]), float(corner[1])), measureDist=True)
            assert signed < -1.0, f"image {index}: corner {corner} is {-signed:.1f} px from the occluder"
    assert with_occluder >= 6


def test_truth_is_the_projection_of_the_lattice() -> None:
    """Stored keypoints are the lattice projected with camera_from_tag; corners are lattice 0, 3, 15, 12."""
    settings = RenderSettings()
    k = settings.camera_matrix()
    for index in range(4):
        sample = render_sample(index, 8, settings)
        truth = sample.tags[0]
        pose = truth.camera_from_tag
        np.testing.assert_allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-12)
        assert np.linalg.det(pose[:3, :3]) == pytest.approx(1.0)
        np.testing.assert_array_equal(pose[3], [0, 0, 0, 1])
        h = truth.size_m / 2
        steps = [-h + truth.size_m * f for f in (0.0, 1 / 3, 2 / 3, 1.0)]
        lattice = np.array([[x, y, 0.0] for y in steps for x in steps])
        rvec, _ = cv2.Rodrigues(pose[:3, :3])
        projected, _ = cv2.projectPoints(lattice, rvec, pose[:3, 3], k, None)
        np.testing.assert_allclose(truth.keypoints_px, projected.reshape(-1, 2), atol=1e-9)
        np.testing.assert_array_equal(truth.corners_px, truth.keypoints_px[list(CORNER_INDICES)])
        for key in ("blur_px", "distance_m", "tilt_deg", "occluded_fraction", "applied"):
            assert key in sample.meta
        assert sample.meta["blur_px"] <= settings.max_motion_blur_px + 1e-6
        assert sample.meta["tilt_deg"] <= settings.tilt_deg[1]


def test_axis_scale_reads_a_stretch_along_one_direction() -> None:
    """bench.accuracy's blur-axis metric: a grid stretched 2 % along a direction reads +2 % along it
    and ~0 across it; the renderer's gamma setting is what each image's meta reports."""
    from bench.accuracy import axis_scale_pct

    true = np.stack(np.meshgrid(np.arange(4.0), np.arange(4.0)), axis=-1).reshape(-1, 2) * 30 + 100
    d = np.array([np.cos(0.6), np.sin(0.6)])
    centred = true - true.mean(axis=0)
    pred = true + 0.02 * np.outer(centred @ d, d) + 3.0  # stretched along d, shifted
    assert abs(axis_scale_pct(pred, true, d) - 2.0) < 1e-9
    assert abs(axis_scale_pct(pred, true, np.array([-d[1], d[0]]))) < 1e-9
    srgb = replace(RenderSettings(), gamma=(2.2, 2.2))
    assert render_sample(0, 5, srgb).meta["gamma"] == 2.2


def test_accuracy_bench_refuses_a_bad_gamma_range(capsys: pytest.CaptureFixture[str]) -> None:
    """`bench.accuracy --gamma 0 1` stops before rendering anything, naming the option."""
    from bench import accuracy

    with pytest.raises(SystemExit):
        accuracy.main(["--gamma", "0", "1"])
    assert "--gamma needs 0 < LO <= HI" in capsys.readouterr().err
