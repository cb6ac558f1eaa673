"""robot_infer loop: newest frame -> stage 1 + head(k) -> Features, with the split set live over Zenoh."""

from __future__ import annotations

import contextlib
import logging
import threading
import time

import torch
import zenoh

from services.robot_infer.settings import RobotInferSettings
from shared.control.compute import ComputeEstimator, head_per_tag_ms
from shared.model.profile import calibrate_cumulative_ms, warm_up
from shared.model.weights import load_keypoint_fusion, load_model
from shared.perception.split import edge_step, robot_step
from shared.runtime.guard import InputGuard, serve_stats
from shared.transport.flow import EdgeWatch, InFlightWindow
from shared.transport.session import declare_latest_subscriber, declare_tensor_publisher, encoding_for, next_sample
from shared.transport.split_control import SplitState, serve_split
from shared.vision.detector import TagDetector
from shared.vision.tagmap import TagMapFile, load_tag_map
from shared.wire import keys
from shared.wire.codec import WireError
from shared.wire.cuts import N_CUTS
from shared.wire.messages import ComputeProfile, Features, Frame, FrameSent, SplitConfig, TagPoses, decode, encode

log = logging.getLogger(__name__)


def run(settings: RobotInferSettings, *, session: zenoh.Session, stop: threading.Event) -> None:
    """Process frames until `stop` is set."""
    torch.set_num_threads(settings.threads)
    model = load_model(settings.weights)
    fusion = load_keypoint_fusion(settings.weights) if settings.fuse_corners else None
    warm_up(model, bf16=settings.bf16)
    emulated = settings.emulated_ms_per_tag_by_k
    per_tag_ms = emulated or head_per_tag_ms(calibrate_cumulative_ms(model, bf16=settings.bf16))
    estimator = ComputeEstimator(per_tag_ms)
    detector = TagDetector(settings.detector)
    state = SplitState(SplitConfig(k=settings.split_k, codec=settings.codec, pinned=False, source="default"))
    rid = settings.robot_id
    sub = declare_latest_subscriber(session, keys.frames(rid))
    pub = declare_tensor_publisher(session, keys.features(rid), Features.SCHEMA)
    compute_pub = session.declare_publisher(keys.compute(rid, "robot"), encoding=encoding_for(ComputeProfile.SCHEMA))
    sent_pub = session.declare_publisher(keys.frame_sent(rid), encoding=encoding_for(FrameSent.SCHEMA))
    queryable = serve_split(session, keys.split(rid), state)
    window = InFlightWindow(settings.max_in_flight, timeout_secs=settings.in_flight_timeout_secs)

    def on_poses(sample: zenoh.Sample) -> None:
        # A bad TagPoses is edge_infer's problem to report; that frame's credit expires on its own.
        with contextlib.suppress(WireError):
            window.done(decode(sample.payload.to_bytes(), TagPoses).seq)

    acks = session.declare_subscriber(keys.tag_poses(rid), on_poses) if settings.max_in_flight else None
    watch = EdgeWatch(answer_timeout_secs=settings.edge_answer_timeout_secs)

    def on_edge(sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            watch.edge_up()
        else:
            watch.edge_down()
            window.clear()

    edge_token = session.liveliness().declare_subscriber(keys.alive(rid, "edge_infer"), on_edge, history=True)
    tag_map = (
        load_tag_map(settings.tag_map) if settings.tag_map else TagMapFile(default_size_m=settings.default_tag_size_m)
    )
    poses_pub = declare_tensor_publisher(session, keys.tag_poses(rid), TagPoses.SCHEMA)
    on_board_frames = 0
    token = session.liveliness().declare_token(keys.alive(rid, "robot_infer"))
    guard = InputGuard("robot_infer")
    stats = serve_stats(session, keys.stats(rid, "robot_infer"), guard)
    last_profile = 0.0

    def on_board(frame: Frame) -> None:
        """The whole chain here (k = 7, PnP) while the edge is gone: TagPoses published by the robot."""
        nonlocal on_board_frames
        tags, timings = robot_step(
            frame, detector=detector, model=model, k=N_CUTS - 1, codec="fp32", bf16=settings.bf16
        )
        now = time.time_ns()
        features = Features(
            robot_id=rid,
            seq=frame.seq,
            capture_nanos=frame.capture_nanos,
            publish_nanos=now,
            split_k=N_CUTS - 1,
            codec="fp32",
            intrinsics=frame.intrinsics,
            robot_compute_secs=timings.total_secs,
            tags=tags,
        )
        poses = edge_step(
            features,
            model=model,
            tag_map=tag_map,
            receive_nanos=now,
            previous_receive_nanos=0,
            payload_bytes=0,  # nothing crossed the link
            bf16=settings.bf16,
            fusion=fusion,
        )
        poses_pub.put(encode(poses.model_copy(update={"link": None})))  # nothing crossed the link
        on_board_frames += 1
        if on_board_frames == 1 or on_board_frames % 100 == 0:
            log.warning("edge unavailable: %d frames computed on board", on_board_frames)

    def process(payload: bytes) -> None:
        """One frame: decode, stage 1 + head(k), Features out (raises on bad input; the guard counts it)."""
        nonlocal last_profile
        frame = decode(payload, Frame, max_bytes=settings.max_payload_bytes)
        if watch.on_board(window.oldest_age_secs()):
            window.clear()
            on_board(frame)
            return
        split = state.get()  # changes apply from the next frame; each message says its k
        tags, timings = robot_step(
            frame, detector=detector, model=model, k=split.k, codec=split.codec, bf16=settings.bf16
        )
        # Emulate the robot's CPU: the latency really grows to gamma x the reference, not just a model.
        network_ms = len(tags) * per_tag_ms[split.k] if emulated else timings.head_secs * 1e3
        fixed_secs = timings.detect_secs + timings.warp_secs
        target = settings.gamma * (fixed_secs + network_ms / 1e3)
        if target > timings.total_secs:
            time.sleep(target - timings.total_secs)
        compute = max(target, timings.total_secs)
        wire = encode(
            Features(
                robot_id=rid,
                seq=frame.seq,
                capture_nanos=frame.capture_nanos,
                publish_nanos=time.time_ns(),
                split_k=split.k,
                codec=split.codec,
                intrinsics=frame.intrinsics,
                robot_compute_secs=compute,
                tags=tags,
            )
        )
        sent_nanos = time.time_ns()
        window.send(frame.seq, lambda: pub.put(wire))
        sent_pub.put(encode(FrameSent(robot_id=rid, seq=frame.seq, sent_nanos=sent_nanos, payload_bytes=len(wire))))
        estimator.observe(k=split.k, tags=len(tags), network_ms=network_ms, fixed_ms=fixed_secs * 1e3)
        if time.monotonic() - last_profile >= settings.profile_period_secs:
            last_profile = time.monotonic()
            profile = estimator.message(robot_id=rid, side="robot", stamp_nanos=time.time_ns(), factor=settings.gamma)
            compute_pub.put(encode(profile))

    log.info("robot_infer ready: k=%d codec=%s gamma=%.2f", settings.split_k, settings.codec, settings.gamma)
    try:
        # Take a frame only with a credit in hand: the ring keeps the newest one while the edge catches up.
        give_up = lambda: watch.on_board(window.oldest_age_secs())  # noqa: E731 (the edge is gone)
        while window.acquire(stop, abandon=give_up) and (sample := next_sample(sub, stop)) is not None:
            payload = sample.payload.to_bytes()
            guard.run("frame", len(payload), lambda: process(payload))  # noqa: B023 (called at once)
    finally:
        detector.close()
        token.undeclare()
        if acks is not None:
            acks.undeclare()
        queryable.undeclare()
        stats.undeclare()
        edge_token.undeclare()
        log.info(
            "robot_infer: %s, %d credits expired, %d frames on board in %d edge outages",
            guard.stats(),
            window.expired,
            on_board_frames,
            watch.outages,
        )
