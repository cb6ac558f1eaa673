"""Planar PnP: exact recovery, both IPPE branches kept, clear errors."""

from __future__ import annotations

import numpy as np
import pytest

from shared.datasets.synth import pose_facing
from shared.vision.geometry import GeometryError, default_camera, lattice_in_tag, project
from shared.vision.metrics import rotation_error_deg
from shared.vision.pnp import solve_planar_pnp

CAM = default_camera()


def test_exact_points_give_exact_pose_and_a_worse_alternative() -> None:
    pose = pose_facing(CAM, np.array([700.0, 300.0]), 1.5, 0.6, 0.3, 1.0)
    pts = project(CAM, pose, lattice_in_tag(0.2))
    cand = solve_planar_pnp(CAM, lattice_in_tag(0.2), pts)
    np.testing.assert_allclose(cand.camera_from_tag, pose, atol=1e-6)
    assert cand.reprojection_error_px < 1e-6
    assert cand.alt_reprojection_error_px > cand.reprojection_error_px
    assert rotation_error_deg(cand.alt_camera_from_tag[:3, :3], pose[:3, :3]) > 1.0


def test_small_frontal_tag_is_ambiguous() -> None:
    pose = pose_facing(CAM, np.array([640.0, 360.0]), 6.0, 0.05, 0.0, 0.0)
    rng = np.random.default_rng(0)
    pts = project(CAM, pose, lattice_in_tag(0.1)) + rng.normal(0, 0.3, (16, 2))
    cand = solve_planar_pnp(CAM, lattice_in_tag(0.1), pts)
    assert cand.ambiguity_ratio < 3.0


def test_bad_input() -> None:
    with pytest.raises(GeometryError, match=">= 4"):
        solve_planar_pnp(CAM, lattice_in_tag(0.2)[:3], np.zeros((3, 2)))
    with pytest.raises(GeometryError, match="finite"):
        solve_planar_pnp(CAM, lattice_in_tag(0.2), np.full((16, 2), np.nan))
