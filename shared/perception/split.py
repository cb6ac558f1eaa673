"""Pure cores of robot_infer and edge_infer: one frame in, one message out, no I/O.

Wire dtype per cut: k = 0 sends the ROI pixels (uint8), k = 7 the keypoints (float32), cuts 1..6
the feature map in the configured codec (fp16 by default, or fp32).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import NDArray

from shared.model.runtime import SplitNet
from shared.perception.single import extract_rois
from shared.vision.detector import Detection, Stage1
from shared.vision.fusion import KeypointFusion, edge_width_px
from shared.vision.geometry import Array, keypoints_to_image, lattice_in_tag
from shared.vision.pnp import solve_planar_pnp
from shared.vision.tagmap import TagMapFile
from shared.vision.tracking import TagTracker, verify_tag
from shared.wire.cuts import CUTS, CodecName, FeatureShapeError, check_cut, check_tensor
from shared.wire.messages import Features, Frame, HopTimings, LinkStamps, TagFeature, TagPose, TagPoses

_LATTICE_CORNERS: Final[tuple[int, int, int, int]] = (0, 3, 15, 12)  # TL, TR, BR, BL in the 4x4 lattice


@dataclass
class RobotTimings:
    """Where the robot's time went for one frame, seconds."""

    detect_secs: float
    warp_secs: float
    head_secs: float

    @property
    def total_secs(self) -> float:
        """Everything the robot computed."""
        return self.detect_secs + self.warp_secs + self.head_secs


def track_missed(frame: Frame, detections: list[Detection], tracker: TagTracker) -> tuple[list[Detection], int]:
    """Track-then-refine's robot half: quads predicted for the recently seen tags stage 1 missed, kept
    when the soft decode accepts them (shared.vision.tracking). Runs on the robot at every cut (it
    needs the image, not the keypoints); returns the accepted ones and how many were refused."""
    if frame.seq <= tracker.last_frame:
        tracker.reset()  # the camera restarted: its numbering begins again
    h, w = frame.image.shape
    accepted, refused = [], 0
    for p in tracker.predict(frame.seq, {d.tag_id for d in detections}, (w, h)):
        verdict = verify_tag(frame.image, p, tracker.settings)
        if verdict.accepted:
            accepted.append(Detection(p.tag_id, 0.0, 0, verdict.corners_px))
        else:
            refused += 1
    return accepted, refused


@dataclass(frozen=True)
class Stage1Output:
    """Stage 1 of one frame on the robot: its tags (stage 1's, then the tracked ones), their ROIs and
    ROI->image homographies, and what it cost. `robot_head` takes it from here."""

    frame: Frame
    detections: list[Detection]
    n_detected: int  # the first n_detected are stage 1's; the rest the tracker's
    rois: NDArray[np.uint8]  # (N, 256, 256)
    roi_to_image: Array  # (N, 3, 3)
    detect_secs: float
    warp_secs: float


def robot_stage1(frame: Frame, *, detector: Stage1, tracker: TagTracker | None = None) -> Stage1Output:
    """Stage 1 and the ROI warps of one frame; with a tracker, also the tags stage 1 missed that it
    carries and verifies."""
    t0 = time.perf_counter()
    detections = detector.detect(frame.image)
    n_detected = len(detections)
    if tracker is not None:
        tracked, _ = track_missed(frame, detections, tracker)
        detections = detections + tracked
    t1 = time.perf_counter()
    rois, roi_to_image = extract_rois(frame.image, detections)
    t2 = time.perf_counter()
    return Stage1Output(frame, detections, n_detected, rois, roi_to_image, t1 - t0, t2 - t1)


def robot_head(
    s1: Stage1Output, *, net: SplitNet, k: int, codec: CodecName, tracker: TagTracker | None = None
) -> tuple[list[TagFeature], RobotTimings]:
    """The network up to cut k for all of a frame's tags in one batch, and their TagFeatures; with a
    tracker, records the frame's quads for the next prediction."""
    check_cut(k)
    detections, rois, roi_to_image = s1.detections, s1.rois, s1.roi_to_image
    t2 = time.perf_counter()
    if k == 0 or not detections:
        tensors = [r[None] for r in rois]
    else:
        z = net.head(rois, k)
        dt = CUTS[k].dtype(codec)
        tensors = list(np.ascontiguousarray(z.astype(dt)))
    t3 = time.perf_counter()
    tags = [
        TagFeature(
            tag_id=d.tag_id,
            decision_margin=d.decision_margin,
            hamming=d.hamming,
            corners_px=d.corners_px.astype(np.float32),
            roi_to_image=roi_to_image[i],
            tensor=tensors[i],
            edge_width_px=edge_width_px(rois[i], roi_to_image[i]),
            tracked=i >= s1.n_detected,
            proposer="tracker" if i >= s1.n_detected else d.proposer,
        )
        for i, d in enumerate(detections)
    ]
    if tracker is not None:
        # The next prediction starts from the best corners the robot has: the network's own at k = 7,
        # else stage 1's (detected) and the verified quads (tracked).
        quads = {}
        for i, d in enumerate(detections):
            if k == CUTS[-1].k:
                kp = np.asarray(tensors[i], np.float64).reshape(16, 2)
                quads[d.tag_id] = keypoints_to_image(kp, roi_to_image[i])[list(_LATTICE_CORNERS)]
            else:
                quads[d.tag_id] = np.asarray(d.corners_px, np.float64)
        tracker.update(s1.frame.seq, quads, {d.tag_id for d in detections[: s1.n_detected]})
    return tags, RobotTimings(s1.detect_secs, s1.warp_secs, t3 - t2)


def robot_step(
    frame: Frame,
    *,
    detector: Stage1,
    net: SplitNet,
    k: int,
    codec: CodecName,
    tracker: TagTracker | None = None,
) -> tuple[list[TagFeature], RobotTimings]:
    """Stage 1, ROI warping and the network up to cut k for all tags of the frame in one batch; with a
    tracker, also the tags stage 1 missed that it carries and verifies (sent with `tracked` set)."""
    check_cut(k)
    s1 = robot_stage1(frame, detector=detector, tracker=tracker)
    return robot_head(s1, net=net, k=k, codec=codec, tracker=tracker)


@dataclass(frozen=True)
class EdgeInput:
    """One Features message as the edge received it: the stamps taken where its bytes came in (edge
    clock, 0 = none) and its size on the wire."""

    features: Features
    receive_nanos: int
    previous_receive_nanos: int
    payload_bytes: int
    tag_map: TagMapFile
    min_compute_secs: float = 0.0


def edge_step(
    features: Features,
    *,
    net: SplitNet,
    tag_map: TagMapFile,
    receive_nanos: int,
    previous_receive_nanos: int,
    payload_bytes: int,
    min_compute_secs: float = 0.0,
    fusion: KeypointFusion | None = None,
    tracked_max_reprojection_px: float = 1.0,
) -> TagPoses:
    """Validate, run the tail for the announced k, map keypoints to the image, solve PnP per tag.
    `receive_nanos`/`previous_receive_nanos`: when this message and the one ahead of it on the uplink
    arrived (edge clock, 0 = none), stamped where the bytes came in. `min_compute_secs` emulates a
    slower edge: the step sleeps until it has taken at least that long. `fusion`: fit the lattice to
    the network's points and the AprilTag corners the robot sent, weighted by their calibrated sigmas
    (not for tracked tags: their corners are predictions). A tracked tag whose 16 keypoints fit a plane
    worse than `tracked_max_reprojection_px` (RMS) is dropped: the keypoint-confidence gate."""
    item = EdgeInput(features, receive_nanos, previous_receive_nanos, payload_bytes, tag_map, min_compute_secs)
    check_features(features)
    (result,) = edge_batch([item], net=net, fusion=fusion, tracked_max_reprojection_px=tracked_max_reprojection_px)
    if isinstance(result, Exception):
        raise result
    return result


MAX_TAGS_PER_FRAME: Final[int] = 256  # far more than any frame holds; a Features with more is refused
TAIL_CHUNK_TAGS: Final[int] = 16  # the tail runs on at most this many tags at once (bounded memory)


def check_features(features: Features, *, max_tags: int = MAX_TAGS_PER_FRAME) -> None:
    """What the edge can check of a Features before any network runs: its number of tags, its codec
    and every tensor's shape and dtype for its cut (FeatureShapeError)."""
    if len(features.tags) > max_tags:  # (a trial's three 200-tag messages took the edge to 4.9 GB)
        raise FeatureShapeError(f"{len(features.tags)} tags in one frame: more than {max_tags}")
    if features.codec not in ("fp16", "fp32"):
        raise FeatureShapeError(f"codec {features.codec!r} is not fp16 or fp32")
    for tag in features.tags:
        check_tensor(tag.tensor, features.split_k, features.codec)


def edge_batch(
    items: list[EdgeInput],
    *,
    net: SplitNet,
    fusion: KeypointFusion | None = None,
    tracked_max_reprojection_px: float = 1.0,
) -> list[TagPoses | FeatureShapeError]:
    """`edge_step` for several messages at once (several robots' frames that arrived together), each
    already through `check_features`: the tags of all messages cut at the same k go through one tail
    pass, then each message gets its own TagPoses, or the FeatureShapeError that refuses it alone (its
    tensors carried NaN/inf: the wire checks a tensor's framing, not its megabytes of values). Each
    message's edge time is its share of the batch's tail (by tags) plus its own PnP."""
    keypoints: list[np.ndarray | None] = [None] * len(items)
    refused: dict[int, FeatureShapeError] = {}
    share_secs = [0.0] * len(items)
    # An int8 tail quantises its input first, so NaN or inf in a cut tensor comes out as finite, plausible
    # keypoints (an all-NaN cut 3: the first keypoint at (0.203, 0.196); a trial found it in the exported
    # int8 tails, and the services' OpenVINO int8 does the same): its cut tensors are checked before it.
    check_inputs = getattr(net, "precision", None) == "int8"
    for k in sorted({i.features.split_k for i in items}):
        members = [n for n, i in enumerate(items) if i.features.split_k == k and i.features.tags]
        if check_inputs and k > 0:
            for n in members:
                bad = [t.tag_id for t in items[n].features.tags if not np.isfinite(t.tensor).all()]
                if bad:
                    refused[n] = FeatureShapeError(
                        f"tag(s) {bad} of {items[n].features.robot_id}: their cut-{k} tensors carry NaN or inf "
                        "(refused before the int8 tail, which would make finite keypoints of them)"
                    )
            members = [n for n in members if n not in refused]
        if not members:
            continue
        t0 = time.perf_counter()
        tensors = [t.tensor for n in members for t in items[n].features.tags]
        # In chunks: a batch's activations grow with its tags (a trial's 600 tags in one batch: 4.9 GB)
        chunks = [
            net.tail(np.stack([np.asarray(x, np.uint8 if k == 0 else np.float32) for x in part]), k)
            for part in (tensors[i : i + TAIL_CHUNK_TAGS] for i in range(0, len(tensors), TAIL_CHUNK_TAGS))
        ]
        out = np.concatenate(chunks)
        tail_secs = time.perf_counter() - t0
        at = 0
        for n in members:
            tags = items[n].features.tags
            kp = out[at : at + len(tags)]
            at += len(tags)
            share_secs[n] = tail_secs * len(tags) / len(tensors)
            if not np.isfinite(kp).all():
                bad = [t.tag_id for t, p in zip(tags, kp, strict=True) if not np.isfinite(p).all()]
                refused[n] = _non_finite(bad, items[n].features.robot_id, k)
            else:
                keypoints[n] = kp
    return [
        refused[n]
        if n in refused
        else _poses(
            item, keypoints[n], share_secs[n], fusion=fusion, tracked_max_reprojection_px=tracked_max_reprojection_px
        )
        for n, item in enumerate(items)
    ]


def _non_finite(tag_ids: list[int], robot_id: str, k: int) -> FeatureShapeError:
    return FeatureShapeError(
        f"non-finite keypoints for tag(s) {tag_ids} of {robot_id}: their cut-{k} tensors carry NaN or inf"
    )


def _poses(
    item: EdgeInput,
    keypoints: np.ndarray | None,
    tail_secs: float,
    *,
    fusion: KeypointFusion | None,
    tracked_max_reprojection_px: float,
) -> TagPoses:
    features, k = item.features, item.features.split_k
    t0 = time.perf_counter()
    poses: list[TagPose] = []
    for tag, kp in zip(features.tags, keypoints if keypoints is not None else [], strict=True):
        size = item.tag_map.size_of(tag.tag_id)
        kp_px = keypoints_to_image(kp, tag.roi_to_image)
        if fusion is not None and not tag.tracked:
            corners = np.asarray(tag.corners_px, np.float64)
            kp_px = fusion.apply(kp_px, corners, tag.roi_to_image, tag.edge_width_px)
        cand = solve_planar_pnp(features.intrinsics, lattice_in_tag(size), kp_px)
        if tag.tracked and cand.reprojection_error_px > tracked_max_reprojection_px:
            continue
        poses.append(
            TagPose(
                tag_id=tag.tag_id,
                tag_size_m=size,
                keypoints_px=kp_px.astype(np.float32),
                corners_px=tag.corners_px,
                camera_from_tag=cand.camera_from_tag,
                reprojection_error_px=cand.reprojection_error_px,
                alt_camera_from_tag=cand.alt_camera_from_tag,
                alt_reprojection_error_px=cand.alt_reprojection_error_px,
                tracked=tag.tracked,
                proposer=tag.proposer,
            )
        )
    edge_secs = tail_secs + time.perf_counter() - t0
    if edge_secs < item.min_compute_secs:
        time.sleep(item.min_compute_secs - edge_secs)
        edge_secs = item.min_compute_secs
    done_nanos = time.time_ns()
    receive_nanos = item.receive_nanos
    return TagPoses(
        robot_id=features.robot_id,
        seq=features.seq,
        capture_nanos=features.capture_nanos,
        split_k=k,
        payload_bytes=item.payload_bytes,
        intrinsics=features.intrinsics,
        link=LinkStamps(
            sent_nanos=features.publish_nanos,
            received_nanos=receive_nanos,
            previous_received_nanos=item.previous_receive_nanos,
        ),
        timings=HopTimings(
            robot_compute_secs=features.robot_compute_secs,
            transport_secs=(receive_nanos - features.publish_nanos) / 1e9,
            edge_compute_secs=edge_secs,
            capture_to_pose_secs=(done_nanos - features.capture_nanos) / 1e9,
        ),
        tags=poses,
    )
