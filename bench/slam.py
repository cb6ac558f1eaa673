"""Marker SLAM on rendered room sequences, next to AprilTag 3 known-map PnP, in one run.

Three sequences from bench/tagseq.py (slow; medium with lighting flicker; fast with exposure-time
motion blur up to ~20 px), 10 s at 30 fps, 1280x720, tags of 0.10-0.20 m on the walls. Per frame the
bench renders the image and runs:
- AprilTag 3 (the product's stage-1 settings, restated in bench/accuracy.py) and, on a known tag map,
  PnP over every mapped tag's corners (IPPE_SQUARE for one tag, SQPnP + Levenberg-Marquardt for more):
  what an engineer gets from AprilTag alone;
- the product's perception (stage 1 -> ROI -> network at the services' precision, `auto` by default:
  int8 where the weights folder has it -> keypoint fusion -> PnP on 16 points), whose tag poses then
  feed the SLAM core (shared/slam) as slam feeds it: without a map ("splittag SLAM"), with the known
  map as priors ("splittag SLAM + map"), and localisation-only on the map;
- on a rough map (every tag but the anchor 2 cm / 1 deg off per axis, as a tape measure gives):
  AprilTag PnP on it, SLAM given it with those stated sigmas, and SLAM taking it as surveyed.

Metrics over the frames of the sequence: frames with a pose; ATE (RMSE of position, cm) and rotation
RMSE (deg) in the true world frame, without fitting (the known-map methods work in the map's frame;
SLAM without a map works in its anchor tag's frame, mapped to the world by that tag's true pose, so
the map's errors count too); RPE over 1 s (RMSE of the relative translation error, cm); ATE after
SE(3) alignment (Umeyama, as TUM's evaluation tool does); and the online ATE (the pose slam published
for each frame as it came, not the final smoothed trajectory); and "bridged %": frames slam posed in a
map fragment begun after a long gap without tags and never tied back to the world (their placement
is the gap's guess: left out of pose % and every ATE); "sigma cm" and "in 95 %": how the online poses'
own covariance (CameraPose.covariance_world) compares with their errors (the median position sigma,
sqrt of the trace, and the share of errors inside the 95 % ellipsoid). Perception results are cached
(bench/seqperception.py: data/bench_slam, keyed by renderer, weights and perception code, not by this
file) so SLAM changes re-run in seconds.

    .venv/bin/python -m bench.slam [--sequences slow medium fast] [--workers 2] [--weights models]
        [--room-seed-offset N] [--perturb N] [--json out.json]

`--room-seed-offset 10` renders other rooms, tag layouts and camera paths of the same three kinds:
the held-out check for anything tuned on the default ones. `--perturb 8` reruns every SLAM row on 8
copies of the records 1 nm apart: the fast rooms' SLAM is sensitive to rounding, so judge by the median.
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from bench.accuracy import MIN_BLUR_FOR_AXIS_PX, axis_scale_pct, solve_pose
from bench.machine import cpu_label
from bench.seqperception import (
    ROOT,
    FloatArray,
    FrameRecord,
    TagObservation,
    perceive_sequences,
)
from bench.tagrender import project_points
from bench.tagseq import SEQUENCES, SequenceSpec, Trajectory, place_tags

TagMap = dict[int, tuple[float, FloatArray]]


def _tag_map(spec: SequenceSpec) -> tuple[TagMap, int]:
    tags = place_tags(spec)
    return {t.tag_id: (t.size_m, t.world_from_tag) for t in tags}, tags[0].tag_id


def place_tags_map(spec: SequenceSpec) -> TagMap:
    """The sequence's true tag map."""
    return _tag_map(spec)[0]


ROUGH_POSITION_SIGMA_M = 0.02  # a map measured with a tape and a protractor, not surveyed
ROUGH_ROTATION_SIGMA_DEG = 1.0


def rough_tag_map(spec: SequenceSpec) -> tuple[TagMap, int, dict[int, tuple[float, float]]]:
    """The true map with every tag but the anchor moved by N(0, 2 cm) per axis and turned by N(0, 1 deg)
    per axis (fixed seed per room), and the sigmas such a map would state: (map, anchor, {id: (rotation
    rad, position m)})."""
    true, anchor = _tag_map(spec)
    rng = np.random.default_rng(spec.seed + 1000)
    rough: TagMap = {}
    for tag_id, (size, pose) in sorted(true.items()):
        moved = np.array(pose, np.float64)
        if tag_id != anchor:
            turn = cv2.Rodrigues(rng.normal(0.0, math.radians(ROUGH_ROTATION_SIGMA_DEG), 3))[0]
            moved[:3, :3] = moved[:3, :3] @ turn
            moved[:3, 3] += rng.normal(0.0, ROUGH_POSITION_SIGMA_M, 3)
        rough[tag_id] = (size, moved)
    sigmas = {t: (math.radians(ROUGH_ROTATION_SIGMA_DEG), ROUGH_POSITION_SIGMA_M) for t in rough if t != anchor}
    return rough, anchor, sigmas


def _corners_world(size_m: float, world_from_tag: FloatArray) -> FloatArray:
    h = size_m / 2
    tl_tr_br_bl = np.array([[-h, -h, 0, 1], [h, -h, 0, 1], [h, h, 0, 1], [-h, h, 0, 1]], np.float64)
    return (tl_tr_br_bl @ world_from_tag.T)[:, :3]


def apriltag_known_map(records: list[FrameRecord], tag_map: TagMap, k: FloatArray) -> dict[int, FloatArray]:
    """AprilTag 3 corners -> PnP on every mapped tag in the frame (the map's world frame)."""
    out = {}
    for rec in records:
        dets = [(i, c) for i, c in rec.apriltag if i in tag_map]
        if not dets:
            continue
        if len(dets) == 1:
            tag_id, corners = dets[0]
            size, world_from_tag = tag_map[tag_id]
            cam_from_tag = solve_pose(np.asarray(corners, np.float64), "corners4", size, k)
            if cam_from_tag is None:
                continue
            out[rec.index] = world_from_tag @ np.linalg.inv(cam_from_tag)
            continue
        obj = np.vstack([_corners_world(*tag_map[i]) for i, _ in dets])
        img = np.vstack([np.asarray(c, np.float64) for _, c in dets])
        ok, rvec, tvec = cv2.solvePnP(obj, img, k, None, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            continue
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, k, None, rvec, tvec)
        rot, _ = cv2.Rodrigues(rvec)
        cam_from_world = np.eye(4)
        cam_from_world[:3, :3] = rot
        cam_from_world[:3, 3] = np.asarray(tvec).ravel()
        out[rec.index] = np.linalg.inv(cam_from_world)
    return out


def _slam_observation(o: TagObservation, focal_px: float, *, tracked: bool = False) -> Any:
    """What the slam service makes of a TagPose (shared.slam.marker_slam.Observation)."""
    from shared.slam.marker_slam import Observation

    return Observation(
        o.tag_id,
        o.size_m,
        o.camera_from_tag,
        o.reprojection_error_px,
        o.alt_camera_from_tag,
        o.alt_reprojection_error_px,
        focal_px,
        tracked,
        "tracker" if tracked else o.proposer,
    )


def splittag_slam(
    records: list[FrameRecord],
    spec: SequenceSpec,
    *,
    known: TagMap | None,
    anchor: int | None,
    localisation_only: bool,
    tracking: bool = False,
    known_sigmas: dict[int, tuple[float, float]] | None = None,
    soft_reads: str = "localise",
    tracked_reads: str = "localise",
) -> tuple[dict[int, FloatArray], dict[int, FloatArray], dict[str, Any]]:
    """The slam core fed frame by frame: (final trajectory, online poses, counters). `known_sigmas`: how
    well the known map states each tag (rotation rad, position m; none: as surveyed)."""
    from shared.slam.marker_slam import MarkerSlam, SlamSettings

    settings = SlamSettings.model_validate(
        {
            "anchor_tag_id": anchor,
            "localisation_only": localisation_only,
            "soft_reads": soft_reads,
            "tracked_reads": tracked_reads,
        }
    )
    slam = MarkerSlam(settings, known_tags=known, known_sigmas=dict(known_sigmas or {}))
    online: dict[int, FloatArray] = {}
    focal = (spec.fx + spec.fy) / 2
    stamp_to_index = {}
    online_cov: dict[int, FloatArray] = {}
    t0 = time.perf_counter()
    for rec in records:
        stamp = round(rec.stamp_s * 1e9)
        stamp_to_index[stamp] = rec.index
        obs = [
            _slam_observation(o, focal, tracked=tracked)
            for o, tracked in [(o, False) for o in rec.splittag]
            + ([(o, True) for o in rec.tracked] if tracking else [])
        ]
        res = slam.update(rec.index, stamp, obs)
        if res.world_from_camera is not None:
            online[rec.index] = res.world_from_camera
            if res.covariance_world is not None:
                online_cov[rec.index] = res.covariance_world[:3, :3]
    secs = time.perf_counter() - t0
    trajectory = slam.trajectory()
    # Poses in a fragment begun after a long gap and never tied back to the world: counted apart (their
    # placement is the gap's guess), not in the pose % or the ATE.
    bridged = {stamp_to_index[s] for s, _ in trajectory if slam.bridged(s)}
    final = {stamp_to_index[s]: p for s, p in trajectory if stamp_to_index[s] not in bridged}
    online = {i: p for i, p in online.items() if i not in bridged}
    if known is None and slam.anchor is not None:
        # SLAM's world is its anchor tag's frame: express it in the true world with the anchor's true
        # pose (no fitting, so every error of the map and trajectory relative to the anchor counts).
        world_from_anchor = dict(place_tags_map(spec))[slam.anchor][1]
        final = {i: world_from_anchor @ p for i, p in final.items()}
        online = {i: world_from_anchor @ p for i, p in online.items()}
        r = world_from_anchor[:3, :3]
        online_cov = {i: r @ c @ r.T for i, c in online_cov.items()}
    gt = {rec.index: rec.world_from_camera for rec in records}
    st = slam.state
    return (
        final,
        online,
        {
            "slam_ms_per_frame": secs * 1e3 / max(1, len(records)),
            "rejected_ambiguous": st.rejected_ambiguous,
            "bridged_pct": 100.0 * len(bridged) / max(1, len(records)),
            **covariance_check(online, online_cov, gt),
        },
    )


def covariance_check(
    est: dict[int, FloatArray], position_cov: dict[int, FloatArray], gt: dict[int, FloatArray]
) -> dict[str, float | None]:
    """How the poses' own covariance (CameraPose.covariance_world, its position block) compares with
    their true errors: the median position sigma (sqrt of the trace, cm: comparable to an error's
    length) and the share of poses whose error lies inside their 95 % ellipsoid (chi-square, 3 dof: 95 %
    when calibrated, more when pessimistic)."""
    common = [i for i in est if i in position_cov and i in gt]
    if not common:
        return {"sigma_cm": None, "inside95_pct": None}
    sigma = [100 * math.sqrt(float(np.trace(position_cov[i]))) for i in common]
    inside = []
    for i in common:
        err = est[i][:3, 3] - gt[i][:3, 3]
        inside.append(float(err @ np.linalg.solve(position_cov[i], err)) <= CHI2_3DOF_95)
    return {"sigma_cm": float(np.median(sigma)), "inside95_pct": 100.0 * float(np.mean(inside))}


# ----------------------------------------------------------------------------------------------------
# Metrics


CHI2_3DOF_95 = 7.815  # 95 % quantile of chi-square with 3 degrees of freedom


def _umeyama(src: FloatArray, dst: FloatArray) -> FloatArray:
    mu_s, mu_d = src.mean(0), dst.mean(0)
    cov = (dst - mu_d).T @ (src - mu_s) / len(src)
    u, _, vt = np.linalg.svd(cov)
    d = np.eye(3)
    d[2, 2] = math.copysign(1.0, float(np.linalg.det(u @ vt)))
    t = np.eye(4)
    t[:3, :3] = u @ d @ vt
    t[:3, 3] = mu_d - t[:3, :3] @ mu_s
    return t


def _angle_deg(r: FloatArray) -> float:
    return math.degrees(math.acos(float(np.clip((np.trace(r) - 1) / 2, -1.0, 1.0))))


def trajectory_metrics(est: dict[int, FloatArray], gt: dict[int, FloatArray], *, fps: float) -> dict[str, float | None]:
    """Frames with a pose (%); ATE and rotation RMSE in the map's frame (every method's world is the
    true one: the tag map's, or for SLAM its anchor tag's true pose), and ATE after SE(3) alignment
    (Umeyama, as TUM's tool); RPE over 1 s."""
    common = sorted(set(est) & set(gt))
    out: dict[str, float | None] = {
        "pose_pct": 100.0 * len(common) / len(gt),
        "ate_cm": None,
        "rot_deg": None,
        "aligned_ate_cm": None,
        "rpe_cm": None,
    }
    if len(common) < 3:
        return out
    a = np.array([est[i][:3, 3] for i in common])
    b = np.array([gt[i][:3, 3] for i in common])
    out["ate_cm"] = 100 * float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))
    rot = [_angle_deg(est[i][:3, :3] @ gt[i][:3, :3].T) for i in common]
    out["rot_deg"] = float(np.sqrt(np.mean(np.square(rot))))
    align = _umeyama(a, b)
    aligned = a @ align[:3, :3].T + align[:3, 3]
    out["aligned_ate_cm"] = 100 * float(np.sqrt(np.mean(np.sum((aligned - b) ** 2, axis=1))))
    step = round(fps)
    errs = []
    for i in common:
        j = i + step
        if j in est and j in gt:
            de = np.linalg.inv(est[i]) @ est[j]
            dg = np.linalg.inv(gt[i]) @ gt[j]
            errs.append(float(np.linalg.norm(de[:3, 3] - dg[:3, 3])))
    out["rpe_cm"] = 100 * float(np.sqrt(np.mean(np.square(errs)))) if errs else None
    return out


# ----------------------------------------------------------------------------------------------------
# Running and printing


PERTURB_M = 1e-9  # --perturb: each observation's position moved by this (1 nm): only the rounding changes


def perturbed(records: list[FrameRecord], seed: int, metres: float = PERTURB_M) -> list[FrameRecord]:
    """Copies of `records` with every observation's position (camera_from_tag, both the detected and the
    tracked tags') moved by a Gaussian of `metres` per axis; the originals are untouched."""
    rng = np.random.default_rng(seed)

    def moved(o: TagObservation) -> TagObservation:
        m = o.camera_from_tag.copy()
        m[:3, 3] += rng.normal(0.0, metres, 3)
        return replace(o, camera_from_tag=m)

    return [
        replace(rec, splittag=[moved(o) for o in rec.splittag], tracked=[moved(o) for o in rec.tracked])
        for rec in records
    ]


def evaluate(
    records: list[FrameRecord],
    spec: SequenceSpec,
    *,
    soft_reads: str = "localise",
    tracked_reads: str = "localise",
    perturb: int = 0,
) -> dict[str, dict[str, Any]]:
    """Every method's metrics on one sequence (`soft_reads`, `tracked_reads`: SlamSettings' for every SLAM
    run).
    `perturb` > 0: each SLAM row is also run that many times on `perturbed` records (seeds 0..perturb-1)
    and the row gets the median, min and max of their ATEs (`perturbed_ate_cm`): how much of a figure is
    the luck of rounding (a fast room's SLAM + map has read anything from 2.9 to 5.3 cm)."""
    slam_run = partial(splittag_slam, soft_reads=soft_reads, tracked_reads=tracked_reads)
    gt = {r.index: r.world_from_camera for r in records}
    tag_map, anchor = _tag_map(spec)
    rows: dict[str, dict[str, Any]] = {}
    pnp = apriltag_known_map(records, tag_map, spec.camera_matrix())
    rows["apriltag3 known-map PnP"] = trajectory_metrics(pnp, gt, fps=spec.fps)
    rough, _, rough_sigmas = rough_tag_map(spec)
    rows["apriltag3 rough-map PnP"] = trajectory_metrics(
        apriltag_known_map(records, rough, spec.camera_matrix()), gt, fps=spec.fps
    )
    Run = Callable[[list[FrameRecord]], tuple[dict[int, FloatArray], dict[int, FloatArray], dict[str, Any]]]
    runs: dict[str, Run] = {
        "splittag SLAM": lambda recs: slam_run(recs, spec, known=None, anchor=None, localisation_only=False),
        "splittag SLAM + map": lambda recs: slam_run(recs, spec, known=tag_map, anchor=anchor, localisation_only=False),
        "splittag localisation": lambda recs: slam_run(
            recs, spec, known=tag_map, anchor=anchor, localisation_only=True
        ),
        "splittag SLAM + rough map": lambda recs: slam_run(
            recs, spec, known=rough, anchor=anchor, localisation_only=False, known_sigmas=rough_sigmas
        ),
        "splittag SLAM + rough map as surveyed": lambda recs: slam_run(
            recs, spec, known=rough, anchor=anchor, localisation_only=False
        ),
        "splittag SLAM, tracking": lambda recs: slam_run(
            recs, spec, known=None, anchor=None, localisation_only=False, tracking=True
        ),
        "splittag SLAM + map, tracking": lambda recs: slam_run(
            recs, spec, known=tag_map, anchor=anchor, localisation_only=False, tracking=True
        ),
    }
    for name, fn in runs.items():
        final, online, extra = fn(records)
        row: dict[str, Any] = dict(trajectory_metrics(final, gt, fps=spec.fps))
        row["online_ate_cm"] = trajectory_metrics(online, gt, fps=spec.fps)["ate_cm"]
        row["online_pose_pct"] = trajectory_metrics(online, gt, fps=spec.fps)["pose_pct"]
        row.update(extra)
        if perturb:
            ates = [
                trajectory_metrics(fn(perturbed(records, seed))[0], gt, fps=spec.fps)["ate_cm"]
                for seed in range(perturb)
            ]
            known = [a for a in ates if a is not None]
            row["perturbed_ate_cm"] = {
                "runs": perturb,
                "median": float(np.median(known)) if known else None,
                "min": min(known, default=None),
                "max": max(known, default=None),
            }
        rows[name] = row
    return rows


def sequence_facts(records: list[FrameRecord]) -> dict[str, float]:
    """Tags in view, stage-1 recall and blur of one sequence."""
    in_view = sum(len(r.in_view) for r in records)
    found = sum(len({i for i, _ in r.apriltag} & set(r.in_view)) for r in records)
    found_st = sum(len({o.tag_id for o in r.splittag} & set(r.in_view)) for r in records)
    found_tr = sum(len({o.tag_id for o in r.splittag + r.tracked} & set(r.in_view)) for r in records)
    tracked = [e for r in records for e in r.tracked_corner_error_px.values()]
    # a tracked tag is false when it is not in the frame or its corners are off by more than 3 px
    false_tracked = sum(1 for e in tracked if not e <= 3.0)
    blur = [b for r in records for b in r.blur_px.values()]
    st_err = [e for r in records for e in r.splittag_corner_error_px]
    # the tags only the product's stage 1 finds (AprilTag 3 missed them: mostly heavy blur on small tags)
    missed_err = []
    for r in records:
        apriltag_ids = {i for i, _ in r.apriltag}
        missed_err += [
            e
            for o, e in zip(r.splittag, r.splittag_corner_error_px, strict=True)
            if e < float("inf") and o.tag_id not in apriltag_ids
        ]
    return {
        "frames": len(records),
        "frames_with_tag_in_view_pct": 100.0 * sum(1 for r in records if r.in_view) / len(records),
        "tags_in_view_per_frame": in_view / len(records),
        "apriltag_recall_pct": 100.0 * found / max(1, in_view),
        "splittag_recall_pct": 100.0 * found_st / max(1, in_view),
        "tracking_recall_pct": 100.0 * found_tr / max(1, in_view),
        # stage 1 + network: tags not in view (ghosts), tags whose corners are off by > 3 px, the median
        "splittag_ghosts": sum(1 for e in st_err if e == float("inf")),
        "splittag_off_3px": sum(1 for e in st_err if 3.0 < e < float("inf")),
        "splittag_corner_error_p50_px": float(np.median([e for e in st_err if e < float("inf")])) if st_err else 0.0,
        "splittag_only_tags": len(missed_err),
        "splittag_only_corner_error_p50_px": float(np.median(missed_err)) if missed_err else 0.0,
        "splittag_only_corner_error_p90_px": float(np.percentile(missed_err, 90)) if missed_err else 0.0,
        "tracked_tags": len(tracked),
        "tracked_false": false_tracked,
        "tracked_corner_error_p50_px": float(np.median(tracked)) if tracked else 0.0,
        "tracking_rejected": sum(r.tracking_rejected for r in records),
        # prediction, soft decode, and the network + PnP for the accepted ones, per predicted tag
        "tracking_ms_per_prediction": sum(r.tracking_ms for r in records)
        / max(1, sum(len(r.tracked) + r.tracking_rejected for r in records)),
        "blur_p50_px": float(np.median(blur)) if blur else 0.0,
        "blur_max_px": float(np.max(blur)) if blur else 0.0,
        "perception_ms_p50": float(np.median([r.perception_ms for r in records])),
    }


def grid_along_blur(records: list[FrameRecord], spec: SequenceSpec) -> dict[str, float | int | None]:
    """Median signed scale (%) of the product's keypoint grids along each tag's motion blur, by blur:
    a grid shortened along the blur is read by PnP as a tilt, which at 3 m moves the camera by
    decimetres (the fast room with the third weights: -1.47 % at >= 8 px). The grid is the lattice
    projected through the pose fitted to the keypoints; the blur direction is the tag centre's image
    motion over the exposure."""
    from shared.vision.geometry import lattice_in_tag

    tag_map = place_tags_map(spec)
    trajectory = Trajectory(spec)
    k = spec.camera_matrix()
    bins: dict[str, list[float]] = {"3-8": [], ">=8": []}
    for rec in records:
        for o in rec.splittag:
            blur = rec.blur_px.get(o.tag_id, 0.0)
            if o.tag_id not in tag_map or blur < MIN_BLUR_FOR_AXIS_PX:
                continue
            size_m, world_from_tag = tag_map[o.tag_id]
            lattice = lattice_in_tag(size_m)
            ends = [
                project_points(k, np.asarray(np.linalg.inv(trajectory.world_from_camera(t)) @ world_from_tag), lattice)
                for t in (rec.stamp_s - spec.exposure_s / 2, rec.stamp_s + spec.exposure_s / 2)
            ]
            motion = ends[1].mean(axis=0) - ends[0].mean(axis=0)
            if float(np.linalg.norm(motion)) < 1.0:
                continue
            truth = project_points(k, np.linalg.inv(rec.world_from_camera) @ world_from_tag, lattice)
            grid = project_points(k, o.camera_from_tag, lattice)
            value = axis_scale_pct(grid, truth, motion / np.linalg.norm(motion))
            bins["3-8" if blur < 8.0 else ">=8"].append(value)
    out: dict[str, float | int | None] = {}
    for name, values in bins.items():
        out[f"blur_{name}_px_tags"] = len(values)
        out[f"blur_{name}_px_median_pct"] = float(np.median(values)) if values else None
    return out


def _pct(value: float | int | None) -> str:
    return "-" if value is None else f"{value:+.2f} %"


def noise_check(records: list[FrameRecord], spec: SequenceSpec) -> dict[str, list[float]]:
    """How the slam core's observation noise model compares with the observations' true errors: RMS of
    error / modelled sigma per axis of GTSAM's Pose3 tangent (rotation x, y, z in the tag frame, then
    translation), over every observation of the sequence. 1 = calibrated, < 1 = the model is
    pessimistic. The errors are correlated from frame to frame (one tag, similar views, the same
    blur), which independent Gaussian factors cannot express: the model is deliberately pessimistic."""
    import gtsam

    from shared.slam.marker_slam import MarkerSlam, SlamSettings

    slam = MarkerSlam(SlamSettings())
    tag_map = place_tags_map(spec)
    focal = (spec.fx + spec.fy) / 2
    ratios = []
    for rec in records:
        for o in rec.splittag:
            if o.tag_id not in tag_map:
                continue
            obs = _slam_observation(o, focal)
            truth = np.linalg.inv(rec.world_from_camera) @ tag_map[o.tag_id][1]
            err = np.asarray(gtsam.Pose3.Logmap(gtsam.Pose3(o.camera_from_tag).between(gtsam.Pose3(truth))))
            cov = slam.covariance(obs)
            ratios.append(np.abs(err) / np.sqrt(np.diag(cov)))
    if not ratios:
        return {"rms_error_over_sigma": []}
    return {"rms_error_over_sigma": np.sqrt(np.mean(np.square(ratios), axis=0)).round(3).tolist()}


def _fmt(v: float | None, digits: int = 2) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def _spread(row: dict[str, Any]) -> str:
    p = row.get("perturbed_ate_cm")
    if not p or p["median"] is None:
        return "-"
    return f"{p['median']:.2f} [{p['min']:.2f}-{p['max']:.2f}]"


def format_table(results: dict[str, dict[str, Any]]) -> str:
    perturbed_runs = {
        row["perturbed_ate_cm"]["runs"]
        for res in results.values()
        for row in res["methods"].values()
        if row.get("perturbed_ate_cm")
    }
    spread_head = f"ATE, {max(perturbed_runs)} x 1 nm" if perturbed_runs else ""
    lines = [
        f"{'sequence':<8} {'method':<38} {'pose %':>7} {'ATE cm':>7} {'rot deg':>8} {'RPE1s cm':>9} "
        f"{'aligned ATE':>12} {'online ATE':>11} {'bridged %':>10} {'sigma cm':>9} {'in 95 %':>8}"
        + (f" {spread_head:>21}" if spread_head else "")
    ]
    for seq, res in results.items():
        for name, row in res["methods"].items():
            lines.append(
                f"{seq:<8} {name:<38} {_fmt(row['pose_pct'], 1):>7} {_fmt(row['ate_cm']):>7} "
                f"{_fmt(row['rot_deg']):>8} {_fmt(row['rpe_cm']):>9} {_fmt(row['aligned_ate_cm']):>12} "
                f"{_fmt(row.get('online_ate_cm')):>11} {_fmt(row.get('bridged_pct'), 1):>10} "
                f"{_fmt(row.get('sigma_cm')):>9} {_fmt(row.get('inside95_pct'), 0):>8}"
                + (f" {_spread(row):>21}" if spread_head else "")
            )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sequences", nargs="+", default=list(SEQUENCES), choices=sorted(SEQUENCES))
    ap.add_argument("--weights", type=Path, default=ROOT / "models")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--cache-dir", type=Path, default=ROOT / "data" / "bench_slam")
    ap.add_argument("--no-cache", action="store_true")
    ap.add_argument(
        "--soft-decode",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="stage 1 with the line quads' soft decode (on by default; slam localises with its reads against "
        "a known map's tags and maps nothing from them: SlamSettings.soft_reads)",
    )
    ap.add_argument(
        "--room-seed-offset",
        type=int,
        default=0,
        help="add this to every sequence's seed: other rooms, tag layouts and camera paths of the same kinds "
        "(held-out checks for anything tuned on the default ones)",
    )
    ap.add_argument(
        "--precision",
        choices=["auto", "fp32", "bf16", "int8"],
        default="auto",
        help="the network's, as robot_infer's `precision` (auto: int8 where the weights folder has it, else "
        "bf16 where the CPU has it, else fp32)",
    )
    ap.add_argument(
        "--views",
        type=int,
        choices=[1, 2, 4, 8],
        default=1,
        help="test-time views per ROI, as robot_infer's and edge_infer's `views` (shared/model/views.py)",
    )
    from typing import get_args

    from shared.slam.marker_slam import SlamSettings

    for field, what in (
        ("soft_reads", "blind soft reads of a surveyed map's tags place frames nothing else places"),
        ("tracked_reads", "the tracker's views of a surveyed map's tags place frames nothing else places"),
    ):
        ap.add_argument(
            "--" + field.replace("_", "-"),
            choices=get_args(SlamSettings.model_fields[field].annotation),
            default=SlamSettings.model_fields[field].default,
            help=f"slam's SlamSettings.{field} for every SLAM row (localise, the default: {what}; map: fused "
            "like detections; ignore: left out)",
        )
    ap.add_argument(
        "--perturb",
        type=int,
        default=0,
        metavar="N",
        help="also run every SLAM row N times with each observation's position moved by 1 nm (seeds 0..N-1) "
        "and print the median [min-max] of their ATEs: how much of a figure is rounding's luck (the fast "
        "rooms' SLAM is sensitive to it; judge changes by these, not by one run)",
    )
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    if args.perturb < 0:
        ap.error("--perturb takes a number of runs, 0 or more")
    from shared.model.precision import resolve_for_folder

    precision = resolve_for_folder(args.precision, args.weights)
    specs = {n: replace(SEQUENCES[n], seed=SEQUENCES[n].seed + args.room_seed_offset) for n in args.sequences}
    command = "python -m bench.slam " + shlex.join(sys.argv[1:])
    print(f"CPU: {cpu_label()}")
    print(
        f"command: {command}; network precision {precision}, {args.views} view(s) per ROI, "
        f"soft reads {args.soft_reads}, tracked reads {args.tracked_reads}",
        flush=True,
    )
    results: dict[str, dict[str, Any]] = {}
    t_all = time.perf_counter()
    t0 = time.perf_counter()
    perceived = perceive_sequences(
        list(specs.values()),
        args.weights,
        workers=args.workers,
        cache_dir=None if args.no_cache else args.cache_dir,
        soft_decode=args.soft_decode,
        precision=precision,
        views=args.views,
    )
    perceive_s = time.perf_counter() - t0
    for name in args.sequences:
        spec = specs[name]
        records = perceived[name]
        facts: dict[str, Any] = dict(sequence_facts(records))
        facts["render_and_perceive_s_all_sequences"] = perceive_s
        facts["noise_model"] = noise_check(records, spec)
        facts["grid_along_blur"] = along = grid_along_blur(records, spec)
        methods = evaluate(
            records, spec, soft_reads=args.soft_reads, tracked_reads=args.tracked_reads, perturb=args.perturb
        )
        results[name] = {"facts": facts, "methods": methods}
        f = facts
        print(
            f"{name} (room seed {spec.seed}): {spec.speed_mps} m/s, {spec.turn_dps} deg/s mean yaw rate, "
            f"exposure {spec.exposure_s * 1e3:.0f} ms, "
            f"flicker +-{spec.flicker * 100:.0f} %; {f['tags_in_view_per_frame']:.2f} tags in view per frame, "
            f"blur p50/max {f['blur_p50_px']:.1f}/{f['blur_max_px']:.1f} px; stage-1 recall AprilTag "
            f"{f['apriltag_recall_pct']:.1f} %, splittag {f['splittag_recall_pct']:.1f} % "
            f"({f['splittag_ghosts']} not in view, {f['splittag_off_3px']} off by > 3 px, "
            f"corner error p50 {f['splittag_corner_error_p50_px']:.2f} px; on the {f['splittag_only_tags']} "
            f"tags AprilTag missed p50 / p90 {f['splittag_only_corner_error_p50_px']:.2f} / "
            f"{f['splittag_only_corner_error_p90_px']:.2f} px), "
            f"with tracking "
            f"{f['tracking_recall_pct']:.1f} % ({f['tracked_tags']} tracked, {f['tracked_false']} false, corner error "
            f"p50 {f['tracked_corner_error_p50_px']:.2f} px, {f['tracking_rejected']} refused by the gates, "
            f"{f['tracking_ms_per_prediction']:.1f} ms per predicted tag incl. its network pass); observation error / "
            f"modelled sigma, RMS per axis (rot x y z, t x y z): {f['noise_model']['rms_error_over_sigma']}; "
            f"keypoint grid's scale along the blur, median (tags): 3-8 px {_pct(along['blur_3-8_px_median_pct'])} "
            f"({along['blur_3-8_px_tags']}), >= 8 px {_pct(along['blur_>=8_px_median_pct'])} "
            f"({along['blur_>=8_px_tags']})",
            flush=True,
        )
    print()
    print(format_table(results))
    print(f"\nwall {time.perf_counter() - t_all:.1f} s")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"command": command, "cpu": cpu_label(), "results": results}, indent=1))
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
