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
(data/bench_slam, keyed by renderer, weights and perception code) so SLAM changes re-run in seconds.

    .venv/bin/python -m bench.slam [--sequences slow medium fast] [--workers 2] [--weights models]
        [--room-seed-offset N] [--json out.json]

`--room-seed-offset 10` renders other rooms, tag layouts and camera paths of the same three kinds:
the held-out check for anything tuned on the default ones.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import multiprocessing
import pickle
import shlex
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from bench.accuracy import MIN_BLUR_FOR_AXIS_PX, AprilTagMethod, axis_scale_pct, solve_pose
from bench.machine import cpu_label
from bench.tagrender import corners_in_tag, project_points
from bench.tagseq import SEQUENCES, SequenceRenderer, SequenceSpec, Trajectory, place_tags

if TYPE_CHECKING:
    from shared.vision.proposers import Proposer

FloatArray = np.ndarray
ROOT = Path(__file__).resolve().parent.parent
# What the cached perception depends on, besides the spec and the weights.
_CACHE_SOURCES = (
    "bench/tagseq.py",
    "bench/tagrender.py",
    "bench/accuracy.py",
    "shared/perception/single.py",
    "shared/vision/detector.py",
    "shared/vision/proposals.py",
    "shared/vision/fusion.py",
    "shared/vision/pnp.py",
    "shared/vision/geometry.py",
    "shared/model/net.py",
    "shared/model/infer.py",
    "shared/model/runtime.py",
    "shared/model/openvino_net.py",
    "shared/model/precision.py",
    "shared/model/views.py",
    "shared/vision/tracking.py",
    "shared/vision/linequads.py",
    "shared/vision/softdecode.py",
    "bench/slam.py",  # what a FrameRecord holds
)


@dataclass
class TagObservation:
    """One tag the product's perception reported: the pose candidates the slam core takes."""

    tag_id: int
    size_m: float
    camera_from_tag: FloatArray
    reprojection_error_px: float
    alt_camera_from_tag: FloatArray
    alt_reprojection_error_px: float
    proposer: Proposer | None = None  # who found it


@dataclass
class FrameRecord:
    """Truth and both methods' per-frame output."""

    index: int
    stamp_s: float
    world_from_camera: FloatArray
    in_view: list[int]
    blur_px: dict[int, float]
    apriltag: list[tuple[int, FloatArray]] = field(default_factory=list)  # (id, corners TL TR BR BL)
    splittag: list[TagObservation] = field(default_factory=list)
    # with track-then-refine: the tags stage 1 missed that the tracker predicted and the gate accepted
    tracked: list[TagObservation] = field(default_factory=list)
    tracked_corner_error_px: dict[int, float] = field(default_factory=dict)  # mean corner error vs truth
    # stage 1 + the network: each tag's mean corner error vs truth (inf: a tag that is not in view)
    splittag_corner_error_px: list[float] = field(default_factory=list)
    tracking_rejected: int = 0  # predictions the gate (soft decode or keypoint confidence) refused
    perception_ms: float = 0.0
    tracking_ms: float = 0.0


# ----------------------------------------------------------------------------------------------------
# Per-frame perception (worker processes)

_worker: dict[str, Any] = {}


def _init_worker(weights: str, soft_decode: bool = True, precision: str = "bf16", views: int = 1) -> None:
    import torch

    from shared.model.runtime import load_split_net
    from shared.model.views import with_views
    from shared.model.weights import load_keypoint_fusion
    from shared.vision.linequads import LineQuadSettings
    from shared.vision.proposals import Stage1Settings

    torch.set_num_threads(1)
    _worker["model"] = with_views(load_split_net(Path(weights), precision, threads=1), views)  # type: ignore[arg-type]
    _worker["fusion"] = load_keypoint_fusion(Path(weights))
    # the services' stage 1 settings (the soft decode as asked); a fresh detector per sequence, as its
    # full-resolution sweeps and windows carry state from frame to frame
    _worker["stage1"] = Stage1Settings(lines=LineQuadSettings(soft_decode=soft_decode))
    _worker["apriltag"] = AprilTagMethod()
    _worker["renderers"] = {}


def _perceive_sequence(spec: SequenceSpec) -> list[FrameRecord]:
    """One sequence, frame after frame (the tracker needs the order): stage 1, the network on its ROIs
    (at the precision robot_infer runs it) with keypoint fusion and PnP; then track-then-refine for the tags
    stage 1 missed (prediction, soft-decode gate, the network on the predicted ROI, the keypoint
    confidence gate); AprilTag 3 alone as the baseline."""
    from shared.perception.single import extract_rois, run_network
    from shared.vision.camera import CameraIntrinsics
    from shared.vision.detector import Detection
    from shared.vision.fusion import edge_width_px
    from shared.vision.geometry import keypoints_to_image, lattice_in_tag
    from shared.vision.pnp import solve_planar_pnp
    from shared.vision.proposals import Stage1Detector
    from shared.vision.tagmap import TagMapFile
    from shared.vision.tracking import TagTracker, verify_tag

    r = SequenceRenderer(spec)
    s = r.spec
    camera = CameraIntrinsics(
        width=s.width, height=s.height, fx=s.fx, fy=s.fy, cx=s.cx, cy=s.cy, distortion_model="none", distortion=[]
    )
    tag_map = TagMapFile.model_validate(r.tag_map_json())  # the sizes, as a deployment's tag map gives them
    true_tags = {t.tag_id: t for t in r.tags}
    tracker = TagTracker()
    model, fusion = _worker["model"], _worker["fusion"]
    detector = Stage1Detector(_worker["stage1"])  # this sequence's own: no state from another
    records = []
    for index in range(s.n_frames):
        frame = r.render(index)
        rec = FrameRecord(index, frame.stamp_s, frame.world_from_camera, frame.in_view, frame.blur_px)
        rec.apriltag = [(p.tag_id, p.points_px) for p in _worker["apriltag"](frame.image, r.k)]
        t0 = time.perf_counter()
        detections = detector.detect(frame.image)
        rois, homs = extract_rois(frame.image, detections)
        kps = run_network(model, rois)
        refined: dict[int, FloatArray] = {}
        for i, d in enumerate(detections):
            size = tag_map.size_of(d.tag_id)
            kp = keypoints_to_image(kps[i], homs[i])
            if fusion is not None:
                kp = fusion.apply(kp, d.corners_px, homs[i], edge_width_px(rois[i], homs[i]))
            pose = solve_planar_pnp(camera, lattice_in_tag(size), kp)
            rec.splittag.append(_observation(d.tag_id, size, pose, d.proposer))
            refined[d.tag_id] = kp[[0, 3, 15, 12]]
            rec.splittag_corner_error_px.append(_corner_error(r, frame, true_tags.get(d.tag_id), kp))
        rec.perception_ms = (time.perf_counter() - t0) * 1e3
        t0 = time.perf_counter()
        predictions = tracker.predict(index, {d.tag_id for d in detections}, (s.width, s.height))
        accepted = []
        for p in predictions:
            verdict = verify_tag(frame.image, p, tracker.settings)
            if verdict.accepted:
                accepted.append(Detection(p.tag_id, 0.0, 0, verdict.corners_px))
            else:
                rec.tracking_rejected += 1
        if accepted:
            rois, homs = extract_rois(frame.image, accepted)
            kps = run_network(model, rois)
            for i, d in enumerate(accepted):
                size = tag_map.size_of(d.tag_id)
                kp = keypoints_to_image(kps[i], homs[i])
                pose = solve_planar_pnp(camera, lattice_in_tag(size), kp)
                if pose.reprojection_error_px > tracker.settings.max_refined_reprojection_px:
                    rec.tracking_rejected += 1
                    continue
                rec.tracked.append(_observation(d.tag_id, size, pose, "tracker"))
                refined[d.tag_id] = kp[[0, 3, 15, 12]]
                rec.tracked_corner_error_px[d.tag_id] = _corner_error(r, frame, true_tags.get(d.tag_id), kp)
        tracker.update(index, refined, {d.tag_id for d in detections})
        rec.tracking_ms = (time.perf_counter() - t0) * 1e3
        records.append(rec)
    detector.close()
    return records


def _corner_error(r: SequenceRenderer, frame: Any, truth: Any, keypoints: FloatArray) -> float:
    """Mean distance of the keypoints' four corners from the true ones (inf: no such tag in view)."""
    if truth is None or truth.tag_id not in frame.in_view:
        return float("inf")
    true_corners = project_points(r.k, r.camera_from_tag(frame.world_from_camera, truth), corners_in_tag(truth.size_m))
    return float(np.linalg.norm(keypoints[[0, 3, 15, 12]] - true_corners, axis=1).mean())


def _observation(tag_id: int, size_m: float, pose: Any, proposer: Proposer | None) -> TagObservation:
    return TagObservation(
        int(tag_id),
        size_m,
        pose.camera_from_tag,
        pose.reprojection_error_px,
        pose.alt_camera_from_tag,
        pose.alt_reprojection_error_px,
        proposer,
    )


def _cache_key(
    spec: SequenceSpec, weights: Path, soft_decode: bool = True, precision: str = "bf16", views: int = 1
) -> str:
    h = hashlib.sha1(json.dumps(asdict(spec), sort_keys=True).encode())
    if soft_decode:
        h.update(b"soft_decode")
    h.update(f"{precision} views {views}".encode())
    if precision == "int8":
        for f in sorted((weights / "int8").glob("*")):
            st = f.stat()
            h.update(f"{f.name}:{st.st_size}:{st.st_mtime_ns}".encode())
    for rel in _CACHE_SOURCES:
        h.update((ROOT / rel).read_bytes())
    h.update((weights / "config.json").read_bytes())
    st = (weights / "model.safetensors").stat()
    h.update(f"{st.st_size}:{st.st_mtime_ns}".encode())
    return h.hexdigest()[:16]


def perceive_sequences(
    specs: list[SequenceSpec],
    weights: Path,
    *,
    workers: int,
    cache_dir: Path | None,
    soft_decode: bool = True,
    precision: str = "bf16",
    views: int = 1,
) -> dict[str, list[FrameRecord]]:
    """Every frame's truth and both methods' output per sequence, one process per sequence (from the
    cache when nothing it depends on changed). `precision`: the network's (fp32, bf16 or int8; resolve
    `auto` with shared.model.precision.resolve_for_folder first); `views`: test-time views per ROI
    (shared.model.views)."""
    out: dict[str, list[FrameRecord]] = {}
    keys = {s.name: _cache_key(s, weights, soft_decode, precision, views) for s in specs}
    paths = {name: None if cache_dir is None else cache_dir / f"{name}-{key}.pkl" for name, key in keys.items()}
    todo = []
    for spec in specs:
        path = paths[spec.name]
        if path is not None and path.is_file():
            out[spec.name] = pickle.loads(path.read_bytes())
        else:
            todo.append(spec.name)
    if todo:
        ctx = multiprocessing.get_context("spawn")
        with ctx.Pool(
            min(workers, len(todo)), initializer=_init_worker, initargs=(str(weights), soft_decode, precision, views)
        ) as pool:
            by_name = {spec.name: spec for spec in specs}
            for name, records in zip(todo, pool.imap(_perceive_sequence, [by_name[n] for n in todo]), strict=True):
                out[name] = records
                path = paths[name]
                if path is not None:
                    path.parent.mkdir(parents=True, exist_ok=True)
                    tmp = path.with_suffix(".tmp")
                    tmp.write_bytes(pickle.dumps(records))
                    tmp.replace(path)
    return out


# ----------------------------------------------------------------------------------------------------
# Methods: frame records -> {frame index: world_from_camera} (final) and the online poses


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
) -> tuple[dict[int, FloatArray], dict[int, FloatArray], dict[str, Any]]:
    """The slam core fed frame by frame: (final trajectory, online poses, counters). `known_sigmas`: how
    well the known map states each tag (rotation rad, position m; none: as surveyed)."""
    from shared.slam.marker_slam import MarkerSlam, SlamSettings

    settings = SlamSettings.model_validate(
        {"anchor_tag_id": anchor, "localisation_only": localisation_only, "soft_reads": soft_reads}
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


def evaluate(
    records: list[FrameRecord], spec: SequenceSpec, *, soft_reads: str = "localise"
) -> dict[str, dict[str, Any]]:
    """Every method's metrics on one sequence (`soft_reads`: SlamSettings.soft_reads for every SLAM run)."""
    slam_run = partial(splittag_slam, soft_reads=soft_reads)
    gt = {r.index: r.world_from_camera for r in records}
    tag_map, anchor = _tag_map(spec)
    rows: dict[str, dict[str, Any]] = {}
    pnp = apriltag_known_map(records, tag_map, spec.camera_matrix())
    rows["apriltag3 known-map PnP"] = trajectory_metrics(pnp, gt, fps=spec.fps)
    rough, _, rough_sigmas = rough_tag_map(spec)
    rows["apriltag3 rough-map PnP"] = trajectory_metrics(
        apriltag_known_map(records, rough, spec.camera_matrix()), gt, fps=spec.fps
    )
    runs: dict[str, Callable[[], tuple[dict[int, FloatArray], dict[int, FloatArray], dict[str, Any]]]] = {
        "splittag SLAM": lambda: slam_run(records, spec, known=None, anchor=None, localisation_only=False),
        "splittag SLAM + map": lambda: slam_run(records, spec, known=tag_map, anchor=anchor, localisation_only=False),
        "splittag localisation": lambda: slam_run(records, spec, known=tag_map, anchor=anchor, localisation_only=True),
        "splittag SLAM + rough map": lambda: slam_run(
            records, spec, known=rough, anchor=anchor, localisation_only=False, known_sigmas=rough_sigmas
        ),
        "splittag SLAM + rough map as surveyed": lambda: slam_run(
            records, spec, known=rough, anchor=anchor, localisation_only=False
        ),
        "splittag SLAM, tracking": lambda: slam_run(
            records, spec, known=None, anchor=None, localisation_only=False, tracking=True
        ),
        "splittag SLAM + map, tracking": lambda: slam_run(
            records, spec, known=tag_map, anchor=anchor, localisation_only=False, tracking=True
        ),
    }
    for name, fn in runs.items():
        final, online, extra = fn()
        row = trajectory_metrics(final, gt, fps=spec.fps)
        row["online_ate_cm"] = trajectory_metrics(online, gt, fps=spec.fps)["ate_cm"]
        row["online_pose_pct"] = trajectory_metrics(online, gt, fps=spec.fps)["pose_pct"]
        row.update(extra)
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


def format_table(results: dict[str, dict[str, Any]]) -> str:
    lines = [
        f"{'sequence':<8} {'method':<38} {'pose %':>7} {'ATE cm':>7} {'rot deg':>8} {'RPE1s cm':>9} "
        f"{'aligned ATE':>12} {'online ATE':>11} {'bridged %':>10} {'sigma cm':>9} {'in 95 %':>8}"
    ]
    for seq, res in results.items():
        for name, row in res["methods"].items():
            lines.append(
                f"{seq:<8} {name:<38} {_fmt(row['pose_pct'], 1):>7} {_fmt(row['ate_cm']):>7} "
                f"{_fmt(row['rot_deg']):>8} {_fmt(row['rpe_cm']):>9} {_fmt(row['aligned_ate_cm']):>12} "
                f"{_fmt(row.get('online_ate_cm')):>11} {_fmt(row.get('bridged_pct'), 1):>10} "
                f"{_fmt(row.get('sigma_cm')):>9} {_fmt(row.get('inside95_pct'), 0):>8}"
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
    ap.add_argument(
        "--soft-reads",
        choices=["localise", "ignore", "map"],
        default="localise",
        help="slam's SlamSettings.soft_reads for every SLAM row (localise, the default: blind soft reads of a "
        "surveyed map's tags place frames nothing else places)",
    )
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    from shared.model.precision import resolve_for_folder

    precision = resolve_for_folder(args.precision, args.weights)
    specs = {n: replace(SEQUENCES[n], seed=SEQUENCES[n].seed + args.room_seed_offset) for n in args.sequences}
    command = "python -m bench.slam " + shlex.join(sys.argv[1:])
    print(f"CPU: {cpu_label()}")
    print(
        f"command: {command}; network precision {precision}, {args.views} view(s) per ROI, "
        f"soft reads {args.soft_reads}",
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
        results[name] = {"facts": facts, "methods": evaluate(records, spec, soft_reads=args.soft_reads)}
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
    # Run as bench.slam, not __main__, so the cached records pickle under their importable name.
    from bench.slam import main as _main

    _main()
