"""Perception of bench.slam's rendered sequences, cached: what a FrameRecord holds.

Per frame: AprilTag 3's corners, the product's tag poses (stage 1 -> ROI -> network -> fusion -> PnP),
and with track-then-refine the tags the tracker carried. Rendering and the network dominate bench.slam's
time, so the records are cached (data/bench_slam) under a key of the spec, the weights and the source of
everything they depend on: this module, not bench/slam.py, so SLAM changes there re-run in seconds.
"""

from __future__ import annotations

import hashlib
import json
import multiprocessing
import pickle
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from bench.accuracy import AprilTagMethod
from bench.tagrender import corners_in_tag, project_points
from bench.tagseq import SequenceRenderer, SequenceSpec

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
    "bench/seqperception.py",  # what a FrameRecord holds
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
