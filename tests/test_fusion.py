"""Keypoint fusion: a weighted fit of the tag's homography to the network's points and stage 1's corners."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from shared.model.net import SplitKeypointNet
from shared.model.weights import WeightsError, load_keypoint_fusion, save_weights, write_keypoint_fusion
from shared.vision.fusion import KeypointFusion, edge_width_px, fuse_lattice, roi_zoom
from shared.vision.geometry import CORNER_KEYPOINTS, GeometryError, apply_homography

# A tilted tag: unit lattice -> image.
H_TRUE = np.array([[180.0, 25.0, 400.0], [-12.0, 150.0, 220.0], [0.0004, -0.0003, 1.0]])
UNIT = np.array([[x, y] for y in (0, 1 / 3, 2 / 3, 1) for x in (0, 1 / 3, 2 / 3, 1)])
TRUE_PX = apply_homography(H_TRUE, UNIT)


def test_exact_points_are_returned_unchanged() -> None:
    fused = fuse_lattice(TRUE_PX, 0.2, TRUE_PX[list(CORNER_KEYPOINTS)], 0.1)
    np.testing.assert_allclose(fused.keypoints_px, TRUE_PX, atol=1e-7)
    assert fused.residual_sigmas < 1e-6


def test_weights_decide_which_estimate_wins() -> None:
    rng = np.random.default_rng(3)
    noisy_net = TRUE_PX + rng.normal(0, 1.0, TRUE_PX.shape)  # a poor network
    shifted_corners = TRUE_PX[list(CORNER_KEYPOINTS)] + 0.05  # sharp corners, 0.07 px off
    trust_corners = fuse_lattice(noisy_net, 1.0, shifted_corners, 0.01).keypoints_px
    assert np.abs(trust_corners - TRUE_PX).max() < 0.12
    trust_net = fuse_lattice(noisy_net, 0.01, shifted_corners, 10.0).keypoints_px
    # The fit to the net alone still projects its noise onto a plane: smaller than the raw noise.
    raw = np.linalg.norm(noisy_net - TRUE_PX, axis=1).mean()
    assert np.linalg.norm(trust_net - TRUE_PX, axis=1).mean() < raw


def test_plane_constraint_averages_independent_noise() -> None:
    rng = np.random.default_rng(0)
    errs_raw, errs_fit = [], []
    for _ in range(200):
        noisy = TRUE_PX + rng.normal(0, 0.3, TRUE_PX.shape)
        errs_raw.append(np.linalg.norm(noisy - TRUE_PX, axis=1).mean())
        errs_fit.append(np.linalg.norm(fuse_lattice(noisy, 0.3).keypoints_px - TRUE_PX, axis=1).mean())
    assert np.mean(errs_fit) < 0.8 * np.mean(errs_raw)


def test_bad_input_is_a_geometry_error() -> None:
    with pytest.raises(GeometryError):
        fuse_lattice(np.full((16, 2), np.nan), 0.2)
    with pytest.raises(GeometryError):
        fuse_lattice(TRUE_PX, 0.0)


def test_roi_zoom_of_a_scaled_warp() -> None:
    assert roi_zoom(np.diag([0.5, 0.5, 1.0])) == pytest.approx(0.5)
    assert roi_zoom(np.array([[2.0, 0, 10], [0, 2.0, -4], [0, 0, 1]])) == pytest.approx(2.0)


def test_settings_are_bounded() -> None:
    with pytest.raises(ValidationError):
        KeypointFusion(keypoint_sigma_roi_px=0.0, corner_sigma_px=0.1)
    with pytest.raises(ValidationError):
        KeypointFusion(keypoint_sigma_roi_px=0.3, corner_sigma_px=float("inf"))


def test_calibration_round_trips_through_the_weights_folder(tmp_path: Path) -> None:
    save_weights(SplitKeypointNet(roi_margin=0.2), tmp_path)
    assert load_keypoint_fusion(tmp_path) is None  # never calibrated: the network's points as they are
    fusion = KeypointFusion(keypoint_sigma_roi_px=0.31, corner_sigma_px=0.12, calibrated_on="test")
    write_keypoint_fusion(tmp_path, fusion)
    assert load_keypoint_fusion(tmp_path) == fusion
    config = json.loads((tmp_path / "config.json").read_text())
    config["keypoint_fusion"]["corner_sigma_px"] = -1
    (tmp_path / "config.json").write_text(json.dumps(config))
    with pytest.raises(WeightsError, match="keypoint_fusion"):
        load_keypoint_fusion(tmp_path)


def _square_roi(blur_sigma: float, contrast: float = 170.0) -> np.ndarray:
    import cv2

    roi = np.full((256, 256), 200.0, np.float32)
    roi[51:205, 51:205] = 200.0 - contrast  # the black square where stage 1's quad puts it (margin 0.2)
    if blur_sigma > 0:
        roi = np.asarray(cv2.GaussianBlur(roi, (0, 0), blur_sigma), np.float32)
    return np.clip(roi, 0, 255).astype(np.uint8)


def test_edge_width_grows_with_blur_and_scales_to_the_image() -> None:
    sharp = edge_width_px(_square_roi(0.0), np.eye(3))
    assert sharp is not None and 0.8 <= sharp <= 1.2
    measured = [edge_width_px(_square_roi(s), np.eye(3)) for s in (1.0, 2.0, 4.0)]
    widths = [w for w in measured if w is not None]
    assert len(widths) == 3 and widths == sorted(widths)
    # A Gaussian edge: (levels difference) / (steepest gradient) = sqrt(2 pi) sigma.
    assert widths[1] == pytest.approx(np.sqrt(2 * np.pi) * 2.0, rel=0.1)
    half = edge_width_px(_square_roi(2.0), np.diag([0.5, 0.5, 1.0]))  # ROI upsampled 2x from the image
    assert half is not None and half == pytest.approx(widths[1] / 2, rel=1e-6)
    assert edge_width_px(np.full((256, 256), 128, np.uint8), np.eye(3)) is None  # no edge to measure


def test_sigmas_grow_with_the_width() -> None:
    f = KeypointFusion(
        keypoint_sigma_roi_px=0.3, keypoint_sigma_per_blur=0.05, corner_sigma_px=0.1, corner_sigma_per_blur=0.1
    )
    net_sharp, corner_sharp = f.sigmas_px(np.eye(3), 1.0)
    net_blur, corner_blur = f.sigmas_px(np.eye(3), 8.0)
    assert corner_sharp < net_sharp and corner_blur > net_blur  # the corners win when sharp, the net when blurred
    assert f.sigmas_px(np.eye(3), None) == f.sigmas_px(np.eye(3), f.nominal_width_px)
