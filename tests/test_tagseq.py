"""The sequence renderer (bench/tagseq.py) behind the SLAM benchmark: geometry and exposure blur."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bench.accuracy import AprilTagMethod
from bench.slam import trajectory_metrics
from bench.tagrender import corners_in_tag, project_points
from bench.tagseq import SEQUENCES, SequenceRenderer, write_sequence


def test_rendered_tags_sit_where_the_truth_says() -> None:
    """AprilTag 3 finds the tags in view of a slow frame, with its corners within half a pixel of the
    projection of the tags' true world poses through the true camera pose."""
    r = SequenceRenderer(SEQUENCES["slow"])
    frame = r.render(0)
    assert frame.in_view
    det = AprilTagMethod()
    try:
        found = {p.tag_id: p.points_px for p in det(frame.image, r.k)}
    finally:
        det.close()
    tags = {t.tag_id: t for t in r.tags}
    for tag_id in frame.in_view:
        assert tag_id in found
        truth = project_points(
            r.k, r.camera_from_tag(frame.world_from_camera, tags[tag_id]), corners_in_tag(tags[tag_id].size_m)
        )
        assert np.abs(found[tag_id] - truth).max() < 0.5


def test_the_fast_sequence_blurs_and_the_slow_one_hardly() -> None:
    slow = SequenceRenderer(SEQUENCES["slow"]).render(60)
    fast = SequenceRenderer(SEQUENCES["fast"]).render(90)
    assert max(slow.blur_px.values()) < 5.0
    assert max(fast.blur_px.values()) > 10.0


def test_a_sequence_folder_is_tum_style(tmp_path: Path) -> None:
    write_sequence(SEQUENCES["medium"], tmp_path, frames=2)
    rows = [line for line in (tmp_path / "rgb.txt").read_text().splitlines() if not line.startswith("#")]
    assert len(rows) == 2 and all((tmp_path / row.split()[1]).is_file() for row in rows)
    gt = [line.split() for line in (tmp_path / "groundtruth.tum").read_text().splitlines() if not line.startswith("#")]
    assert len(gt) == 2 and all(len(g) == 8 for g in gt)
    q = np.array([float(x) for x in gt[0][4:]])
    assert abs(np.linalg.norm(q) - 1.0) < 1e-6


def test_trajectory_metrics_are_zero_on_the_truth_and_see_an_offset() -> None:
    r = SequenceRenderer(SEQUENCES["slow"])
    gt = {i: r.trajectory.world_from_camera(i / 30) for i in range(60)}
    m = trajectory_metrics(gt, gt, fps=30)
    assert m["pose_pct"] == 100.0 and m["ate_cm"] == 0.0 and m["rpe_cm"] == 0.0
    shifted = {i: p.copy() for i, p in gt.items()}
    for p in shifted.values():
        p[0, 3] += 0.02
    m = trajectory_metrics(shifted, gt, fps=30)
    ate, aligned = m["ate_cm"], m["aligned_ate_cm"]
    assert ate is not None and aligned is not None
    assert abs(ate - 2.0) < 1e-9 and aligned < 1e-6


def test_the_covariance_check_counts_errors_inside_the_95_percent_ellipsoid() -> None:
    """bench.slam's covariance columns: 3 cm off along x with a 1 cm sigma per axis is outside (chi-square
    9 > 7.8), with a 2 cm sigma it is inside (2.25); the sigma column is sqrt of the trace."""
    from bench.slam import covariance_check

    truth = {i: np.eye(4) for i in range(4)}
    est = {i: p.copy() for i, p in truth.items()}
    for p in est.values():
        p[0, 3] += 0.03
    cov = {i: np.eye(3) * (0.01 if i < 3 else 0.02) ** 2 for i in est}
    got = covariance_check(est, cov, truth)
    assert got["inside95_pct"] == 25.0
    assert got["sigma_cm"] is not None and abs(got["sigma_cm"] - 100 * 0.01 * np.sqrt(3)) < 1e-9
    assert covariance_check(est, {}, truth) == {"sigma_cm": None, "inside95_pct": None}


def test_the_rough_map_moves_every_tag_but_the_anchor_and_states_it() -> None:
    """bench.slam's rough map: the anchor exact, the others a few cm and about a degree off (seeded: the
    same every run), each stated at the sigmas it was drawn with."""
    import math

    import cv2

    from bench.slam import ROUGH_POSITION_SIGMA_M, ROUGH_ROTATION_SIGMA_DEG, place_tags_map, rough_tag_map

    spec = SEQUENCES["medium"]
    true = place_tags_map(spec)
    rough, anchor, sigmas = rough_tag_map(spec)
    assert rough.keys() == true.keys() and set(sigmas) == set(rough) - {anchor}
    assert all(v == (math.radians(ROUGH_ROTATION_SIGMA_DEG), ROUGH_POSITION_SIGMA_M) for v in sigmas.values())
    np.testing.assert_array_equal(rough[anchor][1], true[anchor][1])
    offsets = [np.linalg.norm(rough[t][1][:3, 3] - true[t][1][:3, 3]) for t in sigmas]
    turns = [np.degrees(np.linalg.norm(cv2.Rodrigues(true[t][1][:3, :3].T @ rough[t][1][:3, :3])[0])) for t in sigmas]
    # |3-D offset| of N(0, s) per axis: median about 1.5 s
    assert 0.7 * ROUGH_POSITION_SIGMA_M < np.median(offsets) < 2.5 * ROUGH_POSITION_SIGMA_M
    assert 0.7 * ROUGH_ROTATION_SIGMA_DEG < np.median(turns) < 2.5 * ROUGH_ROTATION_SIGMA_DEG
    again = rough_tag_map(spec)[0]
    for t in sigmas:
        np.testing.assert_array_equal(again[t][1], rough[t][1])


def test_grid_along_blur_is_zero_on_the_truth_and_reads_a_shrunk_grid() -> None:
    """bench.slam's grid-along-blur fact: exact poses read 0 %, poses 2 % too far (a grid 2 % small)
    read about -2 %, tags blurred < 3 px are left out."""
    from bench.slam import FrameRecord, TagObservation, grid_along_blur, place_tags_map
    from bench.tagseq import Trajectory

    spec = SEQUENCES["fast"]
    tag_map, trajectory = place_tags_map(spec), Trajectory(spec)

    def records(scale: float, blur_px: float) -> list[FrameRecord]:
        out = []
        for index in range(0, 60, 3):
            stamp = index / spec.fps
            world_from_camera = trajectory.world_from_camera(stamp)
            obs, blur = [], {}
            for tag_id, (size_m, world_from_tag) in tag_map.items():
                camera_from_tag = np.linalg.inv(world_from_camera) @ world_from_tag
                if camera_from_tag[2, 3] < 0.5:
                    continue
                seen = camera_from_tag.copy()
                seen[:3, 3] *= scale
                obs.append(TagObservation(tag_id, size_m, seen, 0.0, seen, 1.0))
                blur[tag_id] = blur_px
            out.append(FrameRecord(index, stamp, world_from_camera, list(blur), blur, splittag=obs))
        return out

    exact = grid_along_blur(records(1.0, 10.0), spec)
    assert exact["blur_>=8_px_tags"] and abs(exact["blur_>=8_px_median_pct"]) < 1e-6  # type: ignore[arg-type]
    far = grid_along_blur(records(1.02, 5.0), spec)
    assert far["blur_3-8_px_tags"] and abs(far["blur_3-8_px_median_pct"] + 100 * (1 - 1 / 1.02)) < 0.05  # type: ignore[operator]
    sharp = grid_along_blur(records(1.0, 2.0), spec)
    assert sharp["blur_3-8_px_tags"] == sharp["blur_>=8_px_tags"] == 0


def test_perturbed_records_move_only_the_positions_and_only_by_a_nanometre() -> None:
    """bench.slam --perturb's copies: every observation's position (detected and tracked) moved by about
    1 nm, everything else as it was, the originals untouched, the same seed the same copy."""
    from bench.slam import FrameRecord, TagObservation, perturbed

    pose = np.eye(4)
    pose[:3, 3] = [0.1, -0.2, 3.0]

    def obs(tag_id: int) -> TagObservation:
        return TagObservation(tag_id, 0.15, pose.copy(), 0.1, pose.copy(), 0.3, "lines")

    records = [FrameRecord(i, i / 30, np.eye(4), [1, 2], {}, splittag=[obs(1)], tracked=[obs(2)]) for i in range(20)]
    copies = perturbed(records, seed=3)
    moved = [np.linalg.norm(c.camera_from_tag[:3, 3] - pose[:3, 3]) for r in copies for c in (*r.splittag, *r.tracked)]
    assert len(moved) == 40 and min(moved) > 0 and max(moved) < 1e-8
    for r, c in zip(records, copies, strict=True):
        for o, p in zip((*r.splittag, *r.tracked), (*c.splittag, *c.tracked), strict=True):
            np.testing.assert_array_equal(o.camera_from_tag, pose)  # the original untouched
            np.testing.assert_array_equal(p.camera_from_tag[:3, :3], pose[:3, :3])
            np.testing.assert_array_equal(p.alt_camera_from_tag, pose)
            assert (p.tag_id, p.proposer, p.reprojection_error_px) == (o.tag_id, o.proposer, o.reprojection_error_px)
    again = perturbed(records, seed=3)
    assert all(
        np.array_equal(a.splittag[0].camera_from_tag, b.splittag[0].camera_from_tag)
        for a, b in zip(copies, again, strict=True)
    )


def test_bench_slam_refuses_a_negative_perturb_count_by_name() -> None:
    import subprocess
    import sys

    out = subprocess.run(
        [sys.executable, "-m", "bench.slam", "--perturb", "-1"], capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 2 and "--perturb" in out.stderr
