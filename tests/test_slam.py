"""SLAM core on scripted measurements: exact recovery, and better than frame-by-frame PnP with noise."""

from __future__ import annotations

import dataclasses
import json
import math
import re
import time
from pathlib import Path
from typing import cast

import cv2
import gtsam
import numpy as np
import pytest

from services.slam.service import SlamNode
from services.slam.settings import SlamServiceSettings
from shared.runtime.sources import demo_scene, demo_trajectory
from shared.sim.scene import look_at
from shared.slam.marker_slam import (
    FrameIndexer,
    FrameResult,
    MarkerSlam,
    Observation,
    SlamInputError,
    SlamSettings,
    absolute_trajectory_error,
    camera_prior,
    check_observation,
    umeyama_se3,
)
from shared.vision.geometry import GeometryError, default_camera, lattice_in_tag, make_pose, project
from shared.vision.pnp import solve_planar_pnp
from shared.vision.tagmap import load_tag_map, tag_map_from_poses, write_tag_map
from shared.vision.trajectory import StampMap, read_tum
from shared.wire.messages import HopTimings, TagPose, TagPoses

CAM = default_camera()
SCENE = demo_scene()
TRAJ = demo_trajectory(60)
# The demo's path in 60 frames moves up to 0.2 m and 5 deg a frame: a robot's pace (2 m/s, SLAM's motion
# envelope) at 10 fps, so its frames are stamped 100 ms apart.
TRAJ_FRAME_NS = 100_000_000
SCENE_TAGS = {t.id: t.pose() for t in SCENE.tags}


def _visible(world_from_camera: np.ndarray) -> list[tuple[int, float, np.ndarray]]:
    out = []
    for tag in SCENE.tags:
        cft = np.linalg.inv(world_from_camera) @ tag.pose()
        px = project(CAM, cft, lattice_in_tag(tag.size_m))
        if cft[2, 3] > 0.2 and (px >= 0).all() and (px[:, 0] < CAM.width).all() and (px[:, 1] < CAM.height).all():
            out.append((tag.id, tag.size_m, cft))
    return out


def _exact_obs(tag_id: int, size: float, cft: np.ndarray) -> Observation:
    return Observation(tag_id, size, cft, 0.0, cft, 5.0)


def _noisy_obs(tag_id: int, size: float, cft: np.ndarray, rng: np.random.Generator, sigma_px: float) -> Observation:
    """A tag's view as the edge makes it: its 16 keypoints with Gaussian pixel noise through real PnP."""
    px = project(CAM, cft, lattice_in_tag(size)) + rng.normal(0, sigma_px, (16, 2))
    fit = solve_planar_pnp(CAM, lattice_in_tag(size), px)
    return Observation(
        tag_id,
        size,
        fit.camera_from_tag,
        fit.reprojection_error_px,
        fit.alt_camera_from_tag,
        fit.alt_reprojection_error_px,
    )


def _constant_velocity(n: int) -> list[np.ndarray]:
    # The motion prior is exact for constant velocity, so exact measurements must be recovered exactly.
    return [
        look_at(np.array([-2.0 + 4.0 * i / n, 0.4, 1.2]), np.array([-1.0 + 4.0 * i / n, 3.0, 1.3])) for i in range(n)
    ]


def test_exact_measurements_recover_map_and_trajectory_to_a_millimetre() -> None:
    anchor = SCENE.tags[3]
    slam = MarkerSlam(SlamSettings(anchor_tag_id=anchor.id), known_tags={anchor.id: (anchor.size_m, anchor.pose())})
    traj = _constant_velocity(60)
    for i, wfc in enumerate(traj):
        obs = [_exact_obs(*v) for v in _visible(wfc)]
        res = slam.update(i, i, obs)
        if res.world_from_camera is not None:
            assert np.linalg.norm(res.world_from_camera[:3, 3] - wfc[:3, 3]) < 1e-3
    est = dict(slam.trajectory())
    assert len(est) >= 55
    for stamp, pose in est.items():
        assert np.linalg.norm(pose[:3, 3] - traj[stamp][:3, 3]) < 1e-3
    mapped = slam.tag_map()
    assert len(mapped) >= 5
    truth = {t.id: t.pose() for t in SCENE.tags}
    for tag_id, (_, pose) in mapped.items():
        assert np.linalg.norm(pose[:3, 3] - truth[tag_id][:3, 3]) < 1e-3


def _noisy_run(seed: int, sigma_px: float) -> tuple[float, int, float]:
    """The demo path with every visible tag's 16 keypoints noisy through real PnP: (SLAM ATE, frames SLAM
    posed, frame-by-frame PnP ATE from the nearest tag on the true map)."""
    rng = np.random.default_rng(seed)
    anchor = SCENE.tags[3]
    slam = MarkerSlam(SlamSettings(anchor_tag_id=anchor.id), known_tags={anchor.id: (anchor.size_m, anchor.pose())})
    truth = {t.id: t.pose() for t in SCENE.tags}
    pnp_est, gt = {}, {}
    for i, wfc in enumerate(TRAJ):
        obs = [_noisy_obs(tag_id, size, cft, rng, sigma_px) for tag_id, size, cft in _visible(wfc)]
        slam.update(i, i * TRAJ_FRAME_NS, obs)
        gt[i] = wfc
        if obs:
            best = min(obs, key=lambda o: np.linalg.norm(o.camera_from_tag[:3, 3]))
            pnp_est[i] = truth[best.tag_id] @ np.linalg.inv(best.camera_from_tag)
    slam_ate, n = absolute_trajectory_error({t // TRAJ_FRAME_NS: p for t, p in slam.trajectory()}, gt)
    pnp_ate, _ = absolute_trajectory_error(pnp_est, gt)
    return slam_ate, n, pnp_ate


@pytest.mark.parametrize(
    "sigma_px",
    [
        0.1,
        0.2,
        pytest.param(
            0.6,
            marks=pytest.mark.xfail(
                strict=True,
                raises=AssertionError,
                reason="GTSAM 4.3.0: at 0.6 px SLAM's median (30.5 cm) is no better than PnP's (29.4); "
                "on 4.3a2 it was 11.3 (docs/slam.md, GTSAM version)",
            ),
        ),
    ],
)
def test_noisy_measurements_beat_frame_by_frame_pnp(sigma_px: float) -> None:
    """Over 8 noise draws, SLAM's median ATE is under 0.6x frame-by-frame PnP's, with every frame posed.
    Judged on the median: a single draw on 84 px tags at 2.5 m is chaotic (an IPPE branch flip moves a
    run by centimetres, and which draw flips differs between CPUs and GTSAM versions; docs/slam.md,
    *GTSAM version*)."""
    runs = [_noisy_run(seed, sigma_px) for seed in range(8)]
    slam_cm = [100 * s for s, _, _ in runs]
    pnp_cm = [100 * p for _, _, p in runs]
    print(f"{sigma_px} px: SLAM ATE cm {np.round(slam_cm, 1)} vs frame-by-frame PnP {np.round(pnp_cm, 1)}")
    assert all(n == len(TRAJ) for _, n, _ in runs)
    assert np.median(slam_cm) < 0.6 * np.median(pnp_cm)


def test_world_covariance_is_the_graphs_tangent_covariance_in_the_world_frame() -> None:
    """Monte Carlo: poses T Exp(xi), xi ~ N(0, tangent covariance) (GTSAM's right perturbation in the
    camera frame, rotation first), moved camera centres and world-axis turns; their covariance is
    world_covariance's (position first)."""
    from shared.slam.marker_slam import world_covariance

    rng = np.random.default_rng(5)
    pose = make_pose(cv2.Rodrigues(np.array([0.4, -1.1, 0.3]))[0], [1.0, -2.0, 0.5])
    a = rng.normal(size=(6, 6))
    tangent = (a @ a.T + np.eye(6)) * 1e-6  # small: first order holds
    xis = rng.multivariate_normal(np.zeros(6), tangent, size=20000)
    moved = []
    for xi in xis:
        p = pose @ np.asarray(gtsam.Pose3.Expmap(xi).matrix())
        turn = cv2.Rodrigues(p[:3, :3] @ pose[:3, :3].T)[0].ravel()
        moved.append(np.concatenate([p[:3, 3] - pose[:3, 3], turn]))
    expected = world_covariance(tangent, pose)
    np.testing.assert_allclose(np.cov(np.array(moved).T), expected, atol=0.05 * float(np.abs(expected).max()))


def test_each_pose_says_how_sure_it_is() -> None:
    """Noisy keypoints (0.5 px, the noise model's floor) through real PnP, on a path the motion prior
    holds (constant velocity): every pose has a symmetric positive-definite covariance, the position
    errors lie inside its 95 % ellipsoid about as often as they should but the ellipsoid is not inflated
    past use (the errors' median NEES), and while only the farthest mapped tag is in view the position
    grows less sure."""
    rng = np.random.default_rng(1)
    anchor = SCENE.tags[3]
    slam = MarkerSlam(SlamSettings(anchor_tag_id=anchor.id), known_tags={anchor.id: (anchor.size_m, anchor.pose())})
    nees: list[float] = []  # normalised estimation error squared of each position (chi2(3) if the covariance is right)
    sigma_m: dict[int, float] = {}
    for i, wfc in enumerate(_constant_velocity(60)):
        seen = _visible(wfc)
        lone = 25 <= i < 35
        if lone:  # the farthest tag already in the map, alone
            seen = [max((v for v in seen if v[0] in slam.tags), key=lambda v: float(v[2][2, 3]))]
        obs = [_noisy_obs(tag_id, size, cft, rng, 0.5) for tag_id, size, cft in seen]
        res = slam.update(i, i, obs)
        if res.world_from_camera is None:
            continue
        cov = res.covariance_world
        assert cov is not None and cov.shape == (6, 6)
        np.testing.assert_allclose(cov, cov.T)
        assert np.linalg.eigvalsh(cov).min() > 0
        err = res.world_from_camera[:3, 3] - wfc[:3, 3]
        nees.append(float(err @ np.linalg.solve(cov[:3, :3], err)))
        sigma_m[i] = float(np.sqrt(np.trace(cov[:3, :3])))
    inside = np.asarray(nees) <= 7.815  # chi2(3) 95 %
    assert len(nees) >= 45 and all(i in sigma_m for i in range(24, 35))
    print(
        f"inside the 95 % ellipsoid: {100 * np.mean(inside):.0f} %; median NEES {np.median(nees):.2f} "
        f"(chi2(3): 2.37); position sigma before / after ten frames of the farthest tag alone: "
        f"{100 * sigma_m[24]:.1f} / {100 * sigma_m[34]:.1f} cm"
    )
    assert np.mean(inside) >= 0.9
    # From the other side: a covariance k times too large divides NEES by k, and the 95 % check above
    # passes for any k > 1. Measured with this path and noise: median NEES 2.23 (seed 1); over seeds 1-20,
    # a far bigger perturbation than another CPU's rounding, 0.46 to 3.80 as shipped, at most 0.38 with the
    # covariance x10 and 0.038 x100. The floor sits between: 0.4.
    assert np.median(nees) >= 0.4
    assert sigma_m[34] > 1.3 * sigma_m[24]


def _flip(camera_from_tag: np.ndarray, axis: tuple[float, float, float] = (1.0, 0.0, 0.0)) -> np.ndarray:
    """The other IPPE branch, caricatured: the tag tilted by 0.5 rad about an axis in its plane (which
    axis depends on the view, as the real mirror branch does)."""
    tilt = make_pose(cv2.Rodrigues(0.5 * np.array(axis))[0], [0.0, 0.0, 0.0])
    return camera_from_tag @ tilt


def test_an_ambiguous_view_takes_the_branch_the_map_agrees_with() -> None:
    """The chosen IPPE branch is wrong but the other fits almost as well: the map decides, the
    observation is used with the right branch, the camera pose is exact."""
    anchor = SCENE.tags[3]
    slam = MarkerSlam(SlamSettings(anchor_tag_id=anchor.id), known_tags={anchor.id: (anchor.size_m, anchor.pose())})
    wfc = TRAJ[0]
    vis = _visible(wfc)
    assert len(vis) >= 3
    slam.update(0, 0, [_exact_obs(*v) for v in vis])
    right = vis[1][2]
    ambiguous = Observation(vis[1][0], vis[1][1], _flip(right), 0.05, right, 0.06)
    assert slam.is_ambiguous(ambiguous)
    res = slam.update(1, 1, [_exact_obs(*vis[0]), ambiguous, _exact_obs(*vis[2])])
    assert res.rejected_ambiguous == 0 and res.tags_used == 3
    assert res.world_from_camera is not None
    assert np.linalg.norm(res.world_from_camera[:3, 3] - wfc[:3, 3]) < 1e-3


def test_a_view_that_fits_no_branch_is_rejected() -> None:
    anchor = SCENE.tags[3]
    slam = MarkerSlam(SlamSettings(anchor_tag_id=anchor.id), known_tags={anchor.id: (anchor.size_m, anchor.pose())})
    wfc = TRAJ[0]
    vis = _visible(wfc)
    slam.update(0, 0, [_exact_obs(*v) for v in vis])
    wrong = _flip(_flip(vis[1][2]))  # 57 degrees off, and its "other branch" 29 degrees off
    outlier = Observation(vis[1][0], vis[1][1], wrong, 0.05, _flip(vis[1][2]), 0.06)
    res = slam.update(1, 1, [_exact_obs(*vis[0]), outlier, _exact_obs(*vis[2])])
    assert res.rejected_ambiguous == 1 and res.tags_used == 2
    assert res.world_from_camera is not None
    assert np.linalg.norm(res.world_from_camera[:3, 3] - wfc[:3, 3]) < 1e-3


def test_a_new_tag_seen_ambiguously_waits_for_a_second_view() -> None:
    """A new tag enters the map only from an unambiguous view, or once a second view agrees with one
    of the first view's two branches; the map then holds the right branch."""
    poses = _constant_velocity(6)
    slam = MarkerSlam(SlamSettings())
    vis0 = _visible(poses[0])
    common = sorted(set.intersection(*({v[0] for v in _visible(p)} for p in poses[:3])))
    assert len(common) >= 2
    anchor_id, newcomer = common[:2]
    slam.update(0, 0, [_exact_obs(*v) for v in vis0 if v[0] == anchor_id])
    truth = slam._world_from_tag(anchor_id)
    assert truth is not None
    for i in (1, 2):
        vis = {v[0]: v for v in _visible(poses[i])}
        a, n = vis[anchor_id], vis[newcomer]
        # ambiguous, with the wrong branch chosen in the first view and the right one in the second
        chosen, other = (_flip(n[2]), n[2]) if i == 1 else (n[2], _flip(n[2], (0.0, 1.0, 0.0)))
        res = slam.update(i, i, [_exact_obs(*a), Observation(newcomer, n[1], chosen, 0.05, other, 0.06)])
        if i == 1:
            assert newcomer not in slam.tags and res.rejected_ambiguous == 1
        else:
            assert newcomer in slam.tags and res.tags_used == 2
    world_from_newcomer = slam._world_from_tag(newcomer)
    assert world_from_newcomer is not None
    true_rel = np.linalg.inv(SCENE_TAGS[anchor_id]) @ SCENE_TAGS[newcomer]
    est_rel = np.linalg.inv(truth) @ world_from_newcomer
    np.testing.assert_allclose(est_rel, true_rel, atol=1e-6)


def test_memory_stays_bounded_and_the_trajectory_whole() -> None:
    """Frames older than the window leave the graph (priors keep what they taught the map): the
    graph's size stops growing, the trajectory keeps every frame, exact data stays exact."""
    n = 100
    poses = _constant_velocity(n)
    slam = MarkerSlam(SlamSettings(window_frames=20))
    sizes = []
    for i, pose in enumerate(poses):
        assert slam.update(i, 1_000 + i, [_exact_obs(*v) for v in _visible(pose)]).status == "tracking"
        sizes.append(slam.isam.getFactorsUnsafe().size())
    assert len(slam.stamps) <= 20
    assert max(sizes[50:]) <= max(sizes[:30])
    traj = slam.trajectory()
    assert [s for s, _ in traj] == [1_000 + i for i in range(n)]
    assert slam.anchor is not None
    anchor_truth = SCENE_TAGS[slam.anchor]
    for (_, est), truth in zip(traj, poses, strict=True):
        np.testing.assert_allclose(anchor_truth @ est, truth, atol=1e-6)
    with pytest.raises(SlamInputError, match="already fused"):
        slam.update(5, 1_005, [])  # a frame that left the graph long ago is still known as fused


def test_localisation_only_needs_a_map() -> None:
    with pytest.raises(ValueError, match="tag map"):
        MarkerSlam(SlamSettings(localisation_only=True))


def test_umeyama_recovers_a_rigid_transform() -> None:
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(20, 3))
    t = TRAJ[5]
    moved = (t[:3, :3] @ pts.T).T + t[:3, 3]
    np.testing.assert_allclose(umeyama_se3(pts, moved), t, atol=1e-9)


def test_the_map_slam_writes_loads_back_as_a_tag_map(tmp_path: Path) -> None:
    """map.json is a tag map (it used to carry run statistics that load_tag_map rejects): slam's own
    output can be fed back as slam's or edge_infer's known map."""
    node = SlamNode(SlamServiceSettings(run_dir=tmp_path))
    for i, pose in enumerate(_constant_velocity(20)):
        node.slam.update(i, i * 33_000_000, [_exact_obs(*v) for v in _visible(pose)])
    built = node.slam.tag_map()
    assert len(built) >= 2
    node.write_outputs(tmp_path)
    loaded = load_tag_map(tmp_path / "map.json")
    assert loaded.anchor_tag_id == node.slam.anchor
    assert {t.id for t in loaded.tags} == set(built)
    for t in loaded.tags:
        assert t.size_m == built[t.id][0]
        np.testing.assert_allclose(np.asarray(t.world_from_tag), built[t.id][1], atol=1e-12)
    assert json.loads((tmp_path / "slam.json").read_text())["frames"] == 20
    again = SlamNode(SlamServiceSettings(run_dir=tmp_path, tag_map=tmp_path / "map.json"))
    assert set(again.slam.known) == {t.id for t in loaded.tags}


@pytest.mark.parametrize(
    ("pose", "why"),
    [
        ([[0.0] * 4] * 4, "not a rigid transform"),  # the all-zero pose that killed slam
        ([[1, 0, 0, 1e300], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "translates by more than"),
        ([[1, 0, 0], [0, 1, 0], [0, 0, 1]], "not a finite 4x4"),
        ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0]], "world_from_tag"),
    ],
)
def test_a_tag_map_with_a_bad_pose_is_refused_with_its_reason(
    tmp_path: Path, pose: list[list[float]], why: str
) -> None:
    path = tmp_path / "map.json"
    path.write_text(json.dumps({"tags": [{"id": 3, "size_m": 0.1, "world_from_tag": pose}]}))
    with pytest.raises(GeometryError, match=why):
        load_tag_map(path)


@pytest.mark.parametrize(
    ("extra", "why"),
    [({"position_sigma_m": 0.0}, "position_sigma_m"), ({"rotation_sigma_deg": -1.0}, "rotation_sigma_deg")],
)
def test_a_tag_map_with_a_bad_uncertainty_is_refused_with_its_reason(
    tmp_path: Path, extra: dict[str, float], why: str
) -> None:
    path = tmp_path / "map.json"
    tag = {"id": 3, "size_m": 0.1, "world_from_tag": np.eye(4).tolist(), **extra}
    path.write_text(json.dumps({"tags": [tag]}))
    with pytest.raises(GeometryError, match=why):
        load_tag_map(path)


@pytest.mark.parametrize(
    ("doc", "why"),
    [
        # edge_infer took the first size, slam the last: a trial's ATE went 0.62 -> 17.5 cm, silently
        ({"tags": [{"id": 286, "size_m": 0.166}, {"id": 286, "size_m": 0.2}]}, r"listed more than once: \[286\]"),
        # slam waited for a tag the map never named: every frame lost, not a word
        ({"anchor_tag_id": 999, "tags": [{"id": 286, "size_m": 0.166}]}, "anchor_tag_id 999 is not one of"),
    ],
)
def test_a_tag_map_names_each_tag_once_and_lists_its_anchor(tmp_path: Path, doc: dict[str, object], why: str) -> None:
    path = tmp_path / "map.yaml"
    path.write_text(json.dumps(doc))
    with pytest.raises(GeometryError, match=why):
        load_tag_map(path)


def test_bad_frames_are_refused_before_they_touch_the_state() -> None:
    """Each of these used to kill slam (GTSAM errors); now each is a SlamInputError and the next good
    frame is fused as if nothing had happened."""
    slam = MarkerSlam(SlamSettings())
    poses = _constant_velocity(6)
    for i, pose in enumerate(poses[:3]):
        assert slam.update(i, i, [_exact_obs(*v) for v in _visible(pose)]).status == "tracking"
    before = (slam.state.frames, dict(slam.tags), sorted(slam.stamps))
    good = [_exact_obs(*v) for v in _visible(poses[3])]
    zero = Observation(good[0].tag_id, good[0].size_m, np.zeros((4, 4)), 0.0, np.zeros((4, 4)), 1.0)
    behind = np.array(good[0].camera_from_tag)
    behind[2, 3] = -1.0
    with pytest.raises(SlamInputError, match="already fused"):
        slam.update(2, 2, good)  # a re-sent TagPoses
    with pytest.raises(SlamInputError, match="outside"):
        slam.update(2**56, 3, good)
    with pytest.raises(SlamInputError, match="rigid"):
        slam.update(3, 3, [*good, zero])
    with pytest.raises(SlamInputError, match="in front"):
        slam.update(3, 3, [Observation(good[0].tag_id, good[0].size_m, behind, 0.0, behind, 1.0)])
    with pytest.raises(SlamInputError, match="size"):
        slam.update(3, 3, [Observation(good[0].tag_id, 1e-300, behind, 0.0, behind, 1.0)])
    assert (slam.state.frames, dict(slam.tags), sorted(slam.stamps)) == before
    res = slam.update(3, 3, good)
    reference = MarkerSlam(SlamSettings())  # the same frames without the bad ones
    for i, pose in enumerate(poses[:4]):
        ref = reference.update(i, i, [_exact_obs(*v) for v in _visible(pose)])
    assert res.status == "tracking" and res.world_from_camera is not None and ref.world_from_camera is not None
    np.testing.assert_allclose(res.world_from_camera, ref.world_from_camera, atol=1e-9)


def _tag_poses(seq: int, stamp: int, pose: np.ndarray, only: set[int] | None = None) -> TagPoses:
    tags = [
        TagPose(
            tag_id=tag_id,
            tag_size_m=size,
            keypoints_px=np.zeros((16, 2), np.float32),
            corners_px=np.zeros((4, 2), np.float32),
            camera_from_tag=cft,
            reprojection_error_px=0.0,
            alt_camera_from_tag=cft,
            alt_reprojection_error_px=5.0,
            tracked=False,
        )
        for tag_id, size, cft in _visible(pose)
        if only is None or tag_id in only
    ]
    timings = HopTimings(robot_compute_secs=0.0, transport_secs=0.0, edge_compute_secs=0.0, capture_to_pose_secs=0.0)
    return TagPoses(
        robot_id="r1",
        seq=seq,
        capture_nanos=stamp,
        split_k=7,
        payload_bytes=0,
        timings=timings,
        link=None,
        intrinsics=None,
        tags=tags,
    )


def test_a_repeated_message_is_refused_and_a_restarted_camera_goes_on(tmp_path: Path) -> None:
    """Re-sending a real TagPoses, or restarting the camera (seq from 0 again), used to kill slam."""
    node = SlamNode(SlamServiceSettings(run_dir=tmp_path))
    poses = _constant_velocity(20)
    for i in range(10):
        assert node.on_poses(_tag_poses(i, 1_000 + i, poses[i]))[0].status == "tracking"
    with pytest.raises(SlamInputError, match="already fused"):
        node.on_poses(_tag_poses(5, 1_005, poses[5]))
    with pytest.raises(SlamInputError, match="out of order"):
        node.on_poses(_tag_poses(11, 1_003, poses[11]))
    for i in range(10):  # the camera restarted: seq from 0, later capture times
        assert node.on_poses(_tag_poses(i, 2_000 + i, poses[10 + i]))[0].status == "tracking"
    assert node.indexer.sessions == 2
    assert len(node.slam.trajectory()) == 20
    with pytest.raises(SlamInputError, match="future"):  # would make every real frame after it look stale
        node.on_poses(_tag_poses(99, time.time_ns() + 3_600 * 10**9, poses[0]))


def test_a_frame_numbered_near_the_graphs_limit_does_not_stop_slam(tmp_path: Path) -> None:
    """A trial's one valid frame with seq 2**56 - 10 (the wire allows up to 2**64 - 1) pushed every
    later frame's index past what the graph holds: slam refused every frame for the rest of the run."""
    node = SlamNode(SlamServiceSettings(run_dir=tmp_path))
    poses = _constant_velocity(30)
    for i in range(5):
        assert node.on_poses(_tag_poses(i, 1_000 + i, poses[i]))[0].status == "tracking"
    for j, seq in enumerate((2**56 - 10, 2**64 - 3)):  # each one a jump: a new session, not a huge index
        assert node.on_poses(_tag_poses(seq, 1_005 + j, poses[5 + j]))[0].status == "tracking"
    for i in range(7, 30):  # the real camera goes on (its seq "went back": one more session)
        assert node.on_poses(_tag_poses(i, 1_000 + i, poses[i]))[0].status == "tracking", i
    assert node.indexer.sessions == 4


def test_frame_indices_move_on_by_at_most_one_session_break_per_frame() -> None:
    indexer = FrameIndexer(session_break=100, clock_nanos=lambda: 10**12)
    seqs = [7, 8, 10, 2**63, 3, 4, 104, 205, 2**40, 2**40 + 1]
    got = [indexer.index(seq, 1_000 + t) for t, seq in enumerate(seqs)]
    assert got == [0, 1, 3, 103, 203, 204, 304, 404, 504, 505]  # gaps within a session kept (8 -> 10, 4 -> 104)


def test_a_frame_stamped_ahead_of_its_camera_stops_slam_for_five_frames_not_until_its_time(tmp_path: Path) -> None:
    """A trial's hostile camera sent one frame stamped 45 s ahead (within the 60 s bound): slam fused it
    and refused every real frame for 44 s as older. Five real frames in a row, in order and newer than
    the one before the stray, say the stray was the odd one out: slam goes on from them."""
    node = SlamNode(SlamServiceSettings(run_dir=tmp_path))
    poses = _constant_velocity(40)
    for i in range(10):
        assert node.on_poses(_tag_poses(i, 1_000 + i, poses[i]))[0].status == "tracking"
    node.on_poses(_tag_poses(40, 46_000, poses[10]))  # the stray: seq 40, 45 s ahead
    for i in range(10, 14):
        with pytest.raises(SlamInputError, match="out of order"):
            node.on_poses(_tag_poses(i, 1_000 + i, poses[i]))
    assert node.indexer.strays == 0
    for i in range(14, 30):  # the fifth in a row is taken, and the stream goes on
        assert node.on_poses(_tag_poses(i, 1_000 + i, poses[i]))[0].status == "tracking", i
    assert node.indexer.strays == 1
    # refused ones out of order among themselves, or older than the frame before the stray, do not count
    other = SlamNode(SlamServiceSettings(run_dir=tmp_path / "b"))
    for i in range(10):
        other.on_poses(_tag_poses(i, 1_000 + i, poses[i]))
    other.on_poses(_tag_poses(40, 46_000, poses[10]))
    for j, stamp in enumerate((1_011, 1_012, 1_005, 1_013, 1_003, 1_014, 1_015, 1_016)):  # (1_009: the frame before)
        with pytest.raises(SlamInputError, match="out of order"):
            other.on_poses(_tag_poses(100 + j, stamp, poses[11]))
    assert other.indexer.strays == 0


def test_slam_says_when_it_waits_for_an_anchor_that_never_comes(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Frames lost only because the anchor tag is not in view: slam says which tag it waits for and
    which it sees (a trial's anchor was named wrongly: 134 frames lost without a word)."""
    node = SlamNode(SlamServiceSettings(run_dir=tmp_path, resume=False, slam=SlamSettings(anchor_tag_id=999)))
    poses = _constant_velocity(30)
    with caplog.at_level("WARNING", logger="services.slam.service"):
        for i in range(30):
            assert node.on_poses(_tag_poses(i, 1_000 + i, poses[i]))[0].status == "lost"
    said = [r.getMessage() for r in caplog.records if "waiting for the anchor tag 999" in r.getMessage()]
    assert len(said) == 1 and "30 frames lost" in said[0] and "tags seen so far: [" in said[0], caplog.text
    # A known map places frames before its anchor is seen, and a frame without tags is lost for that
    # reason alone: no word about the anchor then (a reviewer found it said so).
    known = {t.id: (t.size_m, t.pose()) for t in SCENE.tags}
    write_tag_map(tmp_path / "known.json", tag_map_from_poses(known, anchor_tag_id=SCENE.tags[-1].id))
    caplog.clear()
    mapped = SlamNode(SlamServiceSettings(run_dir=tmp_path / "m", resume=False, tag_map=tmp_path / "known.json"))
    longer = _constant_velocity(36)
    statuses = []
    with caplog.at_level("WARNING", logger="services.slam.service"):
        for i in range(36):
            only = {t.id for t in SCENE.tags[:-1]} if i < 2 else set()  # then 34 frames that see nothing
            statuses.append(mapped.on_poses(_tag_poses(i, 1_000 + i, longer[i], only=only))[0].status)
    assert statuses.count("lost") >= 30 and mapped.slam.anchor is None, statuses
    assert not [r for r in caplog.records if "waiting for the anchor" in r.getMessage()], caplog.text


def test_a_restarted_slam_resumes_its_map_and_trajectory(tmp_path: Path) -> None:
    """Killing slam used to lose the map (9 tags became 5) and the next save overwrote trajectory.tum
    with less; now the checkpoint in run_dir is resumed: same anchor and world frame, the earlier
    trajectory kept and continued, tags not seen again kept."""
    settings = SlamServiceSettings(run_dir=tmp_path)
    first = SlamNode(settings)
    poses = _constant_velocity(30)
    for i in range(15):
        first.on_ground_truth(1_000 + i, poses[i])
        first.on_poses(_tag_poses(i, 1_000 + i, poses[i]))
    first.write_outputs(tmp_path)  # the last checkpoint before the kill
    before = load_tag_map(tmp_path / "map.json")
    revision_before = first.revision
    assert revision_before > 0
    second = SlamNode(settings)  # the restarted process
    assert second.resumed is not None and set(second.slam.known) == {t.id for t in before.tags}
    assert second.slam.surveyed == set()  # soft reads never place the camera by this SLAM's own estimates
    # Before it sees anything the restarted slam publishes (and answers) the map it resumed, under a
    # revision that goes on from the first process's, never one the first already gave another map (a
    # trial's map went from 9 tags at revision 6 to 3 tags at revision 1 after a restart).
    resumed_map = second.current_map("r1")
    assert resumed_map.revision > revision_before
    assert {t.tag_id for t in resumed_map.tags} == {t.id for t in before.tags}
    assert resumed_map.anchor_tag_id == before.anchor_tag_id
    # each tag's observations go on counting from the checkpoint's (a trial read 0 after a restart)
    counted = {t.tag_id: t.observations for t in first.current_map("r1").tags}
    assert all(n > 0 for n in counted.values())
    assert {t.tag_id: t.observations for t in resumed_map.tags} == counted
    for i in range(15, 30):
        second.on_ground_truth(1_000 + i, poses[i])
        res = second.on_poses(_tag_poses(i, 1_000 + i, poses[i]))[0]
        assert res.status == "tracking"
    stats = second.write_outputs(tmp_path)
    # slam.json says which poses came from before the restart (a trial read 'frames' 1877 < 'poses' 2315)
    assert stats["poses"] == 30 and stats["resumed_poses"] == 15 and stats["frames"] == 15, stats
    # Ground truth is kept across the restart too, and the ATE covers the whole run (a fleet trial's
    # covered only the frames since slam's restart: 859 of 1511, nothing said so).
    assert stats["ate_frames"] == 30 and stats["ate_m"] < 1e-3, stats
    assert len(read_tum(tmp_path / "groundtruth.tum")) == 30
    after = load_tag_map(tmp_path / "map.json")
    assert after.anchor_tag_id == before.anchor_tag_id
    assert {t.id for t in after.tags} >= {t.id for t in before.tags}
    stamps = [t for t, _ in read_tum(tmp_path / "trajectory.tum")]
    assert len(stamps) == 30 and stamps == sorted(stamps)
    assert {int(t): n for t, n in stats["observations_by_tag"].items()} == {
        t.tag_id: t.observations for t in second.current_map("r1").tags
    }
    after_counts = {int(t): n for t, n in stats["observations_by_tag"].items()}
    assert all(after_counts[t] >= n for t, n in counted.items()) and sum(after_counts.values()) > sum(counted.values())
    # The world frame did not move: a tag's pose before and after agrees.
    b = {t.id: np.asarray(t.world_from_tag) for t in before.tags}
    a = {t.id: np.asarray(t.world_from_tag) for t in after.tags}
    for tag_id in b:
        np.testing.assert_allclose(a[tag_id][:3, 3], b[tag_id][:3, 3], atol=1e-6)
    # Each tag but the anchor says how well this run placed it (its marginal), and the restart took it
    # as that prior, not as a surveyed 1 mm one.
    stated = {t.id: t.stated_sigmas() for t in before.tags}
    assert before.anchor_tag_id is not None and stated[before.anchor_tag_id] == (None, None)
    assert all(rot is not None and pos is not None for i, (rot, pos) in stated.items() if i != before.anchor_tag_id)
    assert second.slam.known_sigmas == stated
    assert second.revision > revision_before and second.current_map("r1").revision == second.revision
    # A third process after a checkpoint older than the last revision, or without resuming: still later.
    (tmp_path / "map.json").unlink()
    third = SlamNode(SlamServiceSettings(run_dir=tmp_path, resume=False))
    assert third.resumed is None and third.revision > second.revision


def test_a_restarted_slam_repeats_the_last_pose_and_says_which_tags_relocalise(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """An EKF integrator's trial killed slam mid-turn: the restarted process published the identity as
    each lost frame's pose (a lost pose repeats the last one), and said it waited for 'the anchor tag 6
    (the tag map's anchor_tag_id)' of a map that named none, where any tag of the resumed map places the
    camera again."""
    poses = _constant_velocity(60)
    first = SlamNode(SlamServiceSettings(run_dir=tmp_path))
    for i in range(15):
        first.on_poses(_tag_poses(i, 1_000 + i, poses[i]))
    first.write_outputs(tmp_path)
    last = read_tum(tmp_path / "trajectory.tum")[-1][1]
    second = SlamNode(SlamServiceSettings(run_dir=tmp_path))
    with caplog.at_level("WARNING", logger="services.slam.service"):
        for i in range(15, 45):  # nothing in view
            cam = second.on_poses(_tag_poses(i, 1_000 + i, poses[i], only=set()))[0]
            assert cam.status == "lost" and cam.covariance_world is None
            np.testing.assert_allclose(cam.world_from_camera, last, atol=1e-9)
    said = [r.getMessage() for r in caplog.records if "frames lost waiting for the anchor" in r.getMessage()]
    assert len(said) == 1 and "resumed map" in said[0] and "or any of the" in said[0], caplog.text
    # ... and a tag of that map (not the anchor) places it again
    anchor = second.resumed.anchor_tag_id if second.resumed else None
    in_view = {tag_id for tag_id, _, _ in _visible(poses[45])}
    other = next(t.id for t in load_tag_map(tmp_path / "map.json").tags if t.id != anchor and t.id in in_view)
    cam = second.on_poses(_tag_poses(45, 1_045, poses[45], only={other}))[0]
    expected = last @ np.linalg.inv(poses[14]) @ poses[45]  # in slam's world (its anchor's), as before the kill
    assert cam.status == "tracking" and np.linalg.norm(cam.world_from_camera[:3, 3] - expected[:3, 3]) < 0.01


def test_a_killed_slam_loses_none_of_the_poses_it_placed_after_its_last_checkpoint(tmp_path: Path) -> None:
    """A trial SIGKILLed slam: the 19 poses it had published since its last checkpoint were missing from
    the final trajectory.tum (a 6.4 s hole). Each pose goes to a journal as it is placed; the restarted
    slam appends what the journal holds after its trajectory's last stamp, and a checkpoint empties it.
    Killed again before its own first checkpoint, the next process still finds them, and their ground
    truth with them (a trial: groundtruth.tum lacked the journal's 10 poses, ATE over 175 of 185)."""
    settings = SlamServiceSettings(run_dir=tmp_path)
    first = SlamNode(settings)
    poses = _constant_velocity(40)
    truth = {1_000 + i: poses[i] for i in range(40)}

    def place(node: SlamNode, i: int) -> np.ndarray:
        node.on_ground_truth(1_000 + i, truth[1_000 + i])
        return node.on_poses(_tag_poses(i, 1_000 + i, poses[i]))[0].world_from_camera

    for i in range(10):
        place(first, i)
    first.write_outputs(tmp_path)  # the last checkpoint
    assert not (tmp_path / "trajectory.tum.journal.old").exists()
    published = {}
    for i in range(10, 17):  # placed and published, then SIGKILL: no checkpoint, no close
        published[1_000 + i] = place(first, i)
    assert len(read_tum(tmp_path / "trajectory.tum")) == 10
    second = SlamNode(settings)
    for i in range(20, 25):
        published[1_000 + i] = place(second, i)
    third = SlamNode(settings)  # the second killed before its first checkpoint too
    for i in range(30, 35):
        place(third, i)
    stats = third.write_outputs(tmp_path)
    rows = read_tum(tmp_path / "trajectory.tum")
    stamps = [round(t * 1e9) for t, _ in rows]
    expected = [1_000 + i for i in [*range(17), *range(20, 25), *range(30, 35)]]
    assert stamps == expected, stamps
    assert stats["poses"] == len(expected) and stats["resumed_poses"] == 22, stats
    truths = read_tum(tmp_path / "groundtruth.tum")
    assert [round(t * 1e9) for t, _ in truths] == expected and stats["ate_frames"] == len(expected), stats
    for t, pose in truths:
        np.testing.assert_allclose(pose, truth[round(t * 1e9)], atol=1e-6)
    for stamp, (_, pose) in zip(stamps, rows, strict=True):
        if stamp in published:  # the journal's poses are the ones published
            np.testing.assert_allclose(pose, published[stamp], atol=1e-6)
    journal = tmp_path / "trajectory.tum.journal"
    assert not journal.exists() or not journal.read_text()  # the checkpoint holds them all
    # a line the kill cut short, or garbage, is skipped; the lines around it are read
    from services.slam.service import PoseJournal

    cut = PoseJournal(tmp_path / "cut.journal")
    cut.append(5, -1, np.eye(4))
    cut.append(7, 70, np.eye(4))
    with cut.path.open("a") as f:
        f.write("9 -1 1.0 0.0\nnot a pose at all but fourteen words long so that only its numbers fail x\n")
    assert cut.read(source_time=False)[0].tolist() == [5, 7]
    assert cut.read(source_time=True)[0].tolist() == [70]  # (a line without a data-set stamp: left out)
    assert not (tmp_path / "trajectory.tum.journal.old").exists()


def test_a_restarted_slam_publishes_and_saves_unseen_tags_as_the_priors_it_holds(tmp_path: Path) -> None:
    """A tag the checkpoint and a configured tag map both give: slam holds the configured map's pose as
    its prior (it wins over the checkpoint's), and the published map and the next map.json say the same
    (review: the publication and the checkpoint writer disagreed), until the tag is seen again."""
    settings = SlamServiceSettings(run_dir=tmp_path)
    first = SlamNode(settings)
    poses = _constant_velocity(15)
    for i in range(15):
        first.on_poses(_tag_poses(i, 1_000 + i, poses[i]))
    first.write_outputs(tmp_path)
    before = load_tag_map(tmp_path / "map.json")
    other = next(t for t in before.tags if t.id != before.anchor_tag_id)
    moved = np.asarray(other.world_from_tag).copy()
    moved[0, 3] += 0.01
    anchor = next(t for t in before.tags if t.id == before.anchor_tag_id)
    assert anchor.world_from_tag is not None
    known = {anchor.id: (anchor.size_m, np.asarray(anchor.world_from_tag)), other.id: (other.size_m, moved)}
    configured = tag_map_from_poses(known, anchor_tag_id=before.anchor_tag_id)
    write_tag_map(tmp_path / "configured.json", configured)
    second = SlamNode(SlamServiceSettings(run_dir=tmp_path, tag_map=tmp_path / "configured.json"))
    published = {t.tag_id: np.asarray(t.world_from_tag) for t in second.current_map("r1").tags}
    np.testing.assert_allclose(published[other.id], moved)
    second.write_outputs(tmp_path)
    saved = {t.id: np.asarray(t.world_from_tag) for t in load_tag_map(tmp_path / "map.json").tags if t.world_from_tag}
    np.testing.assert_allclose(saved[other.id], moved)


def test_a_configured_maps_tags_never_seen_stay_in_the_map(tmp_path: Path) -> None:
    """A trial's surveyed map listed 11 tags; in SLAM mode map.json kept only the 9 seen, so feeding it
    back as tag_map lost the other two. The tags whose world pose slam holds as priors and has not seen
    are published and saved as it holds them."""
    known = {t.id: (t.size_m, t.pose()) for t in SCENE.tags}
    write_tag_map(tmp_path / "known.json", tag_map_from_poses(known, anchor_tag_id=SCENE.tags[0].id))
    node = SlamNode(SlamServiceSettings(run_dir=tmp_path / "run", tag_map=tmp_path / "known.json"))
    poses = _constant_velocity(20)
    unseen = SCENE.tags[-1].id
    seen = {t.id for t in SCENE.tags} - {unseen}
    for i in range(20):
        node.on_poses(_tag_poses(i, 1_000 + i, poses[i], only=seen))
    assert unseen not in node.slam.tag_map()
    published = {t.tag_id: t for t in node.current_map("r1").tags}
    assert set(published) == set(known) and published[unseen].observations == 0
    np.testing.assert_allclose(published[unseen].world_from_tag, known[unseen][1])
    node.write_outputs(tmp_path / "run")
    saved = {t.id: t for t in load_tag_map(tmp_path / "run" / "map.json").tags}
    assert set(saved) == set(known)
    np.testing.assert_allclose(np.asarray(saved[unseen].world_from_tag), known[unseen][1])


def test_a_map_query_takes_a_save_or_nothing() -> None:
    """The split queryable refuses what it does not know; the map's got the map back for `?foo=1`,
    `?save=abc` or a payload (a fresh-clone trial), saving nothing and saying nothing."""
    from services.slam.service import SlamQueryError, map_request

    assert map_request("", False) is False and map_request("save=0", False) is False
    assert map_request("save=1", False) is True and map_request("save=true", False) is True
    for params, payload, said in (
        ("foo=1", False, "unknown parameters ['foo']"),
        ("save=abc", False, "save must be"),
        ("save=1;save=1", False, "given twice"),
        ("", True, "no payload"),
    ):
        with pytest.raises(SlamQueryError, match=re.escape(said)):
            map_request(params, payload)


def test_a_tag_maps_stated_uncertainty_is_how_far_slam_believes_it() -> None:
    """A tag map with one tag placed 5 cm off: stated as surveyed (no sigmas: known_tag_sigma, 1 mm) slam
    holds it near where the map says (a tug of war with 60 frames of views: still over 1.5 cm off the
    truth); its position stated loosely (10 cm) the exact views pull it to within 5 mm of where it
    really is. The anchor fixes the world either way. In localisation-only mode the map is held fixed
    and its marginals say nothing: slam reports none."""
    from shared.vision.tagmap import TagSpec, tag_map_from_poses

    anchor = SCENE.tags[3]
    wrong = SCENE.tags[4]
    misplaced = wrong.pose().copy()
    misplaced[:3, 3] += [0.05, 0.0, 0.0]
    known = {anchor.id: (anchor.size_m, anchor.pose()), wrong.id: (wrong.size_m, misplaced)}
    # Position loose, rotation tight: distinct numbers, so an order or unit mix-up shows.
    loose = TagSpec(id=wrong.id, size_m=wrong.size_m, position_sigma_m=0.1, rotation_sigma_deg=0.05)
    assert loose.stated_sigmas() == (pytest.approx(np.radians(0.05)), 0.1)
    back = tag_map_from_poses({wrong.id: known[wrong.id]}, anchor_tag_id=None, sigmas={wrong.id: (0.002, 0.1)})
    assert back.tags[0].stated_sigmas() == (pytest.approx(0.002), 0.1)
    assert back.tags[0].rotation_sigma_deg == pytest.approx(np.degrees(0.002))
    placed = {}
    for name, sigmas in (("surveyed", None), ("loose", {wrong.id: loose.stated_sigmas()})):
        slam = MarkerSlam(SlamSettings(anchor_tag_id=anchor.id), known_tags=known, known_sigmas=sigmas)
        want = [np.radians(0.05)] * 3 + [0.1] * 3 if sigmas else [1e-3] * 6  # rotation first, as GTSAM's Pose3
        np.testing.assert_allclose(slam._known_noise(wrong.id).sigmas(), want)
        for i, wfc in enumerate(_constant_velocity(60)):
            slam.update(i, i, [_exact_obs(*v) for v in _visible(wfc)])
        assert wrong.id in slam.tag_map(), "the test's path must see the misplaced tag"
        placed[name] = slam.tag_map()[wrong.id][1][:3, 3]
    true = wrong.pose()[:3, 3]
    print({n: round(100 * float(np.linalg.norm(p - true)), 2) for n, p in placed.items()}, "cm from the truth")
    assert np.linalg.norm(placed["surveyed"] - true) > 0.015
    assert np.linalg.norm(placed["loose"] - true) < 0.005
    fixed = MarkerSlam(
        SlamSettings(anchor_tag_id=anchor.id, localisation_only=True),
        known_tags=known,
        known_sigmas={wrong.id: loose.stated_sigmas()},
    )
    for i, wfc in enumerate(_constant_velocity(20)):
        fixed.update(i, i, [_exact_obs(*v) for v in _visible(wfc)])
    assert fixed.tag_sigmas() == {}


def _turning(n: int = 60) -> list[np.ndarray]:
    """Constant velocity, then a sharp turn (8 deg a frame for frames 25-34, 240 deg/s at 30 fps), then on."""
    out, yaw = [], 0.0
    for i in range(n):
        yaw += math.radians(8) if 25 <= i < 35 else 0.0
        p = np.array([-2.0 + 2.0 * i / n, 0.4, 1.2])
        out.append(look_at(p, p + 3 * np.array([math.sin(yaw), math.cos(yaw), 0.02])))
    return out


def test_a_cauchy_motion_kernel_lets_the_views_place_a_sharp_turn() -> None:
    """The constant-velocity prior holds a frame to the motion however far its views are: through a
    sharp turn with a known map the online poses lag by decimetres (a trial's 280 deg/s pitch turn:
    7.7 cm RMS, up to 35 cm). motion_kernel = "cauchy" lets views far from the prior place the frame."""
    known = {t.id: (t.size_m, t.pose()) for t in SCENE.tags}
    rmse = {}
    for kernel in ("gaussian", "cauchy"):
        rng = np.random.default_rng(1)
        slam = MarkerSlam(SlamSettings(motion_kernel=kernel), known_tags=known)
        errors = []
        for i, wfc in enumerate(_turning()):
            res = slam.update(i, i * 33_333_333, [_noisy_obs(*v, rng, 0.3) for v in _visible(wfc)])
            if 25 <= i < 40:
                assert res.world_from_camera is not None
                errors.append(float(np.linalg.norm(res.world_from_camera[:3, 3] - wfc[:3, 3])))
        rmse[kernel] = float(np.sqrt(np.mean(np.square(errors))))
    print({k: f"{100 * v:.2f} cm" for k, v in rmse.items()}, "online RMS through the turn")
    assert rmse["cauchy"] < 0.05 and rmse["cauchy"] < 0.3 * rmse["gaussian"], rmse


def test_surveyed_tags_the_views_keep_further_apart_than_the_map_are_said(caplog: pytest.LogCaptureFixture) -> None:
    """An EKF integrator's trial moved one tag of a map given as surveyed (no sigmas) by 15 cm: frames that
    saw it were 35 cm off, nothing said why. Where the views keep two surveyed tags over 5 cm further apart
    or closer than the map does, slam says so once per pair (slam.json: map_disagreement_cm). The exact
    map says nothing, also through a sharp turn the motion prior lags (a first version, which compared
    where the frame's pose put each tag, said a tag of the exact map was 5.2 cm off there)."""
    anchor = SCENE.tags[3]
    wrong = SCENE.tags[4]

    rng = np.random.default_rng(0)
    for shift_m, path, noisy in (
        (0.15, _constant_velocity(60), False),
        (0.0, _constant_velocity(60), False),
        (0.0, _turning(), True),
    ):
        misplaced = wrong.pose().copy()
        misplaced[:3, 3] += [shift_m, 0.0, 0.0]
        known = {t.id: (t.size_m, t.pose()) for t in SCENE.tags} | {wrong.id: (wrong.size_m, misplaced)}
        slam = MarkerSlam(SlamSettings(anchor_tag_id=anchor.id), known_tags=known)
        caplog.clear()
        with caplog.at_level("WARNING", logger="shared.slam.marker_slam"):
            for i, wfc in enumerate(path):
                views = [_noisy_obs(*v, rng, 0.3) if noisy else _exact_obs(*v) for v in _visible(wfc)]
                slam.update(i, i * 33_000_000, views)
        said = [r.getMessage() for r in caplog.records if "than the tag map does" in r.getMessage()]
        if shift_m:
            assert said and len(said) == len(slam.state.map_disagreement_m), said
            assert all(wrong.id in pair for pair in slam.state.map_disagreement_m), slam.state.map_disagreement_m
            assert all(0.05 < abs(m) <= shift_m + 1e-6 for m in slam.state.map_disagreement_m.values())
        else:
            assert slam.state.map_disagreement_m == {} and not said, said


def test_observation_noise_uses_the_cameras_focal_length() -> None:
    """The same tag pose seen by a long lens (more pixels per metre) is a sharper measurement; the
    focal length comes from the message's intrinsics, the settings' only for v1 messages."""
    slam = MarkerSlam(SlamSettings())
    pose = make_pose(np.eye(3), [0.1, 0.0, 2.0])

    def sigmas(focal: float | None) -> np.ndarray:
        obs = Observation(1, 0.15, pose, 0.8, pose, 2.0, focal)
        cov = slam.covariance(obs)
        return np.sqrt(np.diag(cov))

    wide, long = sigmas(500.0), sigmas(2000.0)
    assert (long < wide).all()
    np.testing.assert_allclose(sigmas(None), sigmas(SlamSettings().focal_px))
    with pytest.raises(SlamInputError, match="focal"):
        check_observation(Observation(1, 0.15, pose, 0.8, pose, 2.0, 0.0))


def test_after_a_loss_any_mapped_tag_relocalises() -> None:
    """Frames without tags are lost; the first frame that sees any tag already in the map (not the
    anchor) gets its pose back, right where it is."""
    poses = _constant_velocity(80)
    slam = MarkerSlam(SlamSettings())
    for i in range(20):
        slam.update(i, i, [_exact_obs(*v) for v in _visible(poses[i])])
    assert slam.anchor is not None
    for i in range(20, 60):  # 40 frames without a tag: longer than the motion prior bridges
        assert slam.update(i, i, []).status == "lost"
    vis = [v for v in _visible(poses[60]) if v[0] in slam.tags and v[0] != slam.anchor]
    assert vis
    res = slam.update(60, 60, [_exact_obs(*vis[0])])
    assert res.status == "tracking" and res.world_from_camera is not None
    np.testing.assert_allclose(SCENE_TAGS[slam.anchor] @ res.world_from_camera, poses[60], atol=1e-6)


def _fragment_run(settings: SlamSettings) -> tuple[MarkerSlam, list[np.ndarray], dict[int, str]]:
    """Tags 4 and 5 for 10 frames; 35 frames without tags; tag 7 alone (new) for 10 frames; tags 5 and 7
    together for 5 frames; tag 7 alone again."""
    poses = _constant_velocity(70)
    slam = MarkerSlam(settings)
    statuses: dict[int, str] = {}
    for i in range(70):
        wanted = {4, 5} if i < 10 else set() if i < 45 else {7} if i < 55 else {5, 7} if i < 60 else {7}
        statuses[i] = slam.update(i, i, [_exact_obs(*v) for v in _visible(poses[i]) if v[0] in wanted]).status
    return slam, poses, statuses


def test_after_a_long_gap_new_tags_start_a_bridged_fragment_that_a_shared_view_ties_to_the_world() -> None:
    """Only new tags after a gap longer than the motion prior bridges: the robot is not lost for good;
    its poses are "bridged" (a fragment placed where it was last seen), until a frame that sees a tag
    of the world and one of the fragment joins them: from then on "tracking", and the whole fragment
    (its tag and its earlier poses) is corrected to the truth."""
    slam, poses, statuses = _fragment_run(SlamSettings())
    assert slam.anchor in (4, 5) and slam.state.fragments == 1
    assert all(statuses[i] == "tracking" for i in range(10))
    assert all(statuses[i] == "lost" for i in range(10, 45))
    assert all(statuses[i] == "bridged" for i in range(45, 55))
    assert all(statuses[i] == "tracking" for i in range(55, 70))
    world_from_anchor = SCENE_TAGS[slam.anchor]
    est = dict(slam.trajectory())
    assert sorted(est) == list(range(10)) + list(range(45, 70))
    for stamp, pose in est.items():
        assert not slam.bridged(stamp)  # joined: nothing is bridged any more
        np.testing.assert_allclose(world_from_anchor @ pose, poses[stamp], atol=1e-3)
    np.testing.assert_allclose(world_from_anchor @ slam.tag_map()[7][1], SCENE_TAGS[7], atol=1e-3)


def test_a_bridged_fragment_stays_flagged_until_it_is_joined() -> None:
    slam, _, statuses = _fragment_run(SlamSettings())
    # Replayed up to the join: the fragment's frames are flagged, the world's are not.
    slam2 = MarkerSlam(SlamSettings())
    poses = _constant_velocity(70)
    for i in range(55):
        wanted = {4, 5} if i < 10 else set() if i < 45 else {7}
        slam2.update(i, i, [_exact_obs(*v) for v in _visible(poses[i]) if v[0] in wanted])
    assert [slam2.bridged(i) for i in (0, 9, 45, 54)] == [False, False, True, True]
    assert not slam.bridged(50) and statuses[50] == "bridged"  # the status a frame had when it came


def test_slam_publishes_bridged_poses_as_such(tmp_path: Path) -> None:
    """The service's CameraPose says "bridged" for a fragment's frames (CameraPose/v2+), "tracking" again
    once a view joins it to the world, and "lost" (the last pose repeated) in between; its TagMap flags
    the fragment's tags until the join."""
    from shared.wire.messages import CameraPose, TagMap, decode, encode

    node = SlamNode(SlamServiceSettings(run_dir=tmp_path))
    poses = _constant_velocity(70)
    statuses = []
    for i in range(70):
        wanted = {4, 5} if i < 10 else set() if i < 45 else {7} if i < 55 else {5, 7}
        cam = decode(encode(node.on_poses(_tag_poses(i, 1_000 + i, poses[i], wanted))[0]), CameraPose)
        statuses.append(cam.status)
        if i in (54, 69):  # the map says which tags are placed by the gap's guess, until the join
            published = decode(encode(node.current_map("r1")), TagMap)
            flags = {t.tag_id: t.bridged for t in published.tags}
            assert flags == ({4: False, 5: False, 7: True} if i == 54 else {4: False, 5: False, 7: False})
            # ... and how well it knows each pose (TagMap/v3): none for the anchor or a bridged tag
            known = {t.tag_id for t in published.tags if t.position_sigma_m and t.rotation_sigma_deg}
            assert known == {t for t, bridged in flags.items() if not bridged} - {published.anchor_tag_id}
        assert (cam.covariance_world is None) == (cam.status == "lost")  # a repeated pose says nothing
    assert statuses == ["tracking"] * 10 + ["lost"] * 35 + ["bridged"] * 10 + ["tracking"] * 15


def _plan_run(plan: dict[range, set[int]], settings: SlamSettings | None = None) -> tuple[MarkerSlam, str]:
    """Exact views of the tags the plan names per frame range; the statuses' first letters."""
    poses = _constant_velocity(70)
    slam = MarkerSlam(settings or SlamSettings())
    letters = ""
    for i in range(70):
        wanted = next((tags for frames, tags in plan.items() if i in frames), set())
        letters += slam.update(i, i, [_exact_obs(*v) for v in _visible(poses[i]) if v[0] in wanted]).status[0]
    return slam, letters


def test_a_bridged_robot_that_sees_only_world_tags_next_joins_its_fragment() -> None:
    """Right after the fragment's frames the motion prior holds the robot to them: a frame that sees
    only a world tag joins the fragment (its link goes), and the fragment's tag is world afterwards."""
    slam, letters = _plan_run({range(10): {4, 5}, range(45, 52): {7}, range(52, 56): {5}, range(56, 70): {7}})
    assert letters == "t" * 10 + "l" * 35 + "b" * 7 + "t" * 18
    assert not slam.bridged(46) and slam.state.fragments == 1


def test_a_bridged_fragment_joins_the_world_at_the_first_view_of_a_world_tag() -> None:
    """The fragment's last pose is the long gap's guess, metres from the truth: the first view of a
    world tag is the join, not a jump (a review found the jump test blocking it: 2 m off for good)."""
    slam, letters = _plan_run({range(10): {4, 5}, range(45, 52): {7}, range(52, 56): {5}})
    assert slam.state.jumps == 0 and not slam.bridged(46) and letters[45:56] == "b" * 7 + "t" * 4
    traj = _constant_velocity(70)
    ate, n = absolute_trajectory_error(dict(slam.trajectory()), dict(enumerate(traj)))  # (the anchor's world)
    assert n == 21 and ate < 1e-3, (n, ate)


def test_new_tags_right_after_a_fragment_starts_belong_to_it() -> None:
    """The frame after a fragment's first has no motion to extrapolate (one pose since the gap): it is
    held still from that pose in the same fragment, not a second fragment; one join ties both tags."""
    slam, letters = _plan_run({range(10): {4, 5}, range(45, 46): {7}, range(46, 55): {6, 8}, range(55, 60): {5, 6}})
    assert slam.state.fragments == 1
    assert letters[45:55] == "b" * 10 and letters[55:60] == "t" * 5
    assert not any(slam.bridged(i) for i in range(45, 60))


def test_frames_that_leave_the_graph_while_bridged_stay_bridged() -> None:
    """Bounded memory during an unjoined fragment: frames marginalised before the join are final as
    they were (placed by the gap's guess), so they stay flagged; the frames still in the graph join."""
    slam, letters = _plan_run(
        {range(10): {4, 5}, range(45, 55): {7}, range(55, 60): {5, 7}, range(60, 70): {7}},
        SlamSettings(window_frames=8),
    )
    assert letters[45:55] == "b" * 10 and letters[55:] == "t" * 15
    assert slam.bridged(45) and slam.bridged(50)
    assert not slam.bridged(9) and not slam.bridged(65)


def _soft_run(settings: SlamSettings, *, known: bool, frames: int = 10) -> tuple[MarkerSlam, int, list[int]]:
    """A constant-velocity run whose one tag in view throughout is read blind (proposer "lines_soft"),
    the others detected; with or without the scene as a known map. Returns slam, the soft tag, and the
    tags used per frame."""
    poses = _constant_velocity(70)[:frames]
    soft = max(set.intersection(*({t for t, _, _ in _visible(p)} for p in poses)))  # in view throughout
    tag_map = {t.id: (t.size_m, t.pose()) for t in SCENE.tags} if known else None
    slam = MarkerSlam(settings, known_tags=tag_map)
    used = []
    for i, pose in enumerate(poses):
        obs = [
            Observation(t, size, cft, 0.0, cft, 5.0, proposer="lines_soft" if t == soft else "apriltag")
            for t, size, cft in _visible(pose)
        ]
        used.append(slam.update(i, i, obs).tags_used)
    return slam, soft, used


def test_blind_soft_reads_map_nothing_and_localise_only_against_a_known_map() -> None:
    """Tags the line quads read blind (proposer "lines_soft") carry biased keypoints. By default
    ("localise") slam measures no tag from them: without a known map they are left out (counted), and
    with one they too are left out where detected tags place the frame. "ignore" leaves them out,
    "map" fuses them like any other view."""
    n = [len(_visible(p)) for p in _constant_velocity(70)[:10]]
    for known in (False, True):
        slam, soft, used = _soft_run(SlamSettings(), known=known)
        assert used == [k - 1 for k in n] and (soft in slam.tags) == known  # known: the map's pose, seeded
        assert slam.state.soft_reads_skipped == 10 and slam.state.soft_reads_localised == 0
    slam, soft, used = _soft_run(SlamSettings(soft_reads="ignore"), known=True)
    assert used == [k - 1 for k in n] and soft not in slam.tags and slam.state.soft_reads_skipped == 10
    slam, soft, used = _soft_run(SlamSettings(soft_reads="map"), known=False)
    assert soft in slam.tags and used == n and slam.state.soft_reads_skipped == 0


def test_a_soft_read_of_a_surveyed_tag_alone_poses_the_frame() -> None:
    """Frames whose only tag is a blind soft read of a surveyed tag: posed from it (exactly, for an exact
    read), status tracking, counted. A tag the map states loosely (10 cm) places nothing: those frames
    are lost."""
    poses = _constant_velocity(40)
    tag_map = {t.id: (t.size_m, t.pose()) for t in SCENE.tags}
    first = _visible(poses[0])[0][0]
    soft = min(set.intersection(*({t for t, _, _ in _visible(p)} for p in poses[:30])) - {first})

    def run(sigmas: dict[int, tuple[float | None, float | None]]) -> tuple[MarkerSlam, list[FrameResult]]:
        slam = MarkerSlam(SlamSettings(), known_tags=tag_map, known_sigmas=sigmas)
        out = []
        for i in range(30):
            obs = []
            for t, size, cft in _visible(poses[i]):
                if t == soft:
                    obs.append(Observation(t, size, cft, 0.0, cft, 5.0, proposer="lines_soft"))
                elif i < 10:  # frames 10-29: only the soft read
                    obs.append(_exact_obs(t, size, cft))
            out.append(slam.update(i, i, obs))
        return slam, out

    slam, results = run({})
    for i in range(10, 30):
        r = results[i]
        assert r.status == "tracking" and r.tags_used == 1 and r.world_from_camera is not None
        np.testing.assert_allclose(r.world_from_camera, poses[i], atol=1e-6)
    assert slam.state.soft_reads_localised == 20
    slam, results = run({soft: (float(np.radians(5.0)), 0.10)})
    assert all(r.status == "lost" for r in results[10:]) and slam.state.soft_reads_localised == 0


def test_a_biased_soft_read_moves_no_tag() -> None:
    """A soft read 5 cm off, always in view with a new tag that detected views map: the new tag ends
    exactly where it is ("localise": the read places no frame a detection places, and no tag is mapped
    in a frame it places), where fused as a view ("map") the read drags it over 1 cm."""
    poses = _constant_velocity(40)
    vis = [t for t, _, _ in _visible(poses[0])]
    anchor, soft, new = vis[0], vis[1], vis[2]
    assert all(new in {t for t, _, _ in _visible(p)} and soft in {t for t, _, _ in _visible(p)} for p in poses[:10])
    tag_map = {t.id: (t.size_m, t.pose()) for t in SCENE.tags if t.id in (anchor, soft)}
    shifted = make_pose(np.eye(3), [0.05, 0.0, 0.0])
    moved = {}
    for mode in ("localise", "map"):
        slam = MarkerSlam(SlamSettings(soft_reads=mode, anchor_tag_id=anchor), known_tags=tag_map)
        for i in range(10):
            obs = []
            for t, size, cft in _visible(poses[i]):
                if t == soft:
                    m = cft @ shifted
                    obs.append(Observation(t, size, m, 0.0, m, 5.0, proposer="lines_soft"))
                elif t == new or (t == anchor and i < 2):
                    obs.append(_exact_obs(t, size, cft))
            slam.update(i, i, obs)
        moved[mode] = float(np.linalg.norm(slam.tag_map()[new][1][:3, 3] - SCENE_TAGS[new][:3, 3]))
    assert moved["localise"] < 1e-3 < 0.01 < moved["map"], moved


def test_a_soft_read_places_the_camera_as_the_same_view_of_a_held_tag_would() -> None:
    """Localisation-only on a map held to 1 um, where a tag cannot move, frames 4-13 seen by one soft read
    alone: the read as a camera prior ("localise": Ad_m (S + S_tag) Ad_m^T) and as a view of the tag
    ("map") give the same poses and covariances. A wrong transform of S (none, or Ad of m^-1) fails."""
    poses = _constant_velocity(70)[:14]
    soft = max(set.intersection(*({t for t, _, _ in _visible(p)} for p in poses)))
    tag_map = {t.id: (t.size_m, t.pose()) for t in SCENE.tags}
    out = {}
    for mode in ("localise", "map"):
        rng = np.random.default_rng(3)
        settings = SlamSettings(soft_reads=mode, localisation_only=True, known_tag_sigma=1e-6)
        slam = MarkerSlam(settings, known_tags=tag_map)
        res = []
        for i, pose in enumerate(poses):
            obs = []
            for t, size, cft in _visible(pose):
                o = _noisy_obs(t, size, cft, rng, 0.3)
                if t == soft and i >= 4:
                    obs.append(dataclasses.replace(o, proposer="lines_soft"))
                elif t != soft and i < 4:
                    obs.append(o)
            res.append(slam.update(i, i, obs))
        out[mode] = res
    for a, b in zip(out["localise"], out["map"], strict=True):
        assert a.world_from_camera is not None and b.world_from_camera is not None
        assert a.covariance_world is not None and b.covariance_world is not None
    # iSAM2 relinearises every 10th update: from then on the two agree (before, their linearisation
    # points differ and so do the early frames' estimates, by up to 4 mm)
    for a, b in list(zip(out["localise"], out["map"], strict=True))[10:]:
        assert a.world_from_camera is not None and b.world_from_camera is not None
        assert a.covariance_world is not None and b.covariance_world is not None
        np.testing.assert_allclose(a.world_from_camera, b.world_from_camera, atol=1e-4)
        np.testing.assert_allclose(np.diag(a.covariance_world), np.diag(b.covariance_world), rtol=1e-3)


def test_a_camera_prior_is_the_view_of_a_held_tag_at_every_camera_pose() -> None:
    """camera_prior's covariance transform, exactly: for a tag held fixed, the prior's Mahalanobis
    distance equals BetweenFactor(camera, tag, m)'s at any camera pose, also far from the prior (where a
    first-order stand-in would not)."""
    rng = np.random.default_rng(7)
    wt = make_pose(cv2.Rodrigues(np.array([0.2, -1.1, 0.4]))[0], [1.0, 2.5, 1.2])
    m = make_pose(cv2.Rodrigues(np.array([2.9, 0.3, -0.2]))[0], [0.2, -0.1, 2.7])
    a = rng.normal(size=(6, 6))
    view = a @ a.T * 1e-4 + np.eye(6) * 1e-6
    prior, cov = camera_prior(wt, m, view, np.zeros((6, 6)))
    np.testing.assert_allclose(prior, wt @ np.linalg.inv(m), atol=1e-12)
    between = gtsam.BetweenFactorPose3(0, 1, gtsam.Pose3(m), gtsam.noiseModel.Gaussian.Covariance(view))
    held = gtsam.PriorFactorPose3(0, gtsam.Pose3(prior), gtsam.noiseModel.Gaussian.Covariance(cov))
    for scale in (1e-3, 0.05, 0.3):
        v = gtsam.Values()
        v.insert(0, gtsam.Pose3(prior).retract(scale * rng.normal(size=6)))
        v.insert(1, gtsam.Pose3(wt))
        assert held.error(v) == pytest.approx(between.error(v), rel=1e-6)


def test_a_known_tag_a_lost_frame_seeded_is_in_the_graph_next_time() -> None:
    """A frame whose only tag is an ambiguous soft read of a known tag, with nothing to choose its branch
    by, is lost; the tag it seeded from the map is in the graph all the same, so its next view is fused."""
    poses = _constant_velocity(70)
    tag_map = {t.id: (t.size_m, t.pose()) for t in SCENE.tags}
    slam = MarkerSlam(SlamSettings(), known_tags=tag_map)
    first = _visible(poses[0])
    slam.update(0, 0, [_exact_obs(*first[0])])
    tag, size, cft = _visible(poses[1])[-1]
    assert tag != slam.anchor and tag not in slam.tags
    ambiguous = Observation(tag, size, cft, 0.05, cft, 0.05, proposer="lines_soft")
    assert slam.update(1, 1, [ambiguous]).status == "lost"
    res = slam.update(2, 2, [_exact_obs(*v) for v in _visible(poses[2]) if v[0] == tag])
    assert res.status == "tracking" and res.world_from_camera is not None
    np.testing.assert_allclose(res.world_from_camera, poses[2], atol=1e-6)


def test_a_frame_placed_by_soft_reads_alone_maps_no_new_tag() -> None:
    """A frame whose camera only a soft read of a known tag places, with a tag the map lacks also in
    view: the frame is posed, the new tag is not mapped from it (it would inherit the soft read's bias);
    seen with a detected known tag, it is."""
    poses = _constant_velocity(70)
    vis = [t for t, _, _ in _visible(poses[10])]
    soft, new = vis[0], vis[-1]
    assert soft != new
    tag_map = {t.id: (t.size_m, t.pose()) for t in SCENE.tags if t.id != new}
    slam = MarkerSlam(SlamSettings(), known_tags=tag_map)
    for i in range(10):
        slam.update(i, i, [_exact_obs(*v) for v in _visible(poses[i]) if v[0] not in (soft, new)])
    views = {t: (t, size, cft) for t, size, cft in _visible(poses[10])}
    t, size, cft = views[soft]
    res = slam.update(
        10, 10, [Observation(t, size, cft, 0.0, cft, 5.0, proposer="lines_soft"), _exact_obs(*views[new])]
    )
    assert res.status == "tracking" and res.tags_used == 1 and new not in slam.tags
    res = slam.update(11, 11, [_exact_obs(*v) for v in _visible(poses[11])])
    assert new in slam.tags


def test_tracked_views_localise_against_a_surveyed_map_and_fuse_only_when_told() -> None:
    """Frames whose only tag is one the tracker carried: by default ("localise") a tracked view places the
    frame against a surveyed map (exactly, for an exact view; counted) and nothing otherwise (SLAM's own
    map: lost, counted skipped); "map" fuses it like a detection, "ignore" leaves it out."""
    poses = _constant_velocity(40)
    tag_map = {t.id: (t.size_m, t.pose()) for t in SCENE.tags}
    first = _visible(poses[0])[0][0]
    carried = min(set.intersection(*({t for t, _, _ in _visible(p)} for p in poses[:30])) - {first})

    def run(settings: SlamSettings, known: bool) -> tuple[MarkerSlam, list[FrameResult]]:
        slam = MarkerSlam(settings, known_tags=tag_map if known else None)
        out = []
        for i in range(30):
            obs = []
            for t, size, cft in _visible(poses[i]):
                if t == carried and i >= 10:  # frames 10-29: only the tracked view
                    obs.append(Observation(t, size, cft, 0.0, cft, 5.0, tracked=True, proposer="tracker"))
                elif i < 10:
                    obs.append(_exact_obs(t, size, cft))
            out.append(slam.update(i, i, obs))
        return slam, out

    slam, results = run(SlamSettings(), known=True)
    for i in range(10, 30):
        r = results[i]
        assert r.status == "tracking" and r.tags_used == 1 and r.world_from_camera is not None
        np.testing.assert_allclose(r.world_from_camera, poses[i], atol=1e-6)
    assert (slam.state.tracked_localised, slam.state.tracked_skipped) == (20, 0)
    slam, results = run(SlamSettings(), known=False)
    assert all(r.status == "lost" for r in results[10:])
    assert (slam.state.tracked_localised, slam.state.tracked_skipped) == (0, 20)
    slam, results = run(SlamSettings(tracked_reads="map"), known=False)
    assert all(r.status == "tracking" and r.tags_used == 1 for r in results[10:])
    assert (slam.state.tracked_localised, slam.state.tracked_skipped) == (0, 0)
    slam, results = run(SlamSettings(tracked_reads="ignore"), known=True)
    assert all(r.status == "lost" for r in results[10:]) and slam.state.tracked_skipped == 20
    assert slam.state.soft_reads_skipped == slam.state.soft_reads_localised == 0  # counted apart


def test_the_old_soft_reads_switch_still_reads() -> None:
    assert SlamSettings.model_validate({"use_soft_reads": True}).soft_reads == "map"
    assert SlamSettings.model_validate({"use_soft_reads": False}).soft_reads == "ignore"
    assert SlamSettings.model_validate({"use_soft_reads": "false"}).soft_reads == "ignore"  # from an env var


def test_rerun_draws_bridged_poses_apart_from_the_worlds(tmp_path: Path) -> None:
    """A real recording: tracking poses at world/camera, bridged ones at world/camera_bridged, a pose's
    2-sigma position ellipsoid at world/camera_sigma."""
    from shared.viz.recording import RerunSettings, RerunViz, recording_entities

    viz = RerunViz(RerunSettings(enabled=True), service="slam", run_dir=tmp_path)
    viz.camera_pose(1_000, np.eye(4), CAM)
    viz.camera_pose(2_000, make_pose(np.eye(3), [1.0, 0.0, 0.0]), CAM, bridged=True)
    viz.camera_pose(3_000, np.eye(4), None, covariance_world=np.diag([1e-4, 4e-4, 9e-4, 1e-5, 1e-5, 1e-5]))
    # tags coloured and labelled by who found them (a tracked tag, a blind soft read, one not said)
    from tests.examples import example_messages

    poses = cast(TagPoses, example_messages()[TagPoses.SCHEMA])
    tags = [poses.tags[0], poses.tags[0].model_copy(update={"tracked": False, "proposer": "lines_soft"})]
    viz.tag_poses(poses.model_copy(update={"tags": [*tags, tags[0].model_copy(update={"proposer": None})]}))
    viz.close()
    entities = recording_entities(tmp_path / "slam.rrd")
    assert {"/world/camera", "/world/camera_bridged", "/world/camera_sigma", "/camera/image/tag_quads"} <= entities
    # read back from Python with rerun-sdk's chunk reader (README; a trial found no API named for it)
    from shared.viz.recording import recording_scalars

    e2e = recording_scalars(tmp_path / "slam.rrd", "/latency/capture_to_pose_ms")
    assert e2e == [(poses.capture_nanos, pytest.approx(1e3 * poses.timings.capture_to_pose_secs))]


def test_a_restarted_process_keeps_the_dead_ones_recording(tmp_path: Path) -> None:
    """A restarted service re-created its .rrd part and the merged recording lost everything before the
    restart (a fleet trial: slam's poses before its kill were gone); each process now writes a part of its own."""
    from shared.viz.recording import RerunSettings, RerunViz, merge_recordings, recording_entities

    first = RerunViz(RerunSettings(enabled=True), service="slam", run_dir=tmp_path)
    first.camera_pose(1_000, np.eye(4), CAM)
    first.close()  # a SIGKILL leaves what was flushed; close() is the clean case of it
    second = RerunViz(RerunSettings(enabled=True), service="slam", run_dir=tmp_path)
    second.camera_pose(2_000, np.eye(4), CAM, bridged=True)
    second.close()
    assert (first.path.name, second.path.name) == ("slam.rrd", "slam.2.rrd")
    merged = merge_recordings(tmp_path)
    assert merged is not None and {"/world/camera", "/world/camera_bridged"} <= recording_entities(merged)


def test_a_long_recording_goes_on_in_new_parts_and_keeps_its_latest_within_keep_mb(tmp_path: Path) -> None:
    """Rerun's file sink keeps an index of every chunk until its file closes: one file per process grew
    slam and edge_infer by ~2 MB a minute (a fresh-clone soak). Each process rotates its part every
    rotate_secs (the clock injected), nothing is lost across a rotation, and keep_mb deletes the oldest."""
    from shared.viz.recording import RerunSettings, RerunViz, merge_recordings, recording_scalars

    now = [0.0]
    viz = RerunViz(
        RerunSettings(enabled=True, rotate_secs=10), service="slam", run_dir=tmp_path, clock_secs=lambda: now[0]
    )
    for i in range(50):
        now[0] = i * 1.0  # a frame a second: a new part every 10 s
        viz.scalars(1_000 + i, {"latency/x_ms": float(i)})
    viz.close()
    assert [p.name for p in viz.parts] == ["slam.rrd", *(f"slam.{n}.rrd" for n in range(2, 6))]
    merged = merge_recordings(tmp_path)
    assert merged is not None
    assert recording_scalars(merged, "/latency/x_ms") == [(1_000 + i, float(i)) for i in range(50)]

    kept = tmp_path / "kept"
    now[0] = 100.0
    viz = RerunViz(
        RerunSettings(enabled=True, rotate_secs=10, keep_mb=1e-6),
        service="slam",
        run_dir=kept,
        clock_secs=lambda: now[0],
    )
    for i in range(50):
        now[0] = 100.0 + i
        viz.scalars(1_000 + i, {"latency/x_ms": float(i)})
    viz.close()
    # every closed part is over the budget (a byte): each rotation deletes them, the latest stretch survives
    assert viz.dropped_parts == 4 and [p.name for p in kept.glob("*.rrd")] == ["slam.5.rrd"]
    assert [v for _, v in recording_scalars(kept / "slam.5.rrd", "/latency/x_ms")] == [float(i) for i in range(40, 50)]


def test_a_failing_checkpoint_is_counted_said_once_and_its_recovery_said(caplog: pytest.LogCaptureFixture) -> None:
    from services.slam.service import CheckpointWrites

    writes = CheckpointWrites()
    outcomes = iter([None, PermissionError("read-only"), OSError("full"), ValueError("odd"), None, None])

    def write() -> None:
        if (outcome := next(outcomes)) is not None:
            raise outcome

    with caplog.at_level("WARNING"):
        for _ in range(6):
            writes.write(write)
    assert (writes.failed, writes.failing) == (3, False)
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 2 and "PermissionError: read-only" in said[0] and "again after 3 failed" in said[1], said


def test_the_anchor_is_the_tag_whose_pose_the_first_view_pins_best() -> None:
    """The world is the anchor's frame, so the anchor is the best-determined view (near, face-on), not
    the one with the luckiest reprojection error: here the near tag fits worse (0.3 vs 0.01 px)."""
    near = make_pose(cv2.Rodrigues(np.array([0.1, 0.2, 0.0]))[0], [0.2, 0.0, 1.2])
    far = make_pose(cv2.Rodrigues(np.array([0.1, -0.2, 0.0]))[0], [-0.4, 0.0, 3.5])
    slam = MarkerSlam(SlamSettings())
    slam.update(0, 0, [Observation(1, 0.15, near, 0.3, near, 5.0), Observation(2, 0.15, far, 0.01, far, 5.0)])
    assert slam.anchor == 1


def test_a_checkpoint_keeps_a_bridged_tags_size_but_not_its_guessed_pose(tmp_path: Path) -> None:
    """map.json is what a restarted slam resumes from, every pose in it a world prior: a tag of an
    unjoined fragment goes in with its size only, so a restart does not pin the gap's guess."""
    node = SlamNode(SlamServiceSettings(run_dir=tmp_path))
    poses = _constant_velocity(70)
    for i in range(55):
        wanted = {4, 5} if i < 10 else set() if i < 45 else {7}
        node.on_poses(_tag_poses(i, 1_000 + i, poses[i], wanted))
    node.write_outputs(tmp_path)
    saved = {t.id: t for t in load_tag_map(tmp_path / "map.json").tags}
    assert set(saved) == {4, 5, 7}
    assert saved[4].pose() is not None and saved[7].pose() is None and saved[7].size_m > 0
    assert saved[7].stated_sigmas() == (None, None)  # a bridged tag states nothing
    again = SlamNode(SlamServiceSettings(run_dir=tmp_path))  # the restarted process
    assert set(again.slam.known) == {4, 5}
    again.write_outputs(tmp_path)  # a tag of the checkpoint not seen again keeps its size (and sigmas)
    resaved = {t.id: t for t in load_tag_map(tmp_path / "map.json").tags}
    assert set(resaved) == {4, 5, 7}
    for t in (4, 5):
        assert resaved[t].stated_sigmas() == saved[t].stated_sigmas()


def test_with_bridging_off_new_tags_after_a_long_gap_stay_lost() -> None:
    _, _, statuses = _fragment_run(SlamSettings(bridge_long_gaps=False))
    assert all(statuses[i] == "lost" for i in range(10, 55))
    assert all(statuses[i] == "tracking" for i in range(55, 60))  # tag 5 relocalises


def test_the_observation_covariance_matches_the_scatter_of_real_pnp() -> None:
    """pnp_covariance against Monte Carlo: 16 lattice keypoints with Gaussian pixel noise through
    OpenCV's IPPE (the product's PnP), at a near, a far and a tilted view; per tangent axis the
    empirical standard deviation is within 20 % of the modelled one (2000 draws: sampling error ~3 %),
    and at 1-1.8 m the errors whitened by the modelled covariance have about the identity covariance
    (at 3 m the fit is no longer linear in the noise: whitened, one direction has 1.8x the variance and
    the mean is off by 0.5 sigma; the per-axis spread still matches).
    Of the two IPPE branches the one nearer the truth counts: far away, noise makes IPPE choose the
    other one at times, and that flip is modelled apart (MarkerSlam.noise)."""
    from shared.slam.marker_slam import pnp_covariance

    rng = np.random.default_rng(3)
    size, sigma_px = 0.15, 0.5
    views = [
        make_pose(cv2.Rodrigues(np.array([0.2, -0.1, 0.05]))[0], [0.1, -0.05, 1.0]),
        make_pose(cv2.Rodrigues(np.array([0.1, 0.2, 0.0]))[0], [-0.3, 0.2, 3.0]),
        make_pose(cv2.Rodrigues(np.array([0.0, 0.9, 0.1]))[0], [0.2, 0.1, 1.8]),
    ]
    for cft in views:
        clean = project(CAM, cft, lattice_in_tag(size))
        errors = []
        for _ in range(2000):
            fit = solve_planar_pnp(CAM, lattice_in_tag(size), clean + rng.normal(0, sigma_px, clean.shape))
            branches = [
                np.asarray(gtsam.Pose3.Logmap(gtsam.Pose3(cft).between(gtsam.Pose3(m))))
                for m in (fit.camera_from_tag, fit.alt_camera_from_tag)
            ]
            errors.append(min(branches, key=lambda e: float(np.linalg.norm(e[:3]))))
        cov = pnp_covariance(cft, size, CAM.fx, sigma_px)
        np.testing.assert_allclose(np.std(np.array(errors), axis=0), np.sqrt(np.diag(cov)), rtol=0.2)
        if cft[2, 3] < 2.5:  # ... and the correlations: whitened by the model, about the identity
            whitened = np.array(errors) @ np.linalg.inv(np.linalg.cholesky(cov)).T
            np.testing.assert_allclose(np.cov(whitened.T), np.eye(6), atol=0.25)


def test_the_pose_log_keeps_poses_compactly_in_stamp_order() -> None:
    from shared.vision.trajectory import PoseLog

    log = PoseLog()
    poses = _constant_velocity(50)
    log.extend([100 + i for i in range(25, 50)], poses[25:])
    for i in range(25):  # late arrivals: still returned in stamp order
        log.append(100 + i, poses[i])
    stamps, back = log.arrays()
    assert stamps.tolist() == [100 + i for i in range(50)] and len(log) == 50
    np.testing.assert_allclose(back, np.array(poses), atol=1e-6)
    per_pose = (log._stamps.nbytes + log._positions.nbytes + log._quats.nbytes) / len(log._stamps)
    assert per_pose <= 52


def _feed(node: SlamNode, poses: list[np.ndarray], frames: range, source_ns: list[int], unstamped: int = -1) -> None:
    """Frames `frames` with their data-set stamps (but `unstamped`'s), ground truth and exact views."""
    for i in frames:
        if i != unstamped:
            node.on_frame_stamp(1_000 + i, source_ns[i])
        node.on_ground_truth(1_000 + i, poses[i])
        node.on_poses(_tag_poses(i, 1_000 + i, poses[i]))


def test_trajectory_is_written_in_the_data_sets_time_when_every_frame_has_it(tmp_path: Path) -> None:
    """A folder source with rgb.txt sends each frame's data-set time (FrameStamp): trajectory.tum and
    groundtruth.tum come out in that time, so a TUM tool compares them with the data set's ground truth
    as it is. A frame whose stamp never came is left out, said and counted (an EKF integrator's trial:
    2 of 402 without one put the whole file in capture time, and evo_ape against the data set failed);
    a run with stamps for fewer than half its poses is written in capture time (said in slam.json)."""
    poses = _constant_velocity(12)
    source_ns = [1_305_031_102_175_304_000 + i * 33_333_333 for i in range(12)]
    node = SlamNode(SlamServiceSettings(run_dir=tmp_path))
    _feed(node, poses, range(12), source_ns)
    node.write_outputs(tmp_path)
    stamps = [t for t, _ in read_tum(tmp_path / "trajectory.tum")]
    np.testing.assert_allclose(stamps, np.array(source_ns) / 1e9, rtol=0, atol=1e-6)
    # exactly the data set's stamps (a float second of this size is only good to ~0.2 us)
    for name in ("trajectory.tum", "groundtruth.tum"):
        written = [line.split()[0] for line in (tmp_path / name).read_text().splitlines()]
        assert written == [f"{t // 10**9}.{t % 10**9:09d}" for t in source_ns], name
    np.testing.assert_allclose([t for t, _ in read_tum(tmp_path / "groundtruth.tum")], stamps, rtol=0, atol=1e-6)
    assert json.loads((tmp_path / "slam.json").read_text())["time"] == "data set (rgb.txt or the video's own)"

    node.on_poses(_tag_poses(12, 1_012, poses[11]))  # no stamp came for this one
    node.write_outputs(tmp_path)
    written = [line.split()[0] for line in (tmp_path / "trajectory.tum").read_text().splitlines()]
    assert written == [f"{t // 10**9}.{t % 10**9:09d}" for t in source_ns]
    stats = json.loads((tmp_path / "slam.json").read_text())
    assert stats["time"] == "data set (rgb.txt or the video's own)" and stats["poses_without_data_set_stamp"] == 1
    for i in range(13, 26):  # most frames without: capture time
        node.on_poses(_tag_poses(i, 1_000 + i, poses[11]))
    node.write_outputs(tmp_path)
    assert read_tum(tmp_path / "trajectory.tum")[0][0] == pytest.approx(1_000e-9)
    assert json.loads((tmp_path / "slam.json").read_text())["time"] == "capture"


def test_a_restarted_slam_keeps_the_time_its_files_are_in(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A resumed trajectory in the data set's time, continued by a process with a frame that has no
    data-set stamp, used to switch the run to capture time: the new stamps never passed the old file's
    last, and nothing was appended again, silently (review). The resumed time base is kept."""
    poses = _constant_velocity(20)
    source_ns = [1_305_031_102_175_304_000 + i * 33_333_333 for i in range(20)]
    first = SlamNode(SlamServiceSettings(run_dir=tmp_path))
    _feed(first, poses, range(10), source_ns)
    first.write_outputs(tmp_path)
    second = SlamNode(SlamServiceSettings(run_dir=tmp_path))
    _feed(second, poses, range(10, 20), source_ns, unstamped=15)  # frame 15's stamp never came
    with caplog.at_level("WARNING", logger="services.slam.service"):
        stats = second.write_outputs(tmp_path)
    expected = [f"{t // 10**9}.{t % 10**9:09d}" for i, t in enumerate(source_ns) if i != 15]
    for name in ("trajectory.tum", "groundtruth.tum"):
        assert [line.split()[0] for line in (tmp_path / name).read_text().splitlines()] == expected, name
    assert stats["time"] == "data set (rgb.txt or the video's own)"
    assert stats["ate_frames"] == 19 and stats["poses"] == 19
    assert "1 of this process's poses have no data-set stamp and are left out" in caplog.text


def test_a_looped_source_wraps_as_a_new_camera_session_not_a_motion(tmp_path: Path) -> None:
    """A data-set trial looped a folder whose path spans 1 m: at 10 fps the wrap was within the motion
    envelope (no jump), and the constant-velocity prior bent the poses around every wrap (11-54 cm off
    under a 2 cm sigma). The camera now starts seq again at each pass, a new camera session for slam:
    the second pass's poses are the first's. Here 0.8 m at 10 fps: seq going on reads up to 18 cm off."""
    n = 30
    path = [
        look_at(np.array([-0.4 + 0.8 * i / n, 0.4, 1.2]), np.array([0.6 + 0.8 * i / n, 3.0, 1.3])) for i in range(n)
    ]
    for restarted in (True, False):
        node = SlamNode(SlamServiceSettings(run_dir=tmp_path / str(restarted)))
        online: dict[tuple[int, int], np.ndarray] = {}
        for k in range(2 * n):
            seq = k % n if restarted else k
            res = node.on_poses(_tag_poses(seq, 10**12 + k * 100_000_000, path[k % n]))[0]
            assert res.status == "tracking"
            online[(k // n, k % n)] = res.world_from_camera[:3, 3]
        worst = max(float(np.linalg.norm(online[(1, i)] - online[(0, i)])) for i in range(n))
        assert (worst < 1e-4) if restarted else (worst > 0.05), (restarted, worst)


def test_the_published_covariance_is_scaled_as_configured(tmp_path: Path) -> None:
    """The marginal is pessimistic on purpose (a data-set trial measured NEES 0.24 where 3 is calibrated);
    `covariance_scale` lets an EKF user publish it calibrated to what a run with ground truth measured."""
    poses = _constant_velocity(6)
    plain = SlamNode(SlamServiceSettings(run_dir=tmp_path / "a"))
    scaled = SlamNode(SlamServiceSettings(run_dir=tmp_path / "b", covariance_scale=0.08))
    for i in range(6):
        a = plain.on_poses(_tag_poses(i, 1_000 + i, poses[i]))[0]
        b = scaled.on_poses(_tag_poses(i, 1_000 + i, poses[i]))[0]
    assert a.covariance_world is not None and b.covariance_world is not None
    np.testing.assert_allclose(b.covariance_world, 0.08 * np.asarray(a.covariance_world), rtol=1e-9)
    with pytest.raises(ValueError, match="greater than 0"):
        SlamServiceSettings(run_dir=tmp_path, covariance_scale=0)


def test_stamp_map_looks_up_capture_times() -> None:
    m = StampMap()
    for i in range(300):  # past the first growth
        m.add(5_000 - i, 10 * i)
    values, found = m.lookup(np.array([5_000, 4_701, 7, 4_999]))
    assert found.tolist() == [True, True, False, True]
    assert values.tolist() == [0, 2_990, 7, 10]
    assert StampMap().lookup(np.array([3]))[1].tolist() == [False]


def test_two_robots_share_one_map_and_keep_their_own_trajectories() -> None:
    """Two robots in one graph: the second is lost until it sees a tag the first mapped, then localised
    in the same world; its own motion prior, frame indices and marginalised log; tags only the second
    robot sees join the shared map; both trajectories stay exact across the bounded window."""
    anchor = SCENE.tags[3]
    slam = MarkerSlam(
        SlamSettings(anchor_tag_id=anchor.id, window_frames=40),
        known_tags={anchor.id: (anchor.size_m, anchor.pose())},
    )
    traj = _constant_velocity(90)
    first, second = traj[:25], traj[20:]  # the second robot starts near the first's end and goes on
    seen_first: set[int] = set()
    for i in range(90):  # interleaved, the second robot starting later (its frame indices from 0)
        if i < 25:
            obs = [_exact_obs(*v) for v in _visible(first[i])]
            seen_first |= {o.tag_id for o in obs}
            res = slam.update(i, 1_000 + i, obs, robot="r1")
            if res.world_from_camera is not None:
                np.testing.assert_allclose(res.world_from_camera, first[i], atol=1e-3)
        if i >= 20:
            j = i - 20
            res2 = slam.update(j, 5_000 + j, [_exact_obs(*v) for v in _visible(second[j])], robot="r2")
            assert res2.status == "tracking", f"r2 frame {j}"
            assert res2.world_from_camera is not None
            np.testing.assert_allclose(res2.world_from_camera, second[j], atol=1e-3)
    assert slam.robots == ["r1", "r2"]
    seen_second = {v[0] for j in range(70) for v in _visible(second[j])}
    assert seen_second - seen_first, "the second robot should see a tag the first did not"
    assert seen_first | seen_second <= set(slam.tag_map())
    for robot, truth, offset in (("r1", first, 1_000), ("r2", second, 5_000)):
        got = slam.trajectory(robot)
        assert [s for s, _ in got] == sorted(s for s, _ in got)
        for stamp, pose in got:
            np.testing.assert_allclose(pose, truth[stamp - offset], atol=2e-3)
    # The frame index of one robot does not collide with the other's, a repeat of either does.
    with pytest.raises(SlamInputError, match="already fused"):
        slam.update(24, 1_024, [], robot="r1")


def test_a_robot_that_never_saw_a_mapped_tag_is_lost_not_placed_in_a_second_world() -> None:
    slam = MarkerSlam(SlamSettings())
    traj = _constant_velocity(60)
    for i in range(5):
        slam.update(i, i, [_exact_obs(*v) for v in _visible(traj[i])], robot="a")
    unseen = [v for v in _visible(traj[59]) if v[0] not in slam.tags]
    assert unseen
    assert slam.update(0, 100, [_exact_obs(*unseen[0])], robot="b").status == "lost"


def test_a_velocity_no_robot_has_is_not_extrapolated() -> None:
    """The motion prior extrapolates the last two poses' velocity; when they are a frame apart yet a metre
    apart (a tracked quad gone astray, a wrong branch: 30 m/s), neither the prediction nor the
    constant-velocity factor uses it, where a robot's own pace (0.9 m/s here) is extrapolated exactly."""
    frame_ns = 33_333_333
    poses = _constant_velocity(130)  # 3 cm a frame: 0.9 m/s at 30 fps

    def run(jump_m: float) -> MarkerSlam:
        slam = MarkerSlam(SlamSettings())
        for i in range(6):
            seen = poses[i].copy()
            if i == 5:
                seen[:3, 3] += np.array([jump_m, 0.0, 0.0])
            # the views the camera at `seen` would have of the tags the true camera sees
            obs = [_exact_obs(t, size, np.linalg.inv(seen) @ SCENE_TAGS[t]) for t, size, _ in _visible(poses[i])]
            assert slam.update(i, i * frame_ns, obs).status == "tracking"
        return slam

    steady = run(0.0)
    predicted = steady.predict(6)
    assert predicted is not None and steady.anchor is not None
    np.testing.assert_allclose(SCENE_TAGS[steady.anchor] @ predicted, poses[6], atol=1e-6)
    jumped = run(1.0)
    assert jumped.anchor is not None
    last = SCENE_TAGS[jumped.anchor] @ dict(jumped.trajectory())[5 * frame_ns]
    assert np.linalg.norm(last[:3, 3] - poses[5][:3, 3]) > 0.3  # the frame did jump
    assert jumped.predict(6) is None
    assert jumped._motion_factor(jumped._track(""), 6) is None
    # The envelope grows with the stamps' gap: 0.25 m a frame is a robot's pace 100 ms apart (within
    # 0.15 + 2 m/s x 0.1 s) and no robot's 1 ns apart (only the 0.15 m margin).
    fast = _constant_velocity(16)
    for frame_gap_ns, extrapolated in ((100_000_000, True), (1, False)):
        slam = MarkerSlam(SlamSettings())
        for i in range(6):
            assert slam.update(i, i * frame_gap_ns, [_exact_obs(*v) for v in _visible(fast[i])]).status == "tracking"
        assert (slam.predict(6) is not None) == extrapolated


def test_a_world_view_right_after_a_fragment_joins_it_only_through_a_motion_factor() -> None:
    """A frame that sees only the world's tags right after a bridged fragment's frames joins the fragment
    (and drops its weak link) only when a factor ties the two frames. Where the motion prior does not
    (a velocity beyond the envelope: the fragment's last frame placed 1 m off; or the fragment's single
    frame, no velocity yet), the fragment stays bridged on its weak link instead of floating free
    (GTSAM: an indeterminate system, or poses with variances of square metres)."""
    frame_ns = 33_333_333
    poses = _constant_velocity(70)  # 1.7 m/s at 30 fps

    def run(fragment_frames: range, jump_last: bool) -> tuple[MarkerSlam, FrameResult]:
        slam = MarkerSlam(SlamSettings())
        for i in range(10):
            slam.update(i, i * frame_ns, [_exact_obs(*v) for v in _visible(poses[i]) if v[0] in (4, 5)])
        for i in fragment_frames:
            seen = poses[i].copy()
            if jump_last and i == fragment_frames[-1]:
                seen[:3, 3] += np.array([1.0, 0.0, 0.0])
            obs = [
                _exact_obs(7, size, np.linalg.inv(seen) @ SCENE_TAGS[7]) for t, size, _ in _visible(poses[i]) if t == 7
            ]
            assert slam.update(i, i * frame_ns, obs).status == "bridged"
        after = fragment_frames[-1] + 1
        res = slam.update(after, after * frame_ns, [_exact_obs(*v) for v in _visible(poses[after]) if v[0] == 5])
        return slam, res

    for frames, jump in ((range(45, 52), True), (range(45, 46), False)):
        slam, res = run(frames, jump)
        assert res.status == "tracking" and res.world_from_camera is not None
        assert slam.bridged(frames[0] * frame_ns) and slam.tag_bridged(7)  # not joined: no shared view
        assert slam._fragment_links  # the fragment's weak link stays
        # tied to the world through the link (its rotation sigma: 2 deg a frame of the gap), not floating
        link_rad = np.radians(2.0 * (frames[0] - 9))
        variances = np.diag(slam.isam.marginalCovariance(slam._track("").key(frames[-1])))
        assert variances[:3].max() < 1.1 * link_rad**2


def test_a_view_that_disagrees_with_the_tag_map_fades_where_the_map_is_the_whole_story() -> None:
    """Every tag in view surveyed, one view 3 cm off (a bad read that passes the gates): under
    map_view_kernel "cauchy" (default) it fades and the camera stays where the other views put it;
    under Huber (the kernel before, huber_k 1.5) it pulls the camera by a centimetre. With a tag the map
    does not give in the same frame, every view keeps Huber, whatever the setting (see the setting)."""
    pose = _constant_velocity(10)[5]
    vis = _visible(pose)
    assert len(vis) >= 3

    def camera_error_cm(kernel: str, *, unsurveyed_in_view: bool) -> float:
        known = {tid: (size, SCENE_TAGS[tid]) for tid, size, _ in vis[: 2 if unsurveyed_in_view else None]}
        settings = SlamSettings(anchor_tag_id=vis[0][0], map_view_kernel=kernel)
        slam = MarkerSlam(settings, known_tags=known)
        obs = [_exact_obs(*v) for v in vis]
        bad = obs[1].camera_from_tag.copy()
        bad[0, 3] += 0.03
        obs[1] = dataclasses.replace(obs[1], camera_from_tag=bad, alt_camera_from_tag=bad)
        res = slam.update(0, 0, obs)
        assert res.world_from_camera is not None
        return 100 * float(np.linalg.norm(res.world_from_camera[:3, 3] - pose[:3, 3]))

    assert camera_error_cm("cauchy", unsurveyed_in_view=False) < 0.05
    assert camera_error_cm("huber", unsurveyed_in_view=False) > 0.5
    assert camera_error_cm("cauchy", unsurveyed_in_view=True) == camera_error_cm("huber", unsurveyed_in_view=True)


def test_a_jump_is_placed_by_the_views_and_bends_nothing_before_it() -> None:
    """A folder replayed from its start (or a robot carried elsewhere): the views of mapped tags place
    the camera metres from its last pose. Its constant-velocity prior used to win (each pass's first
    pose 1.6 m off, the frames before it pulled towards it); now that frame is placed by its views
    and the trajectory before it stays put. Control: with the jump margins out of reach, the old
    behaviour comes back (the test can fail)."""
    anchor = SCENE.tags[3]
    traj = _constant_velocity(30)

    def run(margin_m: float) -> tuple[MarkerSlam, list[float]]:
        slam = MarkerSlam(
            SlamSettings(anchor_tag_id=anchor.id, jump_margin_m=margin_m),
            known_tags={anchor.id: (anchor.size_m, anchor.pose())},
        )
        errors = []
        for i in range(30):  # frames 20-29 replay poses 0-9: a 2.7 m jump at frame 20
            truth = traj[i if i < 20 else i - 20]
            res = slam.update(i, i * TRAJ_FRAME_NS, [_exact_obs(*v) for v in _visible(truth)])
            assert res.world_from_camera is not None
            errors.append(float(np.linalg.norm(res.world_from_camera[:3, 3] - truth[:3, 3])))
        return slam, errors

    slam, errors = run(0.5)
    assert slam.state.jumps == 1
    assert max(errors) < 1e-3, errors
    final = dict(slam.trajectory())
    for i in range(30):
        truth = traj[i if i < 20 else i - 20]
        assert np.linalg.norm(final[i * TRAJ_FRAME_NS][:3, 3] - truth[:3, 3]) < 1e-3, i
    old, old_errors = run(1000.0)
    assert old.state.jumps == 0 and old_errors[20] > 0.1


def test_slam_rescales_a_tag_the_edge_solved_at_another_size(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """edge_infer without slam's tag map solves every tag at its default size: PnP's translation is
    then off by the ratio of the sizes, and the map and trajectory with it. slam takes each tag at its
    own map's size (translation rescaled) and says so once per tag."""
    from shared.vision.tagmap import TagMapFile, TagSpec, write_tag_map

    write_tag_map(tmp_path / "sizes.json", TagMapFile(tags=[TagSpec(id=t.id, size_m=t.size_m) for t in SCENE.tags]))
    poses = _constant_velocity(12)

    def solved_at(tag_id: int) -> float:  # each tag at its own wrong size: rescaling is per tag
        return 0.16 if tag_id % 2 else 0.25

    def wrong_size(msg: TagPoses) -> TagPoses:
        def scaled(m: np.ndarray, k: float) -> np.ndarray:
            out = np.array(m, np.float64)
            out[:3, 3] *= k
            return out

        tags = [
            t.model_copy(
                update={
                    "tag_size_m": solved_at(t.tag_id),
                    "camera_from_tag": scaled(t.camera_from_tag, solved_at(t.tag_id) / t.tag_size_m),
                    "alt_camera_from_tag": scaled(t.alt_camera_from_tag, solved_at(t.tag_id) / t.tag_size_m),
                }
            )
            for t in msg.tags
        ]
        return msg.model_copy(update={"tags": tags})

    assert all(t.size_m not in (0.16, 0.25) for t in SCENE.tags)
    for with_map, expect_cm in ((True, 0.1), (False, None)):
        node = SlamNode(SlamServiceSettings(run_dir=tmp_path, tag_map=tmp_path / "sizes.json" if with_map else None))
        with caplog.at_level("WARNING"):
            for i in range(12):
                node.on_poses(wrong_size(_tag_poses(i, 1_000 + i, poses[i])))
        est = {t - 1_000: p for t, p in node.slam.trajectory()}
        ate, n = absolute_trajectory_error(est, dict(enumerate(poses)))
        assert n == 12
        if expect_cm is not None:
            assert ate * 100 < expect_cm, ate
            warned = [r.message for r in caplog.records if "but slam's tag map says" in r.message]
            assert len(warned) == len({t.tag_id for i in range(12) for t in _tag_poses(i, 0, poses[i]).tags})
            assert {"0.1600", "0.2500"} <= {m.split("solved at ")[1][:6] for m in warned}
        else:
            assert ate * 100 > 1.0  # without slam's map the wrong size stands (the control)
        caplog.clear()


def test_truth_is_drawn_in_the_estimates_frame_when_slam_has_no_world() -> None:
    """Without world poses slam works in its anchor tag's frame: Rerun drew the truth metres away; the
    truth fitted onto the trajectory lands on it (and is not drawn from fewer than 3 shared stamps)."""
    from shared.slam.marker_slam import truth_in_estimate_frame

    rng = np.random.default_rng(3)
    truth = rng.normal(0, 1, (20, 3))
    anchor_from_world = look_at(np.array([3.0, -1.0, 2.0]), np.array([0.0, 0.0, 0.0]))
    est = (anchor_from_world[:3, :3] @ truth.T).T + anchor_from_world[:3, 3]
    stamps = np.arange(20, dtype=np.int64)
    moved = truth_in_estimate_frame(stamps[5:], est[5:], stamps, truth)  # the truth has frames slam lacks
    assert moved is not None
    np.testing.assert_allclose(moved, est, atol=1e-9)
    assert np.linalg.norm(truth - est, axis=1).min() > 0.5  # (they were apart)
    assert truth_in_estimate_frame(stamps[:2], est[:2], stamps, truth) is None


def test_a_size_that_is_no_size_is_refused_before_any_rescaling(tmp_path: Path) -> None:
    """slam rescales a tag to its map's size only after the message's own size passed the checks: a
    1-micrometre tag stays refused (the rescale would have made it look fine)."""
    from shared.vision.tagmap import TagMapFile, TagSpec, write_tag_map

    write_tag_map(tmp_path / "sizes.json", TagMapFile(tags=[TagSpec(id=t.id, size_m=t.size_m) for t in SCENE.tags]))
    node = SlamNode(SlamServiceSettings(run_dir=tmp_path, tag_map=tmp_path / "sizes.json"))
    msg = _tag_poses(0, 1_000, _constant_velocity(2)[0])
    tiny = msg.model_copy(update={"tags": [t.model_copy(update={"tag_size_m": 1e-6}) for t in msg.tags]})
    with pytest.raises(SlamInputError):
        node.on_poses(tiny)


def test_one_map_revision_is_one_map(tmp_path: Path) -> None:
    """The revision used to rise only when a tag was added, while every frame refined the poses and
    counts: a client that cached the map by revision kept stale poses (a fresh-clone trial saw three
    maps at revision 6). Now a map whose content differs from the last one handed out gets the next
    revision, and the same content keeps it."""
    node = SlamNode(SlamServiceSettings(run_dir=tmp_path))
    poses = _constant_velocity(12)
    for i in range(6):
        node.on_poses(_tag_poses(i, 1_000 + i, poses[i]))
    first = node.current_map("r1")
    assert node.current_map("r1").revision == first.revision  # nothing fused since: the same map
    node.on_poses(_tag_poses(6, 1_006, poses[6], only={t.tag_id for t in first.tags}))
    second = node.current_map("r1")
    assert [t.tag_id for t in second.tags] == [t.tag_id for t in first.tags]  # no tag added ...
    assert [t.observations for t in second.tags] != [t.observations for t in first.tags]  # ... but refined
    assert second.revision > first.revision
    assert int((tmp_path / "map_revision").read_text()) == second.revision  # a restart goes on past it
